"""Quiet output: what Lightning prints that a run does not need, silenced in one place.

Lightning's informational lines (advertising tips, "GPU available", "Seed set", a note per loader for
an explicit ``limit_*_batches``, "Restoring states ...") are dropped (a distributed run's "Initializing
distributed" lines stay): a training start prints its own
line (:mod:`src.run.info`). Its warnings stay, except a deprecation inside Lightning's own code (not
the user's to fix), the advice on ``log_every_n_steps`` to a step-budgeted run (:func:`quiet_step_budget`) and the
loader-worker hint (``data.num_workers`` is chosen from the machine:
``${loader_workers:N}``, :func:`src.config.loader_workers`).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Mapping
from typing import Any

#: Lightning's advice for an epoch shorter than ``log_every_n_steps``: a step-budgeted run (``max_epochs=-1``) logs
#: every ``log_every_n_steps`` steps counted across epochs, so the advice does not apply to it.
STEP_BUDGET_WARNINGS = (r"The number of training batches \(\d+\) is smaller than the logging interval",)
LIGHTNING_LOGGERS = ("lightning.pytorch", "lightning.fabric")
#: Kept at INFO: each process of a distributed run says it joined ("Initializing distributed: GLOBAL_RANK: 1, ...").
KEPT_LOGGERS = ("lightning.fabric.utilities.distributed",)
IGNORED_WARNINGS = (
    r"(?s).*isinstance\(treespec, LeafSpec\)",  # torch deprecation raised inside lightning/pytorch/utilities/_pytree.py
    r"The '\w+' does not have many workers",
)


def quiet_lightning() -> None:
    """Lightning's loggers at WARNING (:data:`KEPT_LOGGERS` at INFO); the warnings of :data:`IGNORED_WARNINGS` ignored."""
    for name in LIGHTNING_LOGGERS:
        logging.getLogger(name).setLevel(logging.WARNING)
    for name in KEPT_LOGGERS:
        logging.getLogger(name).setLevel(logging.INFO)
    for message in IGNORED_WARNINGS:
        warnings.filterwarnings("ignore", message=message)


def quiet_step_budget(trainer_cfg: Mapping[str, Any]) -> None:
    """For a step-budgeted trainer config (``max_epochs: -1``, ``max_steps > 0``): :data:`STEP_BUDGET_WARNINGS` ignored."""
    max_steps = trainer_cfg.get("max_steps")
    if trainer_cfg.get("max_epochs") == -1 and max_steps is not None and max_steps > 0:
        for message in STEP_BUDGET_WARNINGS:
            warnings.filterwarnings("ignore", message=message)
