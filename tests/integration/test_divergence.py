"""A run whose loss stops being finite ends in one line, before its optimiser step writes NaN into the weights:
a PRNet run on the GPU trained 400 steps on a NaN loss, logging NaN, until its time was up (benchmarks/results/
gpu_study.md)."""

from __future__ import annotations

import lightning as L
import pytest
import torch

from src.utils.errors import DivergenceError
from src.train import train
from tests.helpers.registration_helpers import last_weights, tiny_config

POISONED_STEP = 3


class NanInputAt(L.Callback):
    """From training step ``step`` on, one source coordinate of every batch is NaN (a loss that turns NaN)."""

    def __init__(self, step: int) -> None:
        self.step = step

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch, batch_idx: int) -> None:
        if trainer.global_step >= self.step:
            batch["points_src"][0, 0, 0] = float("nan")


def test_a_non_finite_loss_stops_training_in_one_line_and_keeps_the_weights_finite(tmp_path):
    run = tmp_path / "run"
    cfg = tiny_config(tmp_path, "+exp=unseen_shapes", "test_after_fit=false", "trainer.max_steps=8",
                      "trainer.check_val_every_n_epoch=null", "trainer.val_check_interval=100",
                      "callbacks.periodic_checkpoint.train_time_interval=null",
                      "+callbacks.periodic_checkpoint.every_n_train_steps=1",
                      f"+callbacks.nan._target_={__name__}.NanInputAt", f"+callbacks.nan.step={POISONED_STEP}")
    with pytest.raises(DivergenceError) as error:
        train(cfg)
    message = str(error.value)
    assert message.startswith(f"training diverged at step {POISONED_STEP}: the loss is not finite (loss=nan")
    assert "lower model.lr" in message and "\n" not in message
    weights = last_weights(run)  # the checkpoint of the last good step stays, and holds no NaN
    assert torch.load(run / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == POISONED_STEP
    assert all(torch.isfinite(w).all() for w in weights.values() if w.is_floating_point())
