"""Interrupt signals (SIGINT, SIGTERM) of a process: handlers set and restored, a block in which they raise
:class:`~src.utils.errors.Interrupted`, and the loader workers that ignore them (the main process shuts them down).
How a run turns them into a resumable stop: :mod:`src.run.signals`."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

from lightning.fabric.utilities.seed import pl_worker_init_function

from src.utils.errors import Interrupted

INTERRUPT_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)
Handler = Callable[[int, FrameType | None], Any]


def install(handler: Handler) -> dict[signal.Signals, Any]:
    """``handler`` for :data:`INTERRUPT_SIGNALS` in this process only (a forked child ignores them);
    returns the handlers it replaced (none outside the main thread, where signals cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    owner = os.getpid()

    def in_owner(signum: int, frame: FrameType | None) -> None:
        if os.getpid() == owner:
            handler(signum, frame)

    return {signum: signal.signal(signum, in_owner) for signum in INTERRUPT_SIGNALS}


def restore(previous: dict[signal.Signals, Any]) -> None:
    """Put back the handlers :func:`install` replaced."""
    for signum, handler in previous.items():
        signal.signal(signum, signal.SIG_DFL if handler is None else handler)


def loader_worker_init(worker_id: int, rank: int) -> None:
    """``worker_init_fn`` of the loaders: the worker ignores SIGTERM/SIGINT (torch's workers die on
    SIGTERM, which ``timeout`` sends to the whole process group, and the main process would then stop
    mid-step), then Lightning's worker seeding as ``seed_everything(workers=True)`` asks for it."""
    for signum in INTERRUPT_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    if int(os.environ.get("PL_SEED_WORKERS", 0)):
        pl_worker_init_function(worker_id, rank)


def _raise(signum: int, frame: FrameType | None) -> None:
    raise Interrupted(signum)


@contextmanager
def interruptible() -> Iterator[None]:
    """Within the block, SIGTERM and SIGINT raise :class:`~src.utils.errors.Interrupted`."""
    previous = install(_raise)
    try:
        yield
    finally:
        restore(previous)
