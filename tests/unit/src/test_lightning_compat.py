"""The patch of Lightning's private ``_hydra_subprocess_cmd``: applied only to the function it was
written for, and what it builds: a DDP rank of a multirun job runs that job alone."""

from __future__ import annotations

import sys
import tomllib

import lightning
import pytest
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode

from packaging.requirements import Requirement
from packaging.version import Version

from src.run import lightning_compat
from src.run.distributed import ddp_job_command, distributed_job_scope
from tests.helpers.registration_helpers import compose_config
from tests.helpers.paths import ROOT


def test_the_installed_lightning_is_in_the_range_pyproject_requires():
    with (ROOT / "pyproject.toml").open("rb") as f:
        dependencies = tomllib.load(f)["project"]["dependencies"]
    (pinned,) = [Requirement(d).specifier for d in dependencies if Requirement(d).name == "lightning"]
    assert pinned.contains(Version(lightning.__version__)), \
        f"Lightning {lightning.__version__} is outside pyproject.toml's lightning{pinned}"
    assert lightning_compat.supported_lightning() == pinned
    assert any(s.operator == "<" for s in pinned), f"lightning{pinned}: an upper bound (the patch is checked per minor)"


def test_the_patched_function_is_the_one_the_patch_was_written_for():
    change = lightning_compat.upstream_change()
    assert change is None, (f"{change}: review src.run.distributed.ddp_job_command against the new source, then set "
                            "SOURCE_SHA256 in src/run/lightning_compat.py and the lightning range in pyproject.toml")
    assert lightning_compat.patch_ddp_subprocess_launcher()
    for launcher in lightning_compat._launchers():
        assert launcher._hydra_subprocess_cmd.func is ddp_job_command


def test_a_changed_function_is_left_to_lightning(monkeypatch):
    fabric_launcher, pytorch_launcher = lightning_compat._launchers()
    original = lightning_compat._original or fabric_launcher._hydra_subprocess_cmd
    monkeypatch.setattr(lightning_compat, "_original", None)
    for launcher in (fabric_launcher, pytorch_launcher):
        monkeypatch.setattr(launcher, "_hydra_subprocess_cmd", original)
    monkeypatch.setattr(lightning_compat, "SOURCE_SHA256", "0" * 64)
    with pytest.warns(UserWarning, match=r"changed lightning\.fabric\..*_hydra_subprocess_cmd .*left to Lightning"):
        assert not lightning_compat.patch_ddp_subprocess_launcher()
    assert fabric_launcher._hydra_subprocess_cmd is original and pytorch_launcher._hydra_subprocess_cmd is original


@pytest.fixture
def hydra_job(tmp_path, monkeypatch):
    """Sets Hydra's config of a running job (``mode`` and ``task``: its overrides) for the test."""
    monkeypatch.setattr(HydraConfig.instance(), "cfg", None)  # restored after the test
    monkeypatch.setattr(sys, "argv", ["src/train.py", "-m", "-cn", "config", "partial=prnet,rpmnet"])

    def set_job(mode: RunMode, task: list[str]) -> None:
        cfg = compose_config(*task, hydra_cfg=True)
        cfg.hydra.mode, cfg.hydra.overrides.task = mode, task
        cfg.hydra.runtime.output_dir, cfg.hydra.runtime.cwd = str(tmp_path / "job"), str(tmp_path)
        HydraConfig.instance().set_config(cfg)

    return set_job


def test_a_ddp_rank_of_a_multirun_job_runs_that_job_alone(hydra_job, tmp_path):
    hydra_job(RunMode.MULTIRUN, ["partial=rpmnet"])
    with distributed_job_scope("on_failure=record"):
        command, cwd = ddp_job_command(1, original=None)
    assert command[command.index("-cn"):] == [  # the config flags and this job's overrides, not the sweep's
        "-cn", "config", "partial=rpmnet", f'hydra.run.dir="{tmp_path / "job"}"', "hydra.job.name=ddp_rank_1",
        "hydra.output_subdir=null", "on_failure=record"]
    assert command[0] == sys.executable and "partial=prnet,rpmnet" not in command and cwd == str(tmp_path)


def test_outside_a_multirun_lightnings_command_is_kept(hydra_job):
    hydra_job(RunMode.RUN, ["partial=rpmnet"])
    assert ddp_job_command(1, original=lambda rank: ([f"rank {rank}"], "here")) == (["rank 1"], "here")
