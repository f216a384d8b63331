"""What a test actually ran on, read from the data rather than the experiment's name.

:class:`PairCounter` (``conf/callbacks/default.yaml``) counts the pairs a test evaluated (every
process, summed); :func:`evaluated_record` adds what they were: the dataset, the cache split, the
categories of the evaluated shapes (from their labels: bathtubs evaluated through ``+exp=real_airplane``
are bathtubs) and how many shapes. ``src.train`` and ``src.eval`` write it into ``metrics.json``.
"""

from __future__ import annotations

from typing import Any

import lightning as L
import numpy as np
import torch

from src.data.cache import Cache

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
