"""Quiet output: what Lightning prints that a run does not need, silenced in one place.

Lightning's informational lines (advertising tips, "GPU available", "Seed set", a note per loader for
an explicit ``limit_*_batches``, "Restoring states ...") are dropped (a distributed run's "Initializing
distributed" lines stay): a training start prints its own
line (:mod:`src.run.info`). Its warnings stay, except a deprecation inside Lightning's own code (not
the user's to fix) and the loader-worker hint (``data.num_workers`` is chosen from the machine:
``${loader_workers:N}``, :func:`src.config.loader_workers`).
"""

from __future__ import annotations

import logging
import warnings

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
