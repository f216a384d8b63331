"""A fractional ``trainer.limit_<stage>_batches`` that selects no batch, refused before a run starts.

Lightning keeps ``int(batches * limit)`` batches of a stage for a fraction ``0 < limit < 1`` and stops with a
long report when that is 0 (e.g. ``trainer.limit_test_batches=0.001`` of 4 test batches), after training
when it is the test's: :func:`refuse_empty_limits` says it in one line, with the smallest fraction that works,
as soon as the stage's data is set up.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import lightning as L
from omegaconf import DictConfig

from src.utils.errors import ConfigError


def _batches(datamodule: L.LightningDataModule, stage: str) -> int | None:
    """The batches of ``stage`` per epoch (training drops an incomplete batch), None when it is not set up."""
    dataset = getattr(datamodule, "datasets", {}).get(stage)
    if dataset is None:
        return None
    if stage == "train":
        return len(dataset) // datamodule.batch_size
    return math.ceil(len(dataset) / datamodule.eval_batch_size)


def refuse_empty_limits(cfg: DictConfig, datamodule: L.LightningDataModule, stages: Sequence[str]) -> None:
    """ConfigError for the first of ``stages`` whose fractional ``trainer.limit_<stage>_batches`` keeps no batch."""
    for stage in stages:
        key = f"limit_{stage}_batches"
        limit = cfg.trainer.get(key)
        batches = _batches(datamodule, stage)
        if not isinstance(limit, float) or not 0 < limit < 1 or batches is None or int(batches * limit) >= 1:
            continue
        raise ConfigError(f"trainer.{key}={limit} keeps no batch: {limit} of the {batches} {stage} batches is less than "
                          f"one; use at least {1 / batches:.3g}, or a number of batches (trainer.{key}=1)")
