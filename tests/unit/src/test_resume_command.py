"""src.run.resume: the command that resumes a run or a multirun in its own folder, and ``ckpt_path=last``."""

from __future__ import annotations

import json
import shlex

import pytest
from hydra.conf import HydraConf
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import OmegaConf

from src.run.resume import LAST, finished_record, resolve_ckpt_path, resume_command


@pytest.fixture
def hydra_job():
    """Sets the running job's Hydra config (``mode``, run dir, sweep dir, overrides) for one test."""

    def set_job(mode: RunMode, run_dir, sweep_dir, task: list[str], hydra: list[str]) -> None:
        job = OmegaConf.structured(HydraConf)
        job.mode, job.runtime.output_dir, job.sweep.dir = mode, str(run_dir), str(sweep_dir)
        job.overrides.task, job.overrides.hydra = task, hydra
        HydraConfig.instance().set_config(OmegaConf.create({"hydra": job}))

    yield set_job
    HydraConfig.instance().cfg = None


def test_a_run_resumes_in_its_folder_with_its_overrides(tmp_path, hydra_job):
    run = tmp_path / "outputs" / "run"
    hydra_job(RunMode.RUN, run, tmp_path / "unused", ["+exp=unseen_shapes", "benchmark.methods=[icp,fgr]",
                                                     "ckpt_path=old.ckpt"], [f"hydra.run.dir={run}"])
    command = shlex.split(resume_command(run / "checkpoints" / "last.ckpt"))
    assert command == ["python", "-m", "src.train", "+exp=unseen_shapes", "benchmark.methods=[icp,fgr]",
                       f"hydra.run.dir={run}", f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]


def test_a_run_started_from_weights_resumes_from_its_own(tmp_path, hydra_job):
    run = tmp_path / "outputs" / "run"
    hydra_job(RunMode.RUN, run, tmp_path / "unused", ["+exp=unseen_shapes", "init_weights=start.ckpt"],
              [f"hydra.run.dir={run}"])
    command = shlex.split(resume_command(run / "checkpoints" / "last.ckpt"))
    assert command == ["python", "-m", "src.train", "+exp=unseen_shapes", f"hydra.run.dir={run}",
                       f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"]


def test_a_job_of_a_multirun_prints_the_sweeps_command_with_ckpt_path_last(tmp_path, hydra_job):
    sweep = tmp_path / "multirun"
    sweep.mkdir()
    OmegaConf.save({"hydra": {"overrides": {"task": ["+sweep=noise", "data=synthetic", "trainer=smoke"],
                                            "hydra": ["hydra.mode=MULTIRUN", "hydra/launcher=joblib"]}}},
                   sweep / "multirun.yaml")
    hydra_job(RunMode.MULTIRUN, sweep / "3", sweep, ["data.pair.noise_sigma=0.01"], [])
    command = shlex.split(resume_command(sweep / "3" / "checkpoints" / "last.ckpt"))
    assert command == ["python", "-m", "src.train", "-m", "hydra/launcher=joblib", "+sweep=noise", "data=synthetic",
                       "trainer=smoke", f"hydra.sweep.dir={sweep}", "ckpt_path=last"]


def test_no_command_outside_a_hydra_job():
    assert resume_command("last.ckpt") is None


def _cfg(run_dir, ckpt_path, max_steps=16):
    return OmegaConf.create({"output_dir": str(run_dir), "ckpt_path": ckpt_path, "trainer": {"max_steps": max_steps}})


def test_ckpt_path_last_is_the_run_dirs_own_last_checkpoint_or_a_fresh_start(tmp_path):
    assert resolve_ckpt_path(_cfg(tmp_path, LAST)) is None  # no last.ckpt yet: step 0
    last = tmp_path / "checkpoints" / "last.ckpt"
    last.parent.mkdir()
    last.write_bytes(b"")
    assert resolve_ckpt_path(_cfg(tmp_path, LAST)) == str(last)
    assert resolve_ckpt_path(_cfg(tmp_path, "other.ckpt")) == "other.ckpt"


def test_a_finished_run_is_not_resumed_by_ckpt_path_last(tmp_path):
    (tmp_path / "metrics.json").write_text(json.dumps({"global_step": 16}))
    assert finished_record(_cfg(tmp_path, LAST)) == tmp_path / "metrics.json"
    assert finished_record(_cfg(tmp_path, LAST, max_steps=32)) is None  # a longer budget: resume
    assert finished_record(_cfg(tmp_path, "some.ckpt")) is None
