"""Resuming training from a checkpoint continues bit-for-bit: same batches (mid-epoch position of the
seeded sampler), same optimizer, scheduler and RNG states."""

from __future__ import annotations

import json
import os
import random
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from src.run.callbacks import RngState, set_rng_states
from src.data.dataset import EpochSampler
from src.utils.errors import CheckpointError, ConfigError
from src.run.reporting import read_csv_logs
from src.train import train
from tests.helpers.registration_helpers import (
    CONF,
    KillAt,
    RESUME_RUN,
    RESUME_STEPS,
    TINY,
    assert_same_weights,
    killed_and_resumed,
    last_weights,
    tiny_config,
)

# 14 synthetic train shapes at batch 2, last.ckpt after every step (RESUME_RUN); the interrupted run is
# killed (an exception) at the start of step `stop`, as a job's time limit would.


def _tag(overrides: tuple[str, ...]) -> str:
    return "".join(o.replace("=", "_") for o in overrides)


def _uninterrupted(tmp, *extra: str) -> dict[str, torch.Tensor]:
    name = "full" + _tag(extra)
    train(tiny_config(tmp, *RESUME_RUN, *extra, f"trainer.max_steps={RESUME_STEPS}", f"output_dir={tmp / name}"))
    return last_weights(tmp / name)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("resume")
    return tmp, _uninterrupted(tmp)


