"""What a run writes and reads back: its resolved config, its CSV logs and its test metrics."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import lightning as L
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from src.run.distributed import global_rank
from src.run.evaluated import describe_evaluated
from src.run.wandb_logging import log_card
from src.utils.errors import DatasetError
from src.utils.files import disk_errors, write_atomic, write_text_atomic


def save_resolved_config(cfg: DictConfig) -> None:
    """``config_resolved.yaml`` in the run dir (``output_dir``), written by global rank 0."""
    if global_rank() != 0:
        return
    output_dir = Path(cfg.output_dir)
    with disk_errors("writing the run folder", output_dir):  # (a file there, a read-only mount: one line)
        output_dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(output_dir / "config_resolved.yaml", OmegaConf.to_yaml(cfg, resolve=True))


def read_csv_logs(run_dir: Path) -> pd.DataFrame:
    """The CSV logger's rows of a run, every version (a resumed run writes a new one) in order."""
    versions = sorted((run_dir / "csv").glob("version_*/metrics.csv"), key=lambda f: int(f.parent.name.split("_")[1]))
    files = [f for f in [run_dir / "csv" / "metrics.csv"] if f.is_file()] + versions  # (logs without versions first)
    if not files:
        return pd.DataFrame()
    return pd.concat([pd.read_csv(f) for f in files], ignore_index=True)


def write_metrics(metrics: dict[str, float], output_dir: Path, context: dict[str, Any]) -> None:
    """metrics.json (context + metrics) and metrics.csv (one tidy row per metric)."""
    output_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(output_dir / "metrics.json", json.dumps({**context, "metrics": metrics}, indent=2))
    flat = {k: ", ".join(map(str, v)) if isinstance(v, list) else v for k, v in context.items()}  # (lists: one cell)
    frame = pd.DataFrame([{**flat, "metric": k, "value": v} for k, v in metrics.items()])
    write_atomic(output_dir / "metrics.csv", lambda path: frame.to_csv(path, index=False))


def report_test_metrics(
    trainer: L.Trainer, cfg: DictConfig, metrics: dict[str, float], checkpoint: str, tested_weights: str, **extra: Any
) -> None:
    """On rank 0 (under DDP every rank holds the same synchronised metrics): write metrics.json/.csv
    into the run dir (``extra`` joins the context, e.g. training time) and print the table, under which weights were
    tested (``tested_weights``: :mod:`src.run.evaluated`)."""
    refuse_non_finite_metrics(metrics, cfg.data.dataset)
    if not trainer.is_global_zero:
        return
    context = {"task": cfg.task_name, "checkpoint": checkpoint, "tested_weights": tested_weights, "sampling": cfg.sampling,
               "partial": cfg.partial, "dataset": cfg.data.dataset, **extra}
    write_metrics(metrics, Path(cfg.output_dir), context)
    log_card(trainer, {**context, "metrics": metrics})
    tested = describe_evaluated(extra) if "test_pairs" in extra else f"{cfg.data.dataset} data"
    print(f"\nTest metrics ({cfg.task_name} protocol, {cfg.sampling}, {cfg.partial}; {tested}; Error(R) in degrees, "
          f"lower is better):\nweights: {tested_weights}\n{format_metrics(metrics)}\n"
          f"wrote {Path(cfg.output_dir) / 'metrics.json'} and metrics.csv")


def refuse_non_finite_metrics(metrics: dict[str, float], dataset: str) -> None:
    """DatasetError naming the metrics that are NaN or infinite (e.g. a Chamfer distance that overflowed):
    such a result is never written as a number."""
    bad = [f"{k}={v}" for k, v in metrics.items() if not math.isfinite(v)]
    if bad:
        raise DatasetError(f"the test gave non-finite metrics ({', '.join(bad)}) on {dataset} data: no result is "
                           "written; check the test shapes (scale, NaN) and the checkpoint's weights")


def format_metrics(metrics: dict[str, float]) -> str:
    """The paper's metrics as a two-column text table."""
    width = max(len(k) for k in metrics)
    return "\n".join(f"{k:<{width}}  {v:.4f}" for k, v in metrics.items())
