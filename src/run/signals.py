"""Signals end a run in a clear, resumable state.

``SIGTERM`` (what ``timeout``, SLURM and sweep launchers send) and ``SIGINT`` (Ctrl+C):

* while training (:class:`CheckpointOnSignal`, a callback of every training Trainer) the signal only
  sets a flag; at the end of the current training step the callback writes ``last.ckpt`` at that step,
  through the trainer (the content a periodic save writes, so the run resumes from it bit-for-bit), and
  stops the run with :class:`~src.utils.errors.Interrupted`; a second signal stops it at once. A run at
  ``trainer.max_steps`` cannot be resumed (it would train nothing), so the callback writes ``last.ckpt`` at the
  step before the last too, and a signal during the last step stops the run with that one: the resumed run
  trains the last step again, then tests;
* anywhere else in a job (:func:`src.utils.interrupts.interruptible`, around every job by :func:`src.run.failures.record_failures`)
  the signal raises :class:`~src.utils.errors.Interrupted` at once.

Either way the job records ``failure.json`` (status ``interrupted``, the step and the checkpoint to resume
from) and exits with ``128 + signal`` (143 for SIGTERM, 130 for SIGINT), never 0. Loader worker processes ignore both signals (:func:`src.utils.interrupts.loader_worker_init`). Limit: under
DDP each rank stops on its own signal; a launcher that signals all ranks at once is assumed.
"""

from __future__ import annotations

import signal
from pathlib import Path
from types import FrameType
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint

from src.utils.errors import Interrupted
from src.utils.interrupts import install, restore


def _keeper(trainer: L.Trainer) -> ModelCheckpoint | None:
    """The trainer's periodic checkpoint (the ModelCheckpoint that keeps ``last.ckpt``), None without one."""
    keepers = (c for c in trainer.checkpoint_callbacks if isinstance(c, ModelCheckpoint) and c.save_last and c.dirpath)
    return next(keepers, None)


def _last_checkpoint_path(trainer: L.Trainer) -> Path:
    """Where the run keeps its ``last.ckpt``: its periodic checkpoint's, else ``<run dir>/checkpoints/last.ckpt``."""
    keeper = _keeper(trainer)
    if keeper is None:
        return Path(trainer.default_root_dir) / "checkpoints" / "last.ckpt"
    return Path(keeper.dirpath) / f"{keeper.CHECKPOINT_NAME_LAST}{keeper.FILE_EXTENSION}"


def save_last_checkpoint(trainer: L.Trainer) -> Path:
    """Write the ``last.ckpt`` of the trainer's periodic checkpoint (``<run dir>/checkpoints/last.ckpt``
    without one), recorded as that callback's own, so the resumed run overwrites it (Lightning writes a
    ``last-v1.ckpt`` beside a ``last.ckpt`` it did not write)."""
    path, keeper = _last_checkpoint_path(trainer), _keeper(trainer)
    if keeper is not None:
        keeper.last_model_path = str(path)
    trainer.save_checkpoint(path)
    return path


class CheckpointOnSignal(L.Callback):
    """On SIGTERM/SIGINT while training: ``last.ckpt`` at the end of the current step, then
    :class:`~src.utils.errors.Interrupted` (module docstring). Lightning's own SIGTERM handling (which
    ends ``fit`` with exit status 0 and no checkpoint) is replaced while training runs."""

    def __init__(self) -> None:
        self.received: int | None = None
        self._previous: dict[signal.Signals, Any] = {}
        #: The checkpoint at the step before the last (:func:`save_last_checkpoint`), once written, and its step.
        self._before_last: tuple[int, Path] | None = None

    def _note(self, signum: int, frame: FrameType | None) -> None:
        if self.received is not None:
            raise Interrupted(signum)
        self.received = signum

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.received, self._before_last = None, None
        if trainer.ckpt_path and _last_step(trainer) == trainer.global_step + 1:  # resumed with one step to go
            own = _last_checkpoint_path(trainer)
            if Path(trainer.ckpt_path).resolve() == own.resolve():
                self._before_last = (trainer.global_step, own)
        self._previous = install(self._note)

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any) -> None:
        if self.received is not None:
            self._stop(trainer)
        elif trainer.global_step + 1 == _last_step(trainer) and self._before_last is None:
            self._before_last = (trainer.global_step, save_last_checkpoint(trainer))

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        restore(self._previous)
        if self.received is not None:
            self._stop(trainer)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        restore(self._previous)

    def _stop(self, trainer: L.Trainer) -> None:
        signum, self.received = self.received, None
        if trainer.global_step == _last_step(trainer):  # trained to max_steps: resume from the step before
            if self._before_last is None:  # (a run of one step: nothing to resume; ckpt_path=last starts it again)
                raise Interrupted(signum, trainer.global_step)
            step, path = self._before_last
        else:
            step, path = trainer.global_step, save_last_checkpoint(trainer)
        raise Interrupted(signum, step, str(path))


def _last_step(trainer: L.Trainer) -> int | None:
    """The step at which the run ends (``trainer.max_steps``), None without a step budget."""
    return trainer.max_steps if trainer.max_steps is not None and trainer.max_steps > 0 else None
