"""Train a registration network, then evaluate its best checkpoint on the experiment's test set.

    python -m src.train                                   # OMNet on the embedded synthetic default
    python -m src.train +exp=unseen_categories            # the paper's experiment on ModelNet40 (once prepared)
    python -m src.train +exp=unseen_shapes data=synthetic trainer=smoke   # a few-minute CPU pipeline check
    python -m src.train ... hydra.run.dir=<run dir> ckpt_path=last        # resume a run in its own folder
    python -m src.train -m ... hydra.sweep.dir=<sweep dir> ckpt_path=last # resume every job of a multirun
    python -m src.train ... init_weights=checkpoints/<name>.ckpt          # start from a checkpoint's weights
    python -m src.train -m +sweep=noise                   # a paper study as a sweep (docs/sweeps.md)

A failing job writes ``failure.json`` into its run dir; ``on_failure=auto`` (default) then goes on
with the sweep in a multirun and re-raises in a single run (``record`` / ``raise`` to force).

Refused in one ``error:`` line before training: ModelNet40 (the paper's experiments' data) never prepared
(:func:`src.run.info.require_prepared_paper_data`); a checkpoint to resume that is missing, unreadable,
of another network or weights-only; a training set smaller than one batch; a value the network
rejects. After training: a run that made no optimisation step (nothing to test).
"""

from __future__ import annotations

import logging
import math
import re
import time
import warnings

import hydra
import lightning as L
from hydra.errors import InstantiationException
from omegaconf import DictConfig

from src.config import register_resolvers
from src.run.batch_limits import refuse_empty_limits
from src.run.checkpoint_io import check_checkpoint, read_checkpoint
from src.run.evaluated import evaluated_record, trained_weights
from src.run.failures import job_main
from src.run.info import require_prepared_paper_data
from src.run.memory import refuse_beyond_memory
from src.run.precision import settle_precision, switch_to_fp32
from src.run.recorded import (
    refuse_resume_past_budget,
    refuse_unread_overrides,
    refuse_unused_in_train,
)
from src.run.reporting import report_test_metrics, save_resolved_config
from src.run.resume import finished_record, resolve_ckpt_path, resuming_in_place
from src.run.run_dir import refuse_reused_run_dir
from src.run.trainer import build_trainer
from src.utils.errors import ConfigError

register_resolvers()
log = logging.getLogger(__name__)
# The datamodule, not the loader, carries the mid-epoch data position (RegistrationDataModule.state_dict).
warnings.filterwarnings("ignore", message="You're resuming from a checkpoint that ended before the epoch ended")


#: How PyTorch reports a tensor larger than memory, or than any memory (a huge ``model_scale``).
_TOO_LARGE = re.compile(r"can't allocate memory|Storage size calculation overflowed|out of memory")


def build_module(model_cfg: DictConfig) -> L.LightningModule:
    """The configured RegistrationModule; a value its network's constructor rejects (ValueError,
    TypeError, e.g. an unknown ``mask_mode``) or a network too large to allocate becomes one ConfigError line."""
    try:
        return hydra.utils.instantiate(model_cfg)
    except InstantiationException as err:
        cause: BaseException = err
        while cause.__cause__ is not None:  # Hydra wraps once per nested instantiation
            cause = cause.__cause__
        if isinstance(cause, (ValueError, TypeError)):
            raise ConfigError(f"model: {model_cfg.network._target_} rejects its config: {cause}") from err
        if isinstance(cause, (MemoryError, RuntimeError)) and _TOO_LARGE.search(str(cause)):
            raise ConfigError(f"model: {model_cfg.network._target_} is too large to build ({str(cause).splitlines()[0]}): "
                              "lower model_scale (its channel width)") from err
        raise


