"""src.run.progress: the training bar says ``Epoch N`` (not ``Epoch 0/-2``), has no ``v_num`` column, and counts a
resumed epoch's batches to the right total."""

from __future__ import annotations

import io
from types import SimpleNamespace

import lightning as L
from lightning.pytorch.demos.boring_classes import BoringModel
from lightning.pytorch.loggers import CSVLogger

from src.run.progress import StepProgressBar, epoch_total


def _trainer(global_step: int, max_steps: int = 16, batches: int = 7):
    return SimpleNamespace(num_training_batches=batches, max_steps=max_steps, global_step=global_step,
                           accumulate_grad_batches=1)


def test_an_epoch_ends_at_its_length_or_at_the_step_budget():
    assert epoch_total(_trainer(0), 0) == 7
    assert epoch_total(_trainer(14), 0) == 2  # the last 2 steps of the budget
    assert epoch_total(_trainer(4, max_steps=6), 4) == 6  # resumed after batch 4: batches 5 and 6 of 6
    assert epoch_total(_trainer(4, max_steps=-1), 4) == 7  # an epoch budget


class _Bar(StepProgressBar):
    """The bar writing into a buffer, remembering what it showed at each batch."""

    def __init__(self) -> None:
        super().__init__()
        self.shown: list[tuple[str, int, int, str]] = []

    def init_train_tqdm(self):
        bar = super().init_train_tqdm()
        bar.fp = io.StringIO()
        return bar

    def on_train_batch_end(self, trainer, *args) -> None:
        super().on_train_batch_end(trainer, *args)
        bar = self.train_progress_bar
        self.shown.append((bar.desc.rstrip(": "), bar.n, bar.total, str(bar.postfix)))


def test_the_bar_of_a_step_budget_shows_epochs_and_no_version(tmp_path):
    bar = _Bar()
    trainer = L.Trainer(max_steps=6, max_epochs=-1, limit_train_batches=4, limit_val_batches=0, log_every_n_steps=1,
                        accelerator="cpu",
                        logger=CSVLogger(tmp_path), callbacks=[bar], enable_model_summary=False,
                        enable_checkpointing=False, default_root_dir=tmp_path)
    trainer.fit(BoringModel())
    assert [(desc, n, total) for desc, n, total, _ in bar.shown] == [
        ("Epoch 0", 1, 4), ("Epoch 0", 2, 4), ("Epoch 0", 3, 4), ("Epoch 0", 4, 4), ("Epoch 1", 1, 2), ("Epoch 1", 2, 2)]
    assert all("v_num" not in postfix for *_, postfix in bar.shown)
