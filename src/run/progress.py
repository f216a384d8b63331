"""The training progress bar: Lightning's tqdm bar, counting what the run will really do.

Lightning's default bar (its rich bar when ``rich`` is installed) shows ``Epoch 0/-2`` for a step budget
(``max_epochs=-1``), the logger's version as a ``v_num`` column, and after a mid-epoch resume a total that
ignores the batches already done. This one shows ``Epoch N``, no ``v_num``, and sets each epoch's total at its
first batch: the epoch's batches, cut at the step budget, counted from the batch it starts at (a resumed
epoch starts mid-way).
"""

from __future__ import annotations

from typing import Any

import lightning as L
from lightning.pytorch.callbacks import TQDMProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import convert_inf


def epoch_total(trainer: L.Trainer, first_batch: int) -> int | float:
    """The batch count the current epoch ends at, its first batch being ``first_batch`` (0, or the batches a
    resumed epoch had done): the epoch's length, or earlier where ``max_steps`` ends the run."""
    total = trainer.num_training_batches
    if trainer.max_steps is not None and trainer.max_steps > 0:
        left = (trainer.max_steps - trainer.global_step) * trainer.accumulate_grad_batches
        total = min(total, first_batch + left)
    return total


class StepProgressBar(TQDMProgressBar):
    """Lightning's tqdm bar with the total of :func:`epoch_total` and without ``v_num`` (module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._epoch_started = False

    def on_train_epoch_start(self, trainer: L.Trainer, *args: Any) -> None:
        super().on_train_epoch_start(trainer, *args)
        self._epoch_started = True

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        if self._epoch_started and self.train_progress_bar is not None:
            self.train_progress_bar.total = convert_inf(epoch_total(trainer, batch_idx))
            self.train_progress_bar.initial = batch_idx
            self._epoch_started = False

    def get_metrics(self, trainer: L.Trainer, pl_module: L.LightningModule) -> dict[str, Any]:
        metrics = super().get_metrics(trainer, pl_module)
        metrics.pop("v_num", None)
        return metrics
