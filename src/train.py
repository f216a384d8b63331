"""Train a registration network, then evaluate its best checkpoint on the experiment's test set.

    python -m src.train                                   # OMNet on the embedded synthetic default
    python -m src.train +exp=unseen_categories data=modelnet40   # the paper's experiment on ModelNet40
    python -m src.train +exp=unseen_shapes trainer=smoke  # 2-minute CPU demo on the synthetic default
    python -m src.train ... ckpt_path=outputs/.../checkpoints/last.ckpt   # resume
    python -m src.train -m +sweep=noise                   # a paper study as a sweep (docs/sweeps.md)

A failing job writes ``failure.json`` into its run dir; ``on_failure=auto`` (default) then goes on
with the sweep in a multirun and re-raises in a single run (``record`` / ``raise`` to force).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import hydra
import lightning as L
from omegaconf import DictConfig

from src.config import register_resolvers
from src.errors import CheckpointError
from src.runtime import (
    build_trainer,
    exit_on_user_error,
    global_rank,
    record_failures,
    report_test_metrics,
    save_resolved_config,
)

register_resolvers()
# The datamodule, not the loader, carries the mid-epoch data position (RegistrationDataModule.state_dict).
warnings.filterwarnings("ignore", message="You're resuming from a checkpoint that ended before the epoch ended")


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit, then test the best checkpoint; returns the test metrics (empty if testing is off)."""
    output_dir = Path(cfg.output_dir)
    if global_rank() == 0:
        save_resolved_config(cfg, output_dir)
    L.seed_everything(cfg.seed, workers=True)
    datamodule = hydra.utils.instantiate(cfg.data)
    module = hydra.utils.instantiate(cfg.model)
    trainer = build_trainer(cfg)
    if cfg.ckpt_path and not Path(cfg.ckpt_path).is_file():
        raise CheckpointError(f"cannot resume: checkpoint {cfg.ckpt_path} does not exist")
    start = time.perf_counter()
    trainer.fit(module, datamodule=datamodule, ckpt_path=cfg.ckpt_path)
    fit_seconds = time.perf_counter() - start
    if not cfg.test_after_fit:
        return {}
    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    trainer.test(module, datamodule=datamodule, ckpt_path=best or None)
    metrics = module.test_results
    report_test_metrics(trainer, cfg, metrics, best, fit_seconds=round(fit_seconds, 1),
                        global_step=trainer.global_step, resumed_from=cfg.ckpt_path)
    return metrics


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
@exit_on_user_error
@record_failures
def main(cfg: DictConfig) -> None:
    train(cfg)


if __name__ == "__main__":
    main()
