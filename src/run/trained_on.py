"""What a checkpoint was trained on, written into the checkpoint itself, and test sets checked against it.

:class:`TrainedOn` (``conf/callbacks/default.yaml``: ``trained_on``) adds to every checkpoint ``src.train``
writes a ``trained_on`` entry: the experiment's identity (task, dataset, sampling, partial) and the data
selection (``data.splits``, ``remove_axisymmetric``). The weights file, not a card beside it, then says what
it is: a shipped card that claims another experiment is refused (:mod:`src.models.pretrained`), and
``src.eval`` refuses a test set that shares shapes with the checkpoint's training set
(:func:`refuse_test_overlap`: e.g. ``+exp=real_airplane test_size=700`` with 626 airplanes would test on all of
them, training shapes included).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import lightning as L
import numpy as np

from src.data.cache import Cache
from src.data.datamodule import select_shapes
from src.utils.config_values import plain
from src.utils.errors import ConfigError

KEY = "trained_on"
IDENTITY_KEYS = ("task", "dataset", "sampling", "partial")


def trained_on_record(identity: Mapping[str, str], splits: Mapping[str, Any], remove_axisymmetric: bool) -> dict:
    """The ``trained_on`` entry of a checkpoint."""
    return {**{k: str(identity[k]) for k in IDENTITY_KEYS}, "splits": plain(splits),
            "remove_axisymmetric": bool(remove_axisymmetric)}


class TrainedOn(L.Callback):
    """Writes :func:`trained_on_record` of the run's experiment and datamodule into every checkpoint saved."""

    def __init__(self, task: str, sampling: str, partial: str) -> None:
        self.identity = {"task": task, "sampling": sampling, "partial": partial}

    def on_save_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        datamodule = trainer.datamodule
        splits = getattr(datamodule, "splits", None)
        if splits is None:
            return
        checkpoint[KEY] = trained_on_record(self.identity | {"dataset": datamodule.dataset}, splits,
                                            getattr(datamodule, "remove_axisymmetric", True))


def training_shape_names(record: Mapping[str, Any], cache: Cache) -> set[str]:
    """The shape ids of ``cache`` that the ``trained_on`` record's training split selects (none for
    another dataset, or a record without a training split)."""
    splits = record.get("splits") or {}
    if record.get("dataset") != cache.dataset or "train" not in splits:
        return set()
    split, indices = select_shapes(cache, splits["train"], bool(record.get("remove_axisymmetric", True)), splits)
    return set(np.asarray(cache.split(split).shape_names)[indices])


def refuse_test_overlap(checkpoint: Mapping[str, Any], ckpt_path: str, datamodule: L.LightningDataModule
                        ) -> dict[str, Any]:
    """ConfigError when the test shapes of ``datamodule`` (set up for ``test``) include shapes the checkpoint
    trained on; else the record for ``metrics.json``: ``test_overlap_checked`` (False when the checkpoint
    records no training set, or the test set is not drawn from a cache)."""
    record = checkpoint.get(KEY)
    cache, test_set = getattr(datamodule, "cache", None), getattr(datamodule, "datasets", {}).get("test")
    if not isinstance(record, Mapping) or not isinstance(cache, Cache) or test_set is None:
        return {"test_overlap_checked": False}
    trained = training_shape_names(record, cache)
    split = datamodule.splits["test"]["split"]
    tested = np.asarray(cache.split(split).shape_names)[np.unique(test_set.shape_indices)]
    shared = [name for name in tested if name in trained]
    if shared:
        raise ConfigError(
            f"{len(shared)} of the {len(tested)} test shapes are shapes {ckpt_path} was trained on (first: "
            f"{shared[0]}; it trained on {len(trained)} shapes of {cache.dataset}, task {record.get('task')}): a test "
            "on them would not measure generalisation; choose a test set disjoint from its training set "
            "(e.g. the experiment's own test_size, data.splits.test)"
        )
    return {"test_overlap_checked": True}
