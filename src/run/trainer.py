"""The Lightning Trainer of a config: its loggers, callbacks (``conf/callbacks/``) and checkpoint writer."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import lightning as L
from lightning.pytorch.callbacks import ModelCheckpoint
from omegaconf import DictConfig

from src.run.checkpoint_io import AtomicCheckpointIO
from src.run.lightning_compat import patch_ddp_subprocess_launcher
from src.run.precision import PrecisionChoice, settle_precision
from src.run.progress import StepProgressBar
from src.run.quiet import quiet_lightning, quiet_step_budget
from src.run.signals import CheckpointOnSignal
from src.run.wandb_logging import wandb_callbacks
from src.utils.files import remove_stale_temporaries

log = logging.getLogger(__name__)

#: Callbacks of ``conf/callbacks/default.yaml`` that only a training run builds.
TRAINING_ONLY_CALLBACKS = ("checkpoint", "periodic_checkpoint", "rng_state")


def build_trainer(cfg: DictConfig, with_checkpoints: bool = True, precision: PrecisionChoice | None = None) -> L.Trainer:
    """Trainer with the configured loggers and callbacks (checkpointing only when training), in ``precision``
    (default: :func:`src.run.precision.settle_precision` of ``cfg``), kept as ``trainer.precision_choice``.

    Checkpoints are written by :class:`~src.run.checkpoint_io.AtomicCheckpointIO` (a temporary beside
    the target, then a rename); temporaries left in the checkpoint folders by killed runs are
    removed here, before training starts.
    """
    quiet_lightning()
    quiet_step_budget(cfg.trainer)
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()]
    callbacks = [
        hydra.utils.instantiate(c)
        for name, c in (cfg.get("callbacks") or {}).items()
        if with_checkpoints or name not in TRAINING_ONLY_CALLBACKS
    ] + ([CheckpointOnSignal()] if with_checkpoints else [])  # last.ckpt on SIGTERM/SIGINT (src/run/signals.py)
    for callback in callbacks:
        if isinstance(callback, ModelCheckpoint) and callback.dirpath:
            for path in remove_stale_temporaries(Path(callback.dirpath)):
                log.info("removed %s, a partial checkpoint left by a killed run", path)
    callbacks += wandb_callbacks(cfg, loggers)  # the wandb tables and 3D objects (src/run/wandb_logging.py)
    if cfg.trainer.get("enable_progress_bar", True):
        callbacks.append(StepProgressBar())  # Epoch N, no v_num, a resumed epoch's true total (src/run/progress.py)
    patch_ddp_subprocess_launcher()
    precision = precision or settle_precision(cfg)
    # plain dicts and lists (_convert_): Lightning takes +trainer.max_time={minutes: 5} as a dict, not as a DictConfig
    trainer = hydra.utils.instantiate(cfg.trainer, _convert_="partial", precision=precision.precision, logger=loggers,
                                      callbacks=callbacks, plugins=[AtomicCheckpointIO()])
    trainer.precision_choice = precision  # for the start line (src/run/info.py)
    return trainer
