"""What ``src.train`` and ``src.eval`` share: building objects from the config and writing results."""

from __future__ import annotations

import functools
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from src.errors import UserError


def exit_on_user_error(main: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Turn a UserError into one ``error: ...`` line on stderr and exit status 2."""

    @functools.wraps(main)
    def wrapper(cfg: DictConfig) -> Any:
        try:
            return main(cfg)
        except UserError as err:
            print(f"error: {err}", file=sys.stderr)
            sys.exit(2)

    return wrapper


def build_trainer(cfg: DictConfig, with_checkpoints: bool = True) -> L.Trainer:
    """Trainer with the configured loggers and callbacks (checkpointing only when training)."""
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()]
    callbacks = [
        hydra.utils.instantiate(c)
        for name, c in (cfg.get("callbacks") or {}).items()
        if with_checkpoints or name != "checkpoint"
    ]
    return hydra.utils.instantiate(cfg.trainer, logger=loggers, callbacks=callbacks)


def save_resolved_config(cfg: DictConfig, output_dir: Path) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))


def write_metrics(metrics: dict[str, float], output_dir: Path, context: dict[str, Any]) -> pd.DataFrame:
    """metrics.json (context + metrics) and metrics.csv (one tidy row per metric)."""
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "metrics.json").write_text(json.dumps({**context, "metrics": metrics}, indent=2))
    frame = pd.DataFrame([{**context, "metric": k, "value": v} for k, v in metrics.items()])
    frame.to_csv(output_dir / "metrics.csv", index=False)
    return frame


def format_metrics(metrics: dict[str, float]) -> str:
    """The paper's metrics as a two-column text table."""
    width = max(len(k) for k in metrics)
    return "\n".join(f"{k:<{width}}  {v:.4f}" for k, v in metrics.items())
