"""A run's test error along its training, beside a classical method's row on the same test pairs.

Evaluates checkpoints a run saved on the way (``src.eval`` on an experiment's test pairs; each evaluation kept in
``--work/<checkpoint>/``, outside the repository, and reused), places each at the CPU hours the run had used at its step, and draws them
with the run's validation curve and the classical method's Error(R) from a grid's ``results.csv``: how far a budget
took a learned method on data it was never selected on, and where it stands against the classical baseline. The test
points are reported, never used to choose anything (the shipped weights are chosen on validation).

    python -m benchmarks.studies.cpu_budget.heldout_curve --run RUNS/omnet_beyond/omnet --checkpoints SNAPSHOTS/*.ckpt \\
        --eval +exp=unseen_categories data=modelnet40_npy partial=prnet --grid outputs/grid/table1_npy/results.csv \\
        --experiment unseen_categories --reference ICP --work RUNS/test_evals --out benchmarks/studies/cpu_budget/results/omnet_table1_npy_b
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.studies.cpu_budget.recipes import CPU_TRAINING_ENV
from src.metrics import ERROR_R, ERROR_T, VAL_ERROR_R
from src.run.reporting import read_csv_logs
from src.utils.errors import ConfigError, exit_code_of
from src.utils.files import read_parquet

CPU_HOURS = "time/cpu_hours"


def evaluate(checkpoint: Path, overrides: Sequence[str], work: Path) -> dict:
    """``src.eval``'s ``metrics.json`` for ``checkpoint`` on the test pairs of ``overrides``, run once in
    ``work/<checkpoint>/`` and then read."""
    record = work / checkpoint.stem / "metrics.json"
    if not record.is_file():
        command = [sys.executable, "-m", "src.eval", *overrides, f"ckpt_path={checkpoint.absolute()}",
                   "trainer.accelerator=cpu", f"hydra.run.dir={record.parent.absolute()}"]
        result = subprocess.run(command, env={**os.environ, **CPU_TRAINING_ENV}, capture_output=True, text=True)
        if result.returncode != 0 or not record.is_file():
            raise ConfigError(f"src.eval of {checkpoint} failed: {(result.stderr or result.stdout).strip().splitlines()[-1:]}")
    return json.loads(record.read_text())


def checkpoint_step(checkpoint: Path) -> int:
    """The optimiser steps the weights in ``checkpoint`` had taken."""
    import torch

    return int(torch.load(checkpoint, map_location="cpu", weights_only=False, mmap=True)["global_step"])


def cpu_hours_at(logs: pd.DataFrame, steps: Sequence[int]) -> np.ndarray:
    """The CPU hours a run had used at each of ``steps`` (interpolated between its logged rows)."""
    rows = logs.dropna(subset=[CPU_HOURS]).sort_values("step")
    if rows.empty:
        raise ConfigError("the run's logs have no CPU hours (time/cpu_hours): a run of src.train with its clock")
    return np.interp(np.asarray(steps, dtype=float), rows["step"].to_numpy(float), rows[CPU_HOURS].to_numpy(float))


def reference_error(grid_results: Path, method: str, experiment: str) -> float:
    """``method``'s Error(R) in the ``experiment`` cell of a grid's tidy results (``results.csv`` or ``.parquet``)."""
    tidy = read_parquet(grid_results) if grid_results.suffix == ".parquet" else pd.read_csv(grid_results)
    rows = tidy[(tidy["method"] == method) & (tidy["experiment"] == experiment) & (tidy["metric"] == ERROR_R)]
    if len(rows) != 1:
        raise ConfigError(f"{grid_results}: {len(rows)} Error(R) rows of {method!r} in {experiment!r} (one needed)")
    return float(rows["value"].iloc[0])


def tested_points(logs: pd.DataFrame, checkpoints: Sequence[Path], overrides: Sequence[str], work: Path) -> pd.DataFrame:
    """One row a checkpoint, by step: its step, the CPU hours its run (``logs``) had used by then, the test
    Error(R) / Error(t)."""
    steps = [checkpoint_step(path) for path in checkpoints]
    tests = [evaluate(path, overrides, work)["metrics"] for path in checkpoints]
    frame = pd.DataFrame({"checkpoint": [path.name for path in checkpoints], "step": steps,
                          "cpu_hours": cpu_hours_at(logs, steps),
                          ERROR_R: [t[ERROR_R] for t in tests], ERROR_T: [t[ERROR_T] for t in tests]})
    return frame.sort_values("step", ignore_index=True)


def plot(validation: pd.DataFrame, tests: pd.DataFrame, reference: tuple[str, float], label: str, path: Path) -> None:
    """Validation Error(R) against CPU hours, the test points, the reference's Error(R) as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    ax.plot(validation[CPU_HOURS], validation[VAL_ERROR_R], marker="o", markersize=2.5, label="validation")
    ax.plot(tests["cpu_hours"], tests[ERROR_R], marker="s", linestyle="none", color="C3", label=f"test: {label}")
    name, value = reference
    ax.axhline(value, color="grey", linestyle="--", label=f"{name} on the same test pairs ({value:.2f}°)")
    ax.set(xlabel="training CPU hours (one thread)", ylabel="Error(R) [deg], lower is better", yscale="log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.cpu_budget.heldout_curve", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="the src.train run folder (its csv logs)")
    parser.add_argument("--checkpoints", type=Path, nargs="+", required=True, help="checkpoints the run saved on the way")
    parser.add_argument("--eval", nargs="+", required=True, help="src.eval overrides that name the test pairs")
    parser.add_argument("--grid", type=Path, required=True, help="a grid's results.csv with the reference's row")
    parser.add_argument("--experiment", required=True, help="the grid's experiment of those test pairs")
    parser.add_argument("--reference", default="ICP", help="the classical method to draw (its label in the grid)")
    parser.add_argument("--work", type=Path, required=True, help="where the evaluations run (outside the repository)")
    parser.add_argument("--out", type=Path, required=True, help="the curves' CSV files and figure")
    args = parser.parse_args(argv)

    def action() -> None:
        args.out.mkdir(parents=True, exist_ok=True)
        reference = (args.reference, reference_error(args.grid, args.reference, args.experiment))
        logs = read_csv_logs(args.run)
        tests = tested_points(logs, args.checkpoints, args.eval, args.work)
        validation = logs.dropna(subset=[VAL_ERROR_R])[["step", CPU_HOURS, VAL_ERROR_R]]
        tests.to_csv(args.out / "test_curve.csv", index=False)
        validation.to_csv(args.out / "validation_curve.csv", index=False)
        plot(validation, tests, reference, args.experiment, args.out / "test_curve.png")
        print(tests.to_string(index=False))
        print(f"{reference[0]} on {args.experiment}: {reference[1]:.3f}; wrote {args.out}/test_curve.csv|png")

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