def _interrupted(tmp, stop: int, *extra: str) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Weights at the interruption and at the end of the run resumed in the same run directory."""
    run = tmp / f"run{stop}{_tag(extra)}"
    weights = killed_and_resumed(tmp, run, stop, *RESUME_RUN, *extra, f"trainer.max_steps={RESUME_STEPS}")
    logs = read_csv_logs(run)  # both runs' logs are kept, one CSV version each
    assert len(list((run / "csv").glob("version_*"))) == 2 and logs["step"].min() < stop <= logs["step"].max()
    assert logs["time/cpu_hours"].max() > 0  # the default callbacks' TrainingClock
    return weights


# killed mid-epoch before (3) and after (4) a validation, and at the start of the second epoch (7)
@pytest.mark.parametrize("stop", [3, 4, 7])
def test_resumed_run_equals_uninterrupted_run(uninterrupted, stop):
    tmp, expected = uninterrupted
    at_stop, got = _interrupted(tmp, stop)
    assert_same_weights(got, expected, at_stop)


def test_stochastic_network_resumes_with_its_rng_state(uninterrupted):
    """PRNet draws Gumbel noise in every training step: equal weights need the restored RNG."""
    tmp, _ = uninterrupted
    expected = _uninterrupted(tmp, "model=prnet")
    at_stop, got = _interrupted(tmp, 3, "model=prnet")
    assert_same_weights(got, expected, at_stop)


# the periodic last.ckpt off (10 minutes): the checkpoint at the signal is the signal handler's own
SIGNAL_RUN = [o for o in RESUME_RUN if "periodic_checkpoint" not in o] + [f"trainer.max_steps={RESUME_STEPS}"]


def _cli_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(CONF.parent / "tests"), os.environ.get("PYTHONPATH", "")]),
            "OMP_NUM_THREADS": "1"}


def _signalled_cli_run(tmp, run, signum: int) -> subprocess.CompletedProcess:
    """``python -m src.train`` (the real command, one loader worker) paused at the start of step 3, sent
    ``signum`` from here to its whole process group, as ``timeout`` and a terminal's Ctrl+C do."""
    ready = tmp / f"ready{signum}"
    pause = ["+callbacks.pause._target_=tests.helpers.registration_helpers.PauseAt", "+callbacks.pause.step=3",
             f"+callbacks.pause.ready={ready}"]
    command = [sys.executable, "-m", "src.train", *TINY, f"data.cache_root={tmp / 'cache'}", *SIGNAL_RUN, *pause,
               "data.num_workers=1", f"hydra.run.dir={run}"]
    process = subprocess.Popen(command, cwd=CONF.parent, env=_cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    deadline = time.monotonic() + 600
    while not ready.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    os.killpg(process.pid, signum)
    stdout, stderr = process.communicate(timeout=300)
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def _best_tracking(checkpoint) -> dict:
    """The best-checkpoint state of the ``val/score`` ModelCheckpoint saved in ``checkpoint``."""
    states = torch.load(checkpoint, weights_only=False)["callbacks"]
    return next(state for key, state in states.items() if key.startswith("ModelCheckpoint") and "val/score" in key)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_saves_the_current_step_and_its_printed_command_resumes_in_place(uninterrupted, signum):
    """SIGTERM exited 0 with no checkpoint, metrics or failure.json (a sweep counted it a success); SIGINT
    lost the steps since the last periodic checkpoint; the printed ckpt_path alone resumed into a new run dir,
    where Lightning dropped the best-checkpoint tracking."""
    tmp, expected = uninterrupted
    run = tmp / f"signal{signum}"
    result = _signalled_cli_run(tmp, run, signum)
    last = run / "checkpoints" / "last.ckpt"
    assert result.returncode == 128 + signum, result.stderr[-3000:]
    line = result.stderr.strip().splitlines()[-1]
    prefix = f"error: interrupted by {signal.Signals(signum).name} at step 4; resume it in its folder with: "
    assert line.startswith(prefix), line
    command = shlex.split(line[len(prefix):])
    assert command[:3] == ["python", "-m", "src.train"] and command[-2:] == [f"hydra.run.dir={run}", f"ckpt_path={last}"]
    failure = json.loads((run / "failure.json").read_text())
    assert failure["status"] == "interrupted" and failure["reason"] == line[len("error: "):] and failure["step"] == 4
    assert torch.load(last, weights_only=False)["global_step"] == 4  # the step of the signal, not a periodic save
    assert not read_csv_logs(run).empty  # the metrics logged so far are kept
    at_stop, tracked = last_weights(run), _best_tracking(last)
    assert Path(tracked["best_model_path"]).parent == last.parent

    resumed = subprocess.run([sys.executable, *command[1:]], cwd=CONF.parent, env=_cli_env(), capture_output=True,
                             text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "dirpath has changed" not in resumed.stderr and "is not empty" not in resumed.stderr, resumed.stderr[-3000:]
    assert_same_weights(last_weights(run), expected, at_stop)
    assert not (run / "failure.json").exists()  # the finished run removed the stale record
    assert sorted(p.name for p in last.parent.glob("last*")) == ["last.ckpt"]  # overwritten, no last-v1.ckpt
    # one best checkpoint over both runs, the best validation score of both: the tracking was kept
    logs = read_csv_logs(run)
    best = _best_tracking(last)
    assert best["best_model_score"].item() == pytest.approx(logs["val/score"].min())
    assert [p.name for p in last.parent.glob("best-*.ckpt")] == [Path(best["best_model_path"]).name]
    assert len(list((run / "csv").glob("version_*"))) == 2  # both runs in the same run dir


def test_an_interrupted_multirun_resumes_every_job_in_its_folder_with_the_printed_command(uninterrupted):
    """A sweep of two jobs (only the first paused, at step 3) stopped by SIGTERM; the printed command resumes the
    sweep in its folder: the interrupted job from its last.ckpt (bit-for-bit), the other in its own folder."""
    tmp, expected = uninterrupted
    sweep, ready = tmp / "sweep", tmp / "ready_sweep"
    pause = ["+callbacks.pause._target_=tests.helpers.registration_helpers.PauseAt", "+callbacks.pause.step=3,100",
             f"+callbacks.pause.ready={ready}"]
    command = [sys.executable, "-m", "src.train", "-m", *TINY, f"data.cache_root={tmp / 'cache'}", *SIGNAL_RUN, *pause,
               f"hydra.sweep.dir={sweep}"]
    process = subprocess.Popen(command, cwd=CONF.parent, env=_cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True)
    deadline = time.monotonic() + 600
    while not ready.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    os.killpg(process.pid, signal.SIGTERM)
    _, stderr = process.communicate(timeout=600)
    assert process.returncode != 0
    said = "resume it in its folder with: "
    line = next(line for line in stderr.splitlines() if said in line)
    resume = shlex.split(line.split(said, 1)[1])
    assert resume[:4] == ["python", "-m", "src.train", "-m"] and resume[-2:] == [f"hydra.sweep.dir={sweep}", "ckpt_path=last"]
    at_stop = last_weights(sweep / "0")

    resumed = subprocess.run([sys.executable, *resume[1:]], cwd=CONF.parent, env=_cli_env(), capture_output=True,
                             text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "dirpath has changed" not in resumed.stderr and "is not empty" not in resumed.stderr, resumed.stderr[-3000:]
    assert_same_weights(last_weights(sweep / "0"), expected, at_stop)
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1"]  # no new job folders
    for job in ("0", "1"):
        assert not (sweep / job / "failure.json").exists()
        assert torch.load(sweep / job / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == RESUME_STEPS


def test_ckpt_path_last_resumes_the_run_dirs_own_checkpoint(uninterrupted):
    """``ckpt_path=last`` (the resume command of a sweep's jobs) takes the run dir's own last.ckpt."""
    tmp, expected = uninterrupted
    run = tmp / "last"
    kill = [f"+callbacks.kill._target_={KillAt.__module__}.KillAt", "+callbacks.kill.step=3"]
    with pytest.raises(RuntimeError, match="killed at step 3"):
        train(tiny_config(tmp, *RESUME_RUN, f"trainer.max_steps={RESUME_STEPS}", *kill, f"output_dir={run}"))
    at_stop = last_weights(run)
    train(tiny_config(tmp, *RESUME_RUN, f"trainer.max_steps={RESUME_STEPS}", f"output_dir={run}", "ckpt_path=last"))
    assert_same_weights(last_weights(run), expected, at_stop)


def test_resume_with_another_batch_size_is_refused(uninterrupted):
    tmp, _ = uninterrupted
    with pytest.raises(ConfigError, match="resume with the same batch size"):
        train(tiny_config(tmp, *RESUME_RUN, "data.batch_size=3", f"trainer.max_steps={RESUME_STEPS + 2}",
                          f"output_dir={tmp / 'other_batch'}", f"ckpt_path={tmp / 'full' / 'checkpoints' / 'last.ckpt'}"))


@pytest.mark.parametrize("change, compared", [
    ("model_scale=0.125", "checkpoint width=0.0625; config width=0.125"),
    ("model.network.share_weights=true", "checkpoint share_weights=False; config share_weights=True"),
    ("model.network.num_iters=2", "checkpoint num_iters=4; config num_iters=2"),
])
def test_resume_with_another_architecture_is_refused_in_one_line(uninterrupted, change, compared):
    """A traceback of torch's load_state_dict, after config_resolved.yaml was overwritten with the new config."""
    tmp, _ = uninterrupted
    last = tmp / "full" / "checkpoints" / "last.ckpt"
    recorded = (tmp / "full" / "config_resolved.yaml").read_text()
    with pytest.raises(CheckpointError) as info:
        train(tiny_config(tmp, *RESUME_RUN, change, f"output_dir={tmp / 'full'}", f"ckpt_path={last}"))
    assert str(info.value) == (f"{last} holds another architecture than the config (model.network: {compared}): train "
                               "with the checkpoint's settings, or start a new run without it")
    assert (tmp / "full" / "config_resolved.yaml").read_text() == recorded


def test_sampler_resume_skips_the_done_part_once():
    sampler = EpochSampler(10, seed=3)
    sampler.set_epoch(2)
    full = list(sampler)
    sampler.resume_at(2, 4)
    assert list(sampler) == full[4:]
    assert list(sampler) == full  # the next pass is whole again
    with pytest.raises(ValueError, match="cannot resume 11 samples"):
        sampler.resume_at(0, 11)


def test_rng_state_round_trip():
    state = RngState().state_dict()
    drawn = (random.random(), np.random.rand(), torch.rand(3))
    set_rng_states(state)
    again = (random.random(), np.random.rand(), torch.rand(3))
    assert drawn[:2] == again[:2] and torch.equal(drawn[2], again[2])


def test_a_run_whose_data_splits_hold_lists_resumes_and_tests(tmp_path):
    """Lists in the config (here ``data.splits.val.slice``, as in every real-data experiment) reach the
    checkpoint's ``trained_on`` record as plain lists: the checkpoint loads with ``weights_only=True``,
    ``ckpt_path=last`` resumes it and the best checkpoint is tested."""
    run = tmp_path / "lists"
    overrides = [o for o in RESUME_RUN if o != "test_after_fit=false"] + ["+data.splits.val.slice=[0,1]",
                                                                          "trainer.max_steps=4", f"output_dir={run}"]
    kill = [f"+callbacks.kill._target_={KillAt.__module__}.KillAt", "+callbacks.kill.step=3"]
    with pytest.raises(RuntimeError, match="killed at step 3"):
        train(tiny_config(tmp_path, *overrides, *kill))
    last = run / "checkpoints" / "last.ckpt"
    checkpoint = torch.load(last, weights_only=True)
    assert checkpoint["trained_on"]["splits"]["val"]["slice"] == [0, 1]
    checkpoint["trained_on"] = OmegaConf.create(checkpoint["trained_on"])  # as earlier releases wrote it
    torch.save(checkpoint, last)
    metrics = train(tiny_config(tmp_path, *overrides, "ckpt_path=last"))
    assert torch.load(last, weights_only=True)["global_step"] == 4 and np.isfinite(metrics["Error(R)"])
