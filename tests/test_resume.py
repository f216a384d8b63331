"""Resuming training from a checkpoint continues bit-for-bit: same batches (mid-epoch position of the
seeded sampler), same optimizer, scheduler and RNG states."""

from __future__ import annotations

import random

import numpy as np
import pytest
import torch
from registration_helpers import (
    RESUME_RUN,
    RESUME_STEPS,
    assert_same_weights,
    killed_and_resumed,
    last_weights,
    tiny_config,
)

from src.callbacks import RngState, set_rng_states
from src.data.dataset import EpochSampler
from src.errors import ConfigError
from src.reporting import read_csv_logs
from src.train import train

# 14 synthetic train shapes at batch 2, last.ckpt after every step (RESUME_RUN); the interrupted run is
# killed (an exception) at the start of step `stop`, as a device session's time limit would.


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
    logs = read_csv_logs(run)  # both sessions' logs are kept, one CSV version each
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


def test_resume_with_another_batch_size_is_refused(uninterrupted):
    tmp, _ = uninterrupted
    with pytest.raises(ConfigError, match="resume with the same batch size"):
        train(tiny_config(tmp, *RESUME_RUN, "data.batch_size=3", f"trainer.max_steps={RESUME_STEPS + 2}",
                          f"output_dir={tmp / 'other_batch'}", f"ckpt_path={tmp / 'full' / 'checkpoints' / 'last.ckpt'}"))


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
