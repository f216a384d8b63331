"""Evaluate a checkpoint on an experiment's fixed test set and print the metrics table.

    python -m src.eval +exp=unseen_categories     # the shipped checkpoint for it (checkpoints/*.json)
    python -m src.eval +exp=unseen_categories ckpt_path=outputs/.../checkpoints/best-*.ckpt
    python -m src.eval -m +sweep=overlap ckpt_path=...    # overlap ratio 1.0 -> 0.1 (docs/sweeps.md)
"""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from src.config import register_resolvers
from src.errors import CheckpointError
from src.models.module import RegistrationModule
from src.models.pretrained import find_shipped
from src.runtime import (
    build_trainer,
    exit_on_user_error,
    global_rank,
    record_failures,
    report_test_metrics,
    save_resolved_config,
)

register_resolvers()
log = logging.getLogger(__name__)


def load_checkpoint(path: str, expected_target: str) -> RegistrationModule:
    """Load a RegistrationModule checkpoint, checking it holds the configured network."""
    if not Path(path).is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        hparams = torch.load(path, map_location="cpu", weights_only=False).get("hyper_parameters", {})
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(f"{path} is not a readable PyTorch checkpoint ({type(err).__name__})") from err
    found = (hparams.get("network") or {}).get("_target_")
    if found is None:
        raise CheckpointError(f"{path} was not written by src.train (no network config inside)")
    if found != expected_target:
        raise CheckpointError(
            f"{path} holds a {found} network but the config asks for {expected_target}: pass model=<its model>"
        )
    return RegistrationModule.load_from_checkpoint(path, map_location="cpu")


def resolve_checkpoint(cfg: DictConfig) -> str:
    """``ckpt_path``, or else the shipped checkpoint trained for this experiment."""
    if cfg.ckpt_path:
        return str(cfg.ckpt_path)
    identity = {"task": cfg.task_name, "dataset": cfg.data.dataset, "sampling": cfg.sampling, "partial": cfg.partial}
    path = find_shipped(identity)
    log.info("no ckpt_path given: evaluating the shipped checkpoint %s (see %s)", path, path.with_suffix(".json").name)
    return str(path)


def evaluate(cfg: DictConfig) -> dict[str, float]:
    output_dir = Path(cfg.output_dir)
    ckpt_path = resolve_checkpoint(cfg)
    module = load_checkpoint(ckpt_path, cfg.model.network._target_)
    if global_rank() == 0:
        save_resolved_config(cfg, output_dir)
    datamodule = hydra.utils.instantiate(cfg.data)
    trainer = build_trainer(cfg, with_checkpoints=False)
    trainer.test(module, datamodule=datamodule)
    metrics = module.test_results
    report_test_metrics(trainer, cfg, metrics, ckpt_path)
    return metrics


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
@exit_on_user_error
@record_failures
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
