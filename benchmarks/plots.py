"""Figures of the paper's studies: error vs noise σ, vs overlap ratio, vs number of iterations.

    python -m benchmarks.plots multirun/sweep_noise/<time> multirun/sweep_overlap/<time> --out results/figures

Inputs: collected frames (``results.parquet`` of :mod:`benchmarks.collect`, CSV) or multirun dirs.
A figure is drawn when its x column (``noise_sigma``, ``overlap_ratio``, ``num_iters``) takes at
least two values; each method (plus sampling / partial manner / experiment where those differ)
is one line, the mean over repeated runs with their standard deviation as error bars. Written as
``<out>/error_vs_<study>.png`` and ``.pdf``.

The paper publishes these figures as images only, without numbers, so no curve of the paper is
drawn. Where one of our points is a setting the paper's tables report (e.g. σ = 0 and σ = 0.01
with N = 4 on ModelNet40, see :mod:`benchmarks.paper`), the table value is marked as "paper
(table)"; every figure states in its legend and footnote which of the two applies.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from benchmarks.paper import attach_paper, canonical_experiment, default_paper_dir, load_paper_tables  # noqa: E402
from benchmarks.tables import read_inputs  # noqa: E402


@dataclass(frozen=True)
class Figure:
    name: str
    x: str
    xlabel: str
    metrics: tuple[str, ...]
    title: str
    reverse_x: bool = False


FIGURES = {
    "noise": Figure("error_vs_noise", "noise_sigma", r"noise $\sigma$", ("Error(R)", "Error(t)"),
                    "Errors under different noise levels"),
    "overlap": Figure("error_vs_overlap", "overlap_ratio", "overlap ratio", ("Error(R)", "Error(t)"),
                      "Isotropic errors of different overlapping ratios", reverse_x=True),
    "iterations": Figure("error_vs_iterations", "num_iters", "iterations N",
                         ("RMSE(R)", "MAE(R)", "Error(R)", "RMSE(t)", "MAE(t)", "Error(t)"),
                         "Anisotropic and isotropic errors over registration iterations"),
}
NO_PAPER_NUMBERS = "paper: no published numbers for this figure"


def _line_columns(frame: pd.DataFrame, x: str) -> list[str]:
    """Columns whose values tell lines apart: the method, and sampling / partial / experiment /
    dataset where they vary (the noise study's experiment only gains a ``_noise`` suffix)."""
    columns = ["method"]
    for col in ("sampling", "partial", "experiment_base", "dataset"):
        if col in frame and frame[col].nunique(dropna=True) > 1:
            columns.append(col)
    for col in ("sweep", "task"):  # one method swept in several sweeps: one line per sweep
        if col in frame:
            if (frame.groupby(columns, dropna=False)[col].nunique() > 1).any():
                columns.append(col)
            break
    return columns


def figure_data(frame: pd.DataFrame, figure: Figure, paper: pd.DataFrame | None) -> pd.DataFrame:
    """Mean, std and count per (line, x, metric), with the paper's table value where it applies."""
    if figure.x not in frame.columns:
        return pd.DataFrame()
    data = frame[frame["metric"].isin(figure.metrics) & frame[figure.x].notna()].copy()
    study = next((c for c in ("sweep", "task") if c in data.columns), None)
    if study is not None:  # only the sweeps that vary x (a noise sweep's N=4 is no iterations study)
        data = data[data.groupby(study, dropna=False)[figure.x].transform("nunique") >= 2]
    if data.empty or data[figure.x].nunique() < 2:
        return pd.DataFrame()
    data["experiment"] = data["experiment"].map(canonical_experiment)
    data["experiment_base"] = data["experiment"].astype(str).str.replace(r"_noise$", "", regex=True)
    keys = [c for c in ("method", "experiment", "experiment_base", "sampling", "partial", "dataset",
                        "noise_sigma", "overlap_ratio", "num_iters", study) if c and c in data.columns]
    keys = list(dict.fromkeys([*keys, figure.x, "metric"]))
    stats = data.groupby(keys, dropna=False)["value"].agg(["mean", "std", "count"]).reset_index()
    stats = stats.rename(columns={"mean": "value"})
    if paper is not None and {"experiment", "sampling"} <= set(stats.columns):
        stats = attach_paper(stats, paper)
    else:
        stats["paper_value"] = math.nan
        stats["paper_table"] = None
    return stats


def plot_figure(stats: pd.DataFrame, figure: Figure, out_dir: Path) -> list[Path]:
    metrics = [m for m in figure.metrics if m in set(stats["metric"])]
    cols = min(3, len(metrics))
    rows = math.ceil(len(metrics) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows + 0.6), squeeze=False)
    line_cols = _line_columns(stats, figure.x)
    groups = list(stats.groupby(line_cols, dropna=False, sort=True))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    has_paper = bool(stats["paper_value"].notna().any())
    for ax, metric in zip(axes.flat, metrics):
        for i, (key, group) in enumerate(groups):
            key = key if isinstance(key, tuple) else (key,)
            label = str(key[0]) + (f" ({', '.join(str(k) for k in key[1:])})" if len(key) > 1 else "")
            part = group[group["metric"] == metric].sort_values(figure.x)
            if part.empty:
                continue
            color = colors[i % len(colors)]
            ax.errorbar(part[figure.x], part["value"], yerr=part["std"].fillna(0.0).where(part["count"] > 1, 0.0),
                        marker="o", ms=4, lw=1.5, capsize=2, color=color, label=label)
            published = part[part["paper_value"].notna()]
            if not published.empty:
                ax.scatter(published[figure.x], published["paper_value"], marker="*", s=90, color=color,
                           edgecolor="black", linewidth=0.6, zorder=5, label=f"{label}: paper (table)")
        ax.set_title(metric)
        ax.set_xlabel(figure.xlabel)
        ax.grid(alpha=0.3)
        if figure.reverse_x:
            ax.invert_xaxis()
        if figure.x == "num_iters":
            ax.xaxis.get_major_locator().set_params(integer=True)
    for ax in list(axes.flat)[len(metrics):]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    if not has_paper:
        handles.append(Line2D([], [], linestyle="none", marker=""))
        labels.append(NO_PAPER_NUMBERS)
    axes.flat[0].legend(handles, labels, fontsize=7, loc="best")
    note = ("Stars: the paper's table values at the same setting; the paper publishes this figure without numbers."
            if has_paper else "The paper publishes this figure without numbers: no paper values are shown.")
    if "dataset" in stats and (stats["dataset"].astype(str) == "synthetic").any():
        note += " Synthetic data, not ModelNet40."
    fig.suptitle(figure.title)
    fig.text(0.5, 0.01, note, ha="center", va="bottom", fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 0.97))
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{figure.name}.png", out_dir / f"{figure.name}.pdf"]
    for path in paths:
        fig.savefig(path, dpi=150)
    plt.close(fig)
    return paths