def require_one_batch(datamodule: L.LightningDataModule, trainer: L.Trainer) -> None:
    """Refuse a training set smaller than one batch per process: the loader drops incomplete
    batches (``drop_last``), so such a run would train nothing."""
    if datamodule.batch_size is None:
        raise ConfigError("data.batch_size is null (a test-only data config): set data.batch_size=N to train")
    datamodule.setup("fit")
    train_set = datamodule.datasets.get("train")
    if train_set is None:
        return  # no train split: the datamodule names it when the loader is asked for
    per_process = math.ceil(len(train_set) / trainer.world_size)
    if per_process >= datamodule.batch_size:
        return
    processes = f" per process ({trainer.world_size} processes)" if trainer.world_size > 1 else ""
    fix = f"set data.batch_size={per_process} or less, or " if per_process else ""
    raise ConfigError(
        f"the training set has {len(train_set)} shapes, fewer than one batch of data.batch_size={datamodule.batch_size}"
        f"{processes}; incomplete batches are dropped, so nothing would be trained: {fix}train on more shapes "
        "(data.splits.train)"
    )


def require_training_steps(trainer: L.Trainer, cfg: DictConfig) -> None:
    """Refuse to test a run that ended without a single optimisation step."""
    if trainer.global_step > 0:
        return
    limits = ", ".join(f"trainer.{k}={cfg.trainer.get(k)}" for k in ("max_steps", "max_epochs", "limit_train_batches"))
    raise ConfigError(f"training ended after 0 optimisation steps ({limits}): nothing was trained, so nothing is "
                      "tested; allow at least one training step")


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit, then test the best checkpoint in float32 (metrics.json: ``trained_precision``, ``test_precision``);
    returns the test metrics (empty if testing is off)."""
    refuse_unused_in_train(cfg)
    refuse_unread_overrides(cfg)
    require_prepared_paper_data(cfg)
    finished = finished_record(cfg)
    if finished is not None:
        log.info("ckpt_path=last: %s records a finished run (trained and tested); nothing to resume", finished)
        return {}
    cfg.ckpt_path = resolve_ckpt_path(cfg)
    refuse_reused_run_dir(cfg)
    if cfg.ckpt_path:
        check_checkpoint(cfg.ckpt_path, cfg.model.network._target_, resume=True, model=cfg.model)
        refuse_resume_past_budget(cfg, read_checkpoint(cfg.ckpt_path))
    if cfg.init_weights:
        check_checkpoint(cfg.init_weights, cfg.model.network._target_, model=cfg.model)
    precision = settle_precision(cfg)  # before the config is recorded: it names the precision run
    save_resolved_config(cfg)
    L.seed_everything(cfg.seed, workers=True, verbose=False)
    datamodule = hydra.utils.instantiate(cfg.data)
    module = build_module(cfg.model)
    if cfg.init_weights:
        module.load_state_dict(read_checkpoint(cfg.init_weights)["state_dict"])
    trainer = build_trainer(cfg, precision=precision)
    require_one_batch(datamodule, trainer)
    if cfg.test_after_fit:
        datamodule.setup("test")
    refuse_empty_limits(cfg, datamodule, ("train", "val", "test"))
    refuse_beyond_memory(module.network, datamodule, trainer, ("train", "val", "test"))
    start = time.perf_counter()
    with resuming_in_place(cfg.ckpt_path, cfg.output_dir):
        # weights_only=False: check_checkpoint has read the whole file already; checkpoints of earlier releases
        # hold OmegaConf lists, which torch.load(weights_only=True) refuses
        trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.ckpt_path, weights_only=False)
    fit_seconds = time.perf_counter() - start
    require_training_steps(trainer, cfg)
    if not cfg.test_after_fit:
        return {}
    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    switch_to_fp32(trainer, module)  # the checkpoint's numbers, as src.eval and the grid compute them
    trainer.test(module, datamodule=datamodule, ckpt_path=best or None, verbose=False, weights_only=False)
    metrics = module.test_results
    report_test_metrics(trainer, cfg, metrics, best, trained_weights(trainer, best), fit_seconds=round(fit_seconds, 1),
                        global_step=trainer.global_step, resumed_from=cfg.ckpt_path,
                        initialised_from=cfg.init_weights, trained_precision=precision.precision,
                        test_precision=trainer.precision, **evaluated_record(trainer))
    return metrics


main = job_main(train)

if __name__ == "__main__":
    main()
