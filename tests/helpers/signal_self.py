"""A callback that signals its own process during a chosen training step, once, as ``timeout`` or SLURM would."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import lightning as L


class SignalAt(L.Callback):
    """At the start of training step ``step``: send ``signum`` (default SIGTERM) to this process, unless the file
    ``sent`` says an earlier run already did (the resumed run, given the same overrides, is not signalled again)."""

    def __init__(self, step: int, sent: str, signum: int = signal.SIGTERM) -> None:
        self.step, self.sent, self.signum = step, Path(sent), signum

    def on_train_batch_start(self, trainer: L.Trainer, *args) -> None:
        if trainer.global_step == self.step and not self.sent.exists():
            self.sent.touch()
            os.kill(os.getpid(), self.signum)