def make_figures(frame: pd.DataFrame, out_dir: Path, studies: Sequence[str] = tuple(FIGURES),
                 paper: pd.DataFrame | None = None) -> tuple[list[Path], list[str]]:
    """Draw every study of ``studies`` the frame has data for; (files written, notes)."""
    written, notes = [], []
    for study in studies:
        figure = FIGURES[study]
        stats = figure_data(frame, figure, paper)
        if stats.empty:
            notes.append(f"{study}: skipped (column {figure.x!r} has fewer than two values)")
            continue
        written += plot_figure(stats, figure, out_dir)
        if stats["paper_value"].notna().any():
            notes.append(f"{study}: paper table values marked at {int(stats['paper_value'].notna().sum())} points")
        else:
            notes.append(f"{study}: {NO_PAPER_NUMBERS}")
    return written, notes


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.plots", description=__doc__.split("\n\n")[0])
    parser.add_argument("inputs", nargs="+", help="collected frames (.parquet/.csv) or multirun dirs")
    parser.add_argument("--out", type=Path, default=Path("results/figures"))
    parser.add_argument("--figures", default=",".join(FIGURES), help=f"comma-separated, from {', '.join(FIGURES)}")
    parser.add_argument("--paper-dir", type=Path, default=None, help=f"paper CSV folder (default {default_paper_dir()})")
    parser.add_argument("--no-paper", action="store_true", help="do not look up the paper's table values")
    args = parser.parse_args(argv)
    studies = [s.strip() for s in args.figures.split(",") if s.strip()]
    unknown = [s for s in studies if s not in FIGURES]
    if unknown:
        print(f"error: unknown figure(s) {unknown}; choose from {list(FIGURES)}", file=sys.stderr)
        return 2
    try:
        frame = read_inputs(args.inputs)
        paper = None
        if not args.no_paper:
            try:
                paper = load_paper_tables(args.paper_dir)
            except FileNotFoundError as err:
                print(f"note: {err}; plotting without paper values", file=sys.stderr)
        written, notes = make_figures(frame, args.out, studies, paper)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for note in notes:
        print(note)
    if not written:
        print("error: nothing to plot (no study column varies in the input)", file=sys.stderr)
        return 2
    print("wrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
