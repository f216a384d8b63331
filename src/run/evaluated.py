"""What a test actually ran on, read from the data rather than the experiment's name, and with which weights.

:class:`PairCounter` (``conf/callbacks/default.yaml``) counts the pairs a test evaluated (every
process, summed); :func:`evaluated_record` adds what they were: the dataset, the cache split, the
categories of the evaluated shapes (from their labels: bathtubs evaluated through ``+exp=real_airplane``
are bathtubs) and how many shapes. ``src.train`` and ``src.eval`` write it into ``metrics.json``.
:func:`trained_weights` and :func:`checkpoint_weights` say which weights were tested (``tested_weights``): a
checkpoint and its training step, or a run's last weights, and a training that stopped before its budget.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Timer

from src.data.cache import Cache
from src.run.callbacks import TrainingClock
from src.run.checkpoint_io import read_checkpoint

#: Categories named in the printed line (all of them go into metrics.json).
SHOWN_CATEGORIES = 4


class PairCounter(L.Callback):
    """The number of pairs of the last test (``pairs``), summed over processes."""

    def __init__(self) -> None:
        self.pairs = 0

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.pairs = 0

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        self.pairs += len(batch["transform_gt"])

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.pairs = int(trainer.strategy.reduce(torch.tensor(self.pairs), reduce_op="sum"))


def evaluated_record(trainer: L.Trainer) -> dict[str, Any]:
    """``test_pairs`` (scored), ``test_set_pairs`` (the test set's; fewer are scored under
    ``trainer.limit_test_batches``), ``test_dropped`` (the pairs the datamodule left out of the set, and why:
    ``{"pairs": 0}`` for a cache's), ``test_dataset`` and, for a cache datamodule, ``test_split``,
    ``test_categories`` (a list) and ``test_shapes`` of the trainer's last test (needs its :class:`PairCounter`)."""
    counter = next(c for c in trainer.callbacks if isinstance(c, PairCounter))
    datamodule = trainer.datamodule
    cache, test_set = getattr(datamodule, "cache", None), getattr(datamodule, "datasets", {}).get("test")
    record: dict[str, Any] = {"test_pairs": counter.pairs, "test_set_pairs": None if test_set is None else len(test_set),
                              "test_dropped": getattr(datamodule, "dropped", None) or {"pairs": 0},
                              "test_dataset": str(datamodule.dataset)}
    if not isinstance(cache, Cache) or test_set is None:  # (scan pairs: no cache splits)
        return record
    shapes = test_set.shape_indices[np.arange(counter.pairs) % len(test_set)]
    labels = np.unique(np.asarray(test_set.labels)[shapes])
    return record | {"test_split": datamodule.splits["test"]["split"],
                     "test_categories": [cache.categories[int(k)] for k in labels],
                     "test_shapes": int(len(np.unique(shapes)))}


def describe_evaluated(record: dict[str, Any]) -> str:
    """``32 pairs of synthetic data, split test: airplanes, cars, ... (7 categories), 32 shapes``."""
    text = f"{record['test_pairs']} pairs of {record['test_dataset']} data"
    if record.get("test_set_pairs") not in (None, record["test_pairs"]):
        text = f"{record['test_pairs']} of {record['test_set_pairs']} pairs of {record['test_dataset']} data"
    dropped = record.get("test_dropped") or {}
    if dropped.get("pairs"):
        text += f" ({dropped['pairs']} pairs left out: {dropped['reason']})"
    if "test_split" not in record:
        return text
    categories = record["test_categories"]
    shown = ", ".join(categories[:SHOWN_CATEGORIES]) + (f", ... ({len(categories)} categories)"
                                                        if len(categories) > SHOWN_CATEGORIES else "")
    return f"{text}, split {record['test_split']}: {shown}; {record['test_shapes']} shapes"


def checkpoint_weights(path: str, checkpoint: Mapping[str, Any]) -> str:
    """``<path> (step N)``: a checkpoint and the training step of its weights, recorded in it or, for the weights-only
    shipped checkpoints, in their card (``training.step_of_checkpoint``)."""
    step, card = checkpoint.get("global_step"), Path(path).with_suffix(".json")
    if step is None and card.is_file():
        step = json.loads(card.read_text()).get("training", {}).get("step_of_checkpoint")
    return f"{path} (step {step})" if step is not None else f"{path} (its training step is not recorded)"


def _stopped_early(trainer: L.Trainer) -> str:
    """``; training stopped at step N of trainer.max_steps=M (what stopped it)`` for a fit that ended before its
    budget of steps or epochs (``trainer.max_time``, ``callbacks.clock.budget_cpu_hours``, another callback); else ``""``."""
    timer = next((c for c in trainer.callbacks if isinstance(c, Timer)), None)
    clock = next((c for c in trainer.callbacks if isinstance(c, TrainingClock)), None)
    epochs_done = trainer.max_epochs not in (None, -1) and trainer.current_epoch >= trainer.max_epochs
    if timer is not None and timer.time_remaining("train") <= 0:
        cause = f"trainer.max_time reached after {timer.time_elapsed('train'):.0f} s of training"
    elif clock is not None and clock.budget_cpu_hours is not None and clock.cpu_seconds >= clock.budget_cpu_hours * 3600:
        cause = f"callbacks.clock.budget_cpu_hours={clock.budget_cpu_hours} reached"
    elif trainer.max_steps != -1 and trainer.global_step < trainer.max_steps and not epochs_done:
        cause = "stopped by a callback"
    else:
        return ""
    budget = f" of trainer.max_steps={trainer.max_steps}" if trainer.max_steps != -1 else ""
    return f"; training stopped at step {trainer.global_step}{budget} ({cause})"


def trained_weights(trainer: L.Trainer, best: str) -> str:
    """Which weights ``src.train`` tests after its fit: the checkpoint ``best`` (its step, and what selected it), or the
    last weights (why no checkpoint); with :func:`_stopped_early`'s note on how the training ended."""
    monitor = getattr(trainer.checkpoint_callback, "monitor", None)
    if best:
        how = f"selected on {monitor} ({trainer.checkpoint_callback.mode})" if monitor else "the last one kept"
        text = f"{checkpoint_weights(best, read_checkpoint(best))}, {how}, of {trainer.global_step} steps trained"
    else:
        why = f"no validation ran, so {monitor} selected no checkpoint" if monitor else "no checkpoint kept"
        text = f"the last weights, step {trainer.global_step} ({why})"
    return text + _stopped_early(trainer)
