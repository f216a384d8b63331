"""Reporting a run of the grid: the console summary and table.md / table.tex in the paper's layout."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig

from benchmarks.grid.run import GridResult
from src.metrics import SUMMARY_METRICS


def summary_table(tidy, metrics: Sequence[str] = SUMMARY_METRICS) -> str:
    """A compact plain-text view: one row per cell, a few metrics (headers with units and ↓), failures and time
    per pair."""
    import pandas as pd

    from benchmarks.tables.render import metric_header

    wide = tidy.pivot_table(index=["partial", "experiment", "sampling", "method"], columns="metric", values="value",
                            aggfunc="first", sort=False)
    extra = tidy.groupby(["partial", "experiment", "sampling", "method"], sort=False)[["n_pairs", "n_failed", "seconds_per_pair"]].first()
    table = wide[[m for m in metrics if m in wide.columns]].join(extra)
    table["ms/pair"] = (table.pop("seconds_per_pair") * 1000).round(1)
    table = table.rename(columns={m: metric_header(m) for m in [*metrics, "ms/pair"]})
    with pd.option_context("display.width", 200, "display.max_rows", 500, "display.float_format", "{:.4f}".format):
        return table.reset_index().to_string(index=False)


def write_tables(tidy, output_dir: Path, paper: bool = True, caption: str | None = None) -> list[Path]:
    """table.md / table.tex in the paper's Table-1 layout via benchmarks.tables (if available), ``caption`` (the
    grid's own words: data, budget, which model each row is) before the layout's."""
    try:
        from benchmarks.tables import render as tables
    except ImportError:  # pragma: no cover - tables module absent
        return []
    paper_frame = None
    if paper:
        try:
            from benchmarks.tables.paper import load_paper_tables

            paper_frame = load_paper_tables()
        except (ImportError, FileNotFoundError):
            paper_frame = None
    try:
        table = tables.build_table(tidy, "table1", paper=paper_frame, caption=caption)
    except ValueError as err:
        print(f"note: no LaTeX/Markdown table ({err})", file=sys.stderr)
        return []
    written = [output_dir / "table.md", output_dir / "table.tex"]
    written[0].write_text(tables.to_markdown(table))
    written[1].write_text(tables.to_latex(table))
    return written


def write_category_figures(result: GridResult, cfg: DictConfig) -> list[Path]:
    """For each experiment of ``benchmark.by_category`` that the grid ran, per sampling and partial manner, every
    method's error per shape category: a figure and a table (:func:`benchmarks.plots.sweep.write_categories`)."""
    from benchmarks.plots.sweep import write_categories
    from benchmarks.tables.paper import canonical_experiment

    wanted = {canonical_experiment(e) for e in cfg.benchmark.get("by_category") or ()}
    cells = result.tidy[["experiment", "sampling", "partial"]].drop_duplicates()
    absent = sorted(wanted - {canonical_experiment(e) for e in cells["experiment"]})
    if absent:
        print(f"note: benchmark.by_category names {', '.join(absent)}, which this grid did not run: no figure for it")
    written: list[Path] = []
    for experiment, sampling, partial in cells.itertuples(index=False):
        if canonical_experiment(experiment) in wanted:
            written += write_categories(result.output_dir, experiment, sampling.lower(), partial,
                                        overrides=list(cfg.benchmark.overrides))[1]
    return written


def report(result: GridResult, cfg: DictConfig) -> None:
    print(f"\nComparison grid '{cfg.benchmark.name}': {len(result.cells)} cells "
          f"({result.computed} computed, {result.reused} reused) in {result.output_dir}")
    datasets = sorted(result.tidy["dataset"].unique())
    if "synthetic" in datasets:
        print("dataset: synthetic (procedural CAD-like shapes) - these are NOT ModelNet40 results")
    print(summary_table(result.tidy))
    failed = [c for c in result.cells if c["n_failed"]]
    for c in failed:
        reasons = "; ".join(f"{k} (x{v})" for k, v in list(c.get("failure_reasons", {}).items())[:3])
        print(f"failed pairs: {c['method']}/{c['experiment']}/{c['sampling']}/{c['partial']}: "
              f"{c['n_failed']} of {c['n_pairs']} (counted with the identity): {reasons}")
    for note in result.skipped:
        print(f"note: {note}")
    written = write_tables(result.tidy, result.output_dir, paper=bool(cfg.get("paper", True)),
                           caption=cfg.benchmark.get("caption"))
    if written:
        print("\n" + written[0].read_text())
    written += write_category_figures(result, cfg)
    print("wrote " + ", ".join(str(p) for p in [result.output_dir / "results.parquet", result.output_dir / "results.csv",
                                                result.output_dir / "pairs.parquet", *written]))
