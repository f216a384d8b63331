"""Resuming training from a checkpoint continues bit-for-bit: same batches (mid-epoch position of the
seeded sampler), same optimizer, scheduler and RNG states."""

from __future__ import annotations

import random

import lightning as L
import numpy as np
import pytest
import torch
from test_entrypoints import _cfg

from src.callbacks import RngState, set_rng_states
from src.data.dataset import EpochSampler
from src.errors import ConfigError
from src.runtime import read_csv_logs
from src.train import train

# 14 synthetic train shapes at batch 2 -> 7 batches an epoch; validation every 2 steps. last.ckpt is
# written after every step on train-batch end (the time-based checkpoint's code path); the interrupted
# run is killed (an exception) at the start of step `stop`, as a device session's time limit would.
RUN = ["+exp=unseen_shapes", "test_after_fit=false", "trainer.val_check_interval=2",
       "trainer.check_val_every_n_epoch=null", "trainer.limit_val_batches=1",
       "callbacks.periodic_checkpoint.train_time_interval=null",
       "+callbacks.periodic_checkpoint.every_n_train_steps=1", "model.lr=1e-2"]
TOTAL_STEPS = 9


def _weights(run_dir) -> dict[str, torch.Tensor]:
    return torch.load(run_dir / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]


def _tag(overrides: tuple[str, ...]) -> str:
    return "".join(o.replace("=", "_") for o in overrides)


def _uninterrupted(tmp, *extra: str) -> dict[str, torch.Tensor]:
    name = "full" + _tag(extra)
    train(_cfg(tmp, *RUN, *extra, f"trainer.max_steps={TOTAL_STEPS}", f"output_dir={tmp / name}"))
    return _weights(tmp / name)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("resume")
    return tmp, _uninterrupted(tmp)


class KillAt(L.Callback):
    """Raises at the start of training step ``step``, like a process killed there."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        if trainer.global_step == self.step:
            raise RuntimeError(f"killed at step {self.step}")


def _interrupted(tmp, stop: int, *extra: str) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    """Weights at the interruption and at the end of the run resumed in the same run directory."""
    run = tmp / f"run{stop}{_tag(extra)}"
    kill = [f"+callbacks.kill._target_={__name__}.KillAt", f"+callbacks.kill.step={stop}"]
    with pytest.raises(RuntimeError, match=f"killed at step {stop}"):
        train(_cfg(tmp, *RUN, *extra, *kill, f"trainer.max_steps={TOTAL_STEPS}", f"output_dir={run}"))
    at_stop = _weights(run)
    train(_cfg(tmp, *RUN, *extra, f"trainer.max_steps={TOTAL_STEPS}", f"output_dir={run}",
               f"ckpt_path={run / 'checkpoints' / 'last.ckpt'}"))
    logged = read_csv_logs(run)["step"].dropna()  # both sessions' logs are kept, one CSV version each
    assert len(list((run / "csv").glob("version_*"))) == 2 and logged.min() < stop <= logged.max()
    return at_stop, _weights(run)


def _assert_same(got: dict[str, torch.Tensor], expected: dict[str, torch.Tensor], at_stop: dict[str, torch.Tensor]):
    assert got.keys() == expected.keys()
    changed = [k for k in got if not torch.equal(got[k], expected[k])]
    assert not changed, f"resumed weights differ from the uninterrupted run in {changed[:5]}"
    assert any(not torch.equal(got[k], v) for k, v in at_stop.items())  # it did train further


# killed mid-epoch before (3) and after (4) a validation, and at the start of the second epoch (7)
@pytest.mark.parametrize("stop", [3, 4, 7])
def test_resumed_run_equals_uninterrupted_run(uninterrupted, stop):
    tmp, expected = uninterrupted
    at_stop, got = _interrupted(tmp, stop)
    _assert_same(got, expected, at_stop)


def test_stochastic_network_resumes_with_its_rng_state(uninterrupted):
    """PRNet draws Gumbel noise in every training step: equal weights need the restored RNG."""
    tmp, _ = uninterrupted
    expected = _uninterrupted(tmp, "model=prnet")
    at_stop, got = _interrupted(tmp, 3, "model=prnet")
    _assert_same(got, expected, at_stop)

def test_resume_with_another_batch_size_is_refused(uninterrupted):
    tmp, _ = uninterrupted
    with pytest.raises(ConfigError, match="resume with the same batch size"):
        train(_cfg(tmp, *RUN, "data.batch_size=3", f"trainer.max_steps={TOTAL_STEPS + 2}",
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
