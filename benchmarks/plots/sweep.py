"""Figures of the paper's studies: error vs noise σ, vs overlap ratio, vs number of iterations; and the
real scan pairs' errors against their true overlap.

    python -m benchmarks.plots multirun/sweep_noise/<time> multirun/sweep_overlap/<time> [--out DIR]
    python -m benchmarks.plots scan-pairs outputs/grid/scan_pairs [the grid's data.* overrides] [--out DIR]

Inputs: collected frames (``results.parquet`` of :mod:`benchmarks.collect`, CSV) or multirun dirs.
A figure is drawn when its x column (``noise_sigma``, ``overlap_ratio``, ``num_iters``) takes at
least two values; each method (plus sampling / partial manner / experiment where those differ)
is one line, the mean over repeated runs with their standard deviation as error bars (drawn, and in the legend,
only where a point has several runs). Each y axis names its unit and direction (↓: lower is better), the x axis
its unit. A job of a multirun that failed or is missing is named in the footnote (it is absent from the curves);
a job trained with ``trainer=smoke`` (a few steps of a reduced-width network) is a pipeline check: its line is
dashed and labelled so. Written as ``<out>/error_vs_<study>.png`` and ``.pdf`` (default ``<out>``: beside the
first input).

``scan-pairs`` reads a ``+benchmark=scan_pairs`` grid (:mod:`benchmarks.grid`): every method's per-pair
Error(R) against the pair's true overlap (``scan_pairs_error_vs_overlap.png``) and the errors binned by
overlap as Markdown (``scan_pairs_by_overlap.md``, also printed).

The paper publishes these figures as images only, without numbers, so no curve of the paper is
drawn. Where one of our points is a setting the paper's tables report (e.g. σ = 0 and σ = 0.01
with N = 4 on ModelNet40, see :mod:`benchmarks.tables.paper`), the table value is marked as "paper
(table)"; every figure states in its legend and footnote which of the two applies.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
import yaml  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from baselines.methods import display_name  # noqa: E402
from benchmarks.tables.paper import attach_paper, canonical_experiment, default_paper_dir, load_paper_tables  # noqa: E402
from benchmarks.tables.render import HIGHER_IS_BETTER, REFERENCE, default_out, read_inputs  # noqa: E402
from src.utils.errors import UserError  # noqa: E402
from src.utils.files import read_parquet  # noqa: E402
from src.metrics import ERROR_R, ERROR_T, MAE_R, MAE_T, RMSE_R, RMSE_T, SUCCESS_THRESHOLDS  # noqa: E402


@dataclass(frozen=True)
class Figure:
    name: str
    x: str
    xlabel: str
    metrics: tuple[str, ...]
    title: str
    reverse_x: bool = False


FIGURES = {
    "noise": Figure("error_vs_noise", "noise_sigma", r"noise $\sigma$ (the shapes' units; unit sphere)", (ERROR_R, ERROR_T),
                    "Errors under different noise levels"),
    "overlap": Figure("error_vs_overlap", "overlap_ratio", "overlap ratio (fraction of points kept)", (ERROR_R, ERROR_T),
                      "Isotropic errors of different overlapping ratios", reverse_x=True),
    "iterations": Figure("error_vs_iterations", "num_iters", "iterations N (count)",
                         (RMSE_R, MAE_R, ERROR_R, RMSE_T, MAE_T, ERROR_T),
                         "Anisotropic and isotropic errors over registration iterations"),
}
NO_PAPER_NUMBERS = "paper: no published numbers for this figure"
#: The ``trainer`` choice of a pipeline check (conf/trainer/smoke.yaml): a few steps, for checking, not for results.
PIPELINE_CHECK_TRAINER = "smoke"
PIPELINE_CHECK = "pipeline check, trainer=smoke"


def is_pipeline_check(run_dir: str | Path | None) -> bool:
    """Whether the job in ``run_dir`` was trained with ``trainer=smoke`` (its ``.hydra/hydra.yaml``)."""
    if run_dir is None or (isinstance(run_dir, float) and math.isnan(run_dir)):
        return False
    hydra_file = Path(run_dir) / ".hydra" / "hydra.yaml"
    if not hydra_file.is_file():
        return False
    choices = (yaml.safe_load(hydra_file.read_text()) or {}).get("hydra", {}).get("runtime", {}).get("choices", {})
    return choices.get("trainer") == PIPELINE_CHECK_TRAINER


def read_sweeps(paths: Sequence[str | Path]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The tidy frame of ``paths`` (:func:`benchmarks.tables.render.read_inputs`) and the jobs that left no metrics
    (failed or missing): from a multirun dir's collection, or the ``jobs.csv`` beside a collected frame."""
    from benchmarks.collect import collect

    failed = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            failed.append(collect(path).failures)
        elif (path.parent / "jobs.csv").is_file():
            jobs = pd.read_csv(path.parent / "jobs.csv")
            failed.append(jobs[jobs["status"] != "ok"])
    failed = [f for f in failed if not f.empty]
    return read_inputs(paths), pd.concat(failed, ignore_index=True) if failed else pd.DataFrame()


def failed_note(failed: pd.DataFrame, shown: int = 3) -> str | None:
    """The footnote naming the jobs absent from the curves (None when every job has metrics)."""
    if failed.empty:
        return None
    named = "; ".join(f"{row.get('sweep', '')}/{row['job']}: {row['status']} ({str(row['reason'])[:80]})"
                      for _, row in failed.head(shown).iterrows())
    more = f"; and {len(failed) - shown} more" if len(failed) > shown else ""
    return f"{len(failed)} job(s) absent from the curves: {named}{more}."


def _line_columns(frame: pd.DataFrame, x: str) -> list[str]:
    """Columns whose values tell lines apart: the method, and sampling / partial / experiment /
    dataset where they vary (the noise study's experiment only gains a ``_noise`` suffix)."""
    columns = ["method"]
    for col in ("sampling", "partial", "experiment_base", "dataset", "pipeline_check"):
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
    runs = data["run_dir"] if "run_dir" in data.columns else pd.Series(None, index=data.index, dtype=object)
    checks = {run: is_pipeline_check(run) for run in runs.dropna().unique()}
    data["pipeline_check"] = runs.map(lambda run: checks.get(run, False)).astype(bool)
    keys = [c for c in ("method", "experiment", "experiment_base", "sampling", "partial", "dataset",
                        "noise_sigma", "overlap_ratio", "num_iters", study, "pipeline_check") if c and c in data.columns]
    keys = list(dict.fromkeys([*keys, figure.x, "metric"]))
    stats = data.groupby(keys, dropna=False)["value"].agg(["mean", "std", "count"]).reset_index()
    stats = stats.rename(columns={"mean": "value"})
    if paper is not None and {"experiment", "sampling"} <= set(stats.columns):
        stats = attach_paper(stats, paper)
    else:
        stats["paper_value"] = math.nan
        stats["paper_table"] = None
    return stats


def axis_label(metric: str) -> str:
    """A metric's axis label with its unit and direction, e.g. ``Error(R) (degrees), lower is better ↓``."""
    unit = "degrees" if metric.endswith("(R)") else "shapes' units" if metric.endswith("(t)") else None
    direction = "higher is better ↑" if metric in HIGHER_IS_BETTER else "lower is better ↓"
    return f"{metric}{f' ({unit})' if unit else ''}, {direction}"


def _line_label(line_cols: list[str], key: tuple, checked: bool) -> str:
    """A line's legend label: the method, then what tells it apart; a pipeline check says so."""
    details = [str(k) for col, k in zip(line_cols[1:], key[1:]) if col != "pipeline_check"]
    label = str(key[0]) + (f" ({', '.join(details)})" if details else "")
    return f"{label} [{PIPELINE_CHECK}]" if checked else label


def plot_figure(stats: pd.DataFrame, figure: Figure, out_dir: Path, failed: str | None = None) -> list[Path]:
    """The figure of ``stats`` (:func:`figure_data`) as PNG and PDF in ``out_dir``; ``failed``: a footnote on the
    jobs absent from it."""
    fig = draw_figure(stats, figure, failed)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f"{figure.name}.png", out_dir / f"{figure.name}.pdf"]
    for path in paths:
        fig.savefig(path, dpi=150)
    plt.close(fig)
    return paths


def draw_figure(stats: pd.DataFrame, figure: Figure, failed: str | None = None) -> plt.Figure:
    """The matplotlib figure of :func:`plot_figure` (one panel per metric)."""
    metrics = [m for m in figure.metrics if m in set(stats["metric"])]
    cols = min(3, len(metrics))
    rows = math.ceil(len(metrics) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows + 0.6), squeeze=False)
    line_cols = _line_columns(stats, figure.x)
    groups = list(stats.groupby(line_cols, dropna=False, sort=True))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    has_paper = bool(stats["paper_value"].notna().any())
    has_spread = bool((stats["count"] > 1).any())
    checks = "pipeline_check" in stats and bool(stats["pipeline_check"].any())
    for ax, metric in zip(axes.flat, metrics):
        for i, (key, group) in enumerate(groups):
            key = key if isinstance(key, tuple) else (key,)
            checked = "pipeline_check" in group and bool(group["pipeline_check"].all())
            label = _line_label(line_cols, key, checked)
            part = group[group["metric"] == metric].sort_values(figure.x)
            if part.empty:
                continue
            color, style = colors[i % len(colors)], "--" if checked else "-"
            if (part["count"] > 1).any():  # error bars only where there is a spread to show
                ax.errorbar(part[figure.x], part["value"], yerr=part["std"].fillna(0.0).where(part["count"] > 1, 0.0),
                            marker="o", ms=4, lw=1.5, ls=style, capsize=2, color=color, label=label)
            else:
                ax.plot(part[figure.x], part["value"], marker="o", ms=4, lw=1.5, ls=style, color=color, label=label)
            published = part[part["paper_value"].notna()]
            if not published.empty:
                ax.scatter(published[figure.x], published["paper_value"], marker="*", s=90, color=color,
                           edgecolor="black", linewidth=0.6, zorder=5, label=f"{label}: paper (table)")
        ax.set_title(metric)
        ax.set_xlabel(figure.xlabel)
        ax.set_ylabel(axis_label(metric))
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
    note += (" Points: the mean over runs; error bars: their standard deviation." if has_spread
             else " Points: one run each (no error bars).")
    if "dataset" in stats and (stats["dataset"].astype(str) == "synthetic").any():
        note += " Synthetic data, not ModelNet40."
    if checks:
        note += f" Dashed [{PIPELINE_CHECK}]: a few steps of a reduced-width network, not a result."
    lines = [note, *([failed] if failed else [])]
    fig.suptitle(figure.title)
    fig.text(0.5, 0.01, "\n".join(lines), ha="center", va="bottom", fontsize=8, wrap=True)
    fig.tight_layout(rect=(0, 0.04 * len(lines), 1, 0.97))
    return fig


def make_figures(frame: pd.DataFrame, out_dir: Path, studies: Sequence[str] = tuple(FIGURES),
                 paper: pd.DataFrame | None = None, failed: pd.DataFrame | None = None) -> tuple[list[Path], list[str]]:
    """Draw every study of ``studies`` the frame has data for; (files written, notes). ``failed``: the jobs
    without metrics (:func:`read_sweeps`), named under every figure and in the notes."""
    absent = failed_note(pd.DataFrame() if failed is None else failed)
    written, notes = [], [f"note: {absent}"] if absent else []
    for study in studies:
        figure = FIGURES[study]
        stats = figure_data(frame, figure, paper)
        if stats.empty:
            notes.append(f"{study}: skipped (column {figure.x!r} has fewer than two values)")
            continue
        written += plot_figure(stats, figure, out_dir, absent)
        if stats["paper_value"].notna().any():
            notes.append(f"{study}: paper table values marked at {int(stats['paper_value'].notna().sum())} points")
        else:
            notes.append(f"{study}: {NO_PAPER_NUMBERS}")
    return written, notes


# --- real scan pairs: errors against the true overlap ------------------------------------------------

SCAN_PAIRS = "scan_pairs"
OVERLAP_BINS = (0.5, 0.7)
"""Inner edges of the overlap bins (< 50 %, 50-70 %, > 70 %)."""


def grid_pairs(grid_dir: Path, test_set) -> pd.DataFrame:
    """The per-pair rows (``pairs.parquet``) of a grid's last run on ``test_set`` (a
    :class:`src.pair_sets.TestSet`); every cell must have been computed on exactly that test set."""
    path = grid_dir / "pairs.parquet"
    if not path.is_file():
        raise ValueError(f"{path} does not exist: run `python -m benchmarks.grid` first")
    rows = read_parquet(path)
    rows = rows[(rows["experiment"] == test_set.experiment) & (rows["sampling"] == test_set.sampling.upper())
                & (rows["partial"] == test_set.partial)]
    if rows.empty:
        raise ValueError(f"{path} holds no pairs of {test_set.key}")
    expected = json.loads(json.dumps(test_set.definition, default=str))
    for digest in rows["cell"].unique():
        [summary] = [json.loads(p.read_text()) for p in (grid_dir / "cells").glob(f"*__{digest[:12]}.json")]
        if summary["definition"]["test_set"] != expected:
            raise ValueError(f"cell {summary['method']} of {grid_dir} ran on other pairs than {test_set.key} composed here: "
                             "pass the data overrides the grid ran with")
    return rows


def scan_pair_rows(grid_dir: Path, overrides: Sequence[str] = ()) -> tuple[pd.DataFrame, str]:
    """The per-pair rows of a ``+benchmark=scan_pairs`` grid with each pair's ``overlap``, ``source`` and
    ``reference`` scans and the method's display ``label``; and the scan sets' names. The test set is
    rebuilt from ``+exp=scan_pairs`` and ``overrides`` (the grid's data overrides)."""
    from src.pair_sets import build_test_set

    test_set = build_test_set(SCAN_PAIRS, "ts", "prnet", None, overrides)
    rows = grid_pairs(grid_dir, test_set)
    dataset = test_set.dataset
    meta = pd.DataFrame([{"pair": i, "overlap": pair.overlap, "source": dataset.names(i)[0],
                          "reference": dataset.names(i)[1]} for i, pair in enumerate(dataset.pairs)])
    rows = rows.merge(meta, on="pair", validate="many_to_one")
    rows["label"] = rows["method"].map(display_name)
    return rows, ", ".join(s.name for s in dataset.source.scan_sets)


def overlap_bins(overlap: pd.Series, bins: Sequence[float] = OVERLAP_BINS) -> pd.Series:
    """The bin of each overlap, labelled ``< 50 %``, ``50-70 %``, ``> 70 %`` (closed on the right)."""
    edges = [0.0, *bins, 1.0]
    pct = [f"{100 * e:g}" for e in edges]
    labels = [f"< {pct[1]} %", *(f"{a}-{b} %" for a, b in zip(pct[1:-2], pct[2:-1])), f"> {pct[-2]} %"]
    return pd.cut(overlap, edges, labels=labels, include_lowest=True)


def overlap_table(rows: pd.DataFrame, bins: Sequence[float] = OVERLAP_BINS) -> str:
    """Markdown: per method (rows, in grid order) and overlap bin (columns, then all pairs), the mean
    Error(R) in degrees, the mean Error(t) and the fraction of pairs under (5°, 0.05); one table each."""
    max_deg, max_t = SUCCESS_THRESHOLDS[-1]
    data = rows.assign(bin=overlap_bins(rows["overlap"], bins),
                       success=(rows[ERROR_R] < max_deg) & (rows[ERROR_T] < max_t))
    columns = [*data["bin"].cat.categories, "all"]
    methods = list(dict.fromkeys(data["label"]))
    blocks = []
    for metric, title, fmt in ((ERROR_R, "Error(R), mean (degrees)", "{:.2f}"), (ERROR_T, "Error(t), mean", "{:.3f}"),
                               ("success", f"success: Error(R) < {max_deg:g}° and Error(t) < {max_t:g}", "{:.0%}")):
        lines = [f"**{title}**", "", "| Method | pairs | " + " | ".join(columns) + " |",
                 "|:---|:---|" + "---:|" * len(columns)]
        for method in methods:
            own = data[data["label"] == method]
            counts = own.groupby("bin", observed=False).size()
            values = [*own.groupby("bin", observed=False)[metric].mean(), own[metric].mean()]
            cells = ["--" if math.isnan(v) else fmt.format(v) for v in values]
            lines.append(f"| {method} | {' / '.join(map(str, counts))} | " + " | ".join(cells) + " |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks) + "\n"


def plot_error_vs_overlap(rows: pd.DataFrame, path: Path, title: str, bins: Sequence[float] = OVERLAP_BINS) -> Path:
    """Every pair's Error(R) (log scale) against its overlap, one colour and marker per method, with each
    method's median per overlap bin as a horizontal bar."""
    fig, ax = plt.subplots(figsize=(7.5, 4.6))
    colors, markers = plt.rcParams["axes.prop_cycle"].by_key()["color"], "os^vDPX*"
    edges = [0.0, *bins, 1.0]
    low = max(float(rows["overlap"].min()) - 0.02, 0.0)
    for i, (label, own) in enumerate(rows.groupby("label", sort=False)):
        color = colors[i % len(colors)]
        ax.scatter(own["overlap"], own[ERROR_R].clip(lower=1e-2), s=16, alpha=0.75, color=color,
                   marker=markers[i % len(markers)], label=f"{label} ({len(own)} pairs)")
        medians = own.groupby(overlap_bins(own["overlap"], bins), observed=False)[ERROR_R].median()
        for lo, hi, median in zip(edges[:-1], edges[1:], medians):
            if not math.isnan(median):
                ax.hlines(max(median, 1e-2), max(lo, low), hi, color=color, lw=2, alpha=0.8)
    for edge in bins:
        ax.axvline(edge, color="grey", ls=":", lw=1)
    ax.set_yscale("log")
    ax.set_xlim(low, 1.0)
    ax.set_xlabel("overlap (the smaller overlapping fraction of the two scans, under the ground truth)")
    ax.set_ylabel("Error(R) (degrees)")
    ax.grid(alpha=0.3, which="both", axis="y")
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title, fontsize=10)
    fig.text(0.5, 0.01, "One marker per ordered scan pair; bars: each method's median in the overlap bin.",
             ha="center", va="bottom", fontsize=8)
    return _save(fig, path, rect=(0, 0.03, 1, 1))


def _save(fig: plt.Figure, path: Path, rect: tuple[float, float, float, float] = (0, 0, 1, 1)) -> Path:
    """``fig`` laid out within ``rect`` and written to ``path`` (its folder made), then closed."""
    fig.tight_layout(rect=rect)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _grid_parser(command: str, description: str, example: str) -> argparse.ArgumentParser:
    """The arguments every grid plot takes: the grid's folder, its data overrides, ``--out``."""
    parser = argparse.ArgumentParser(prog=f"python -m benchmarks.plots {command}", description=description)
    parser.add_argument("grid_dir", type=Path, help=f"the grid's output folder (e.g. {example})")
    parser.add_argument("overrides", nargs="*", help="the data overrides the grid ran with")
    parser.add_argument("--out", type=Path, default=None, help="folder for the PNG and the Markdown (default: grid_dir)")
    return parser


def scan_pairs_main(argv: list[str]) -> int:
    parser = _grid_parser("scan-pairs", "Errors of a +benchmark=scan_pairs grid against the pairs' overlap.",
                          "outputs/grid/scan_pairs")
    args = parser.parse_args(argv)
    out = args.out or args.grid_dir
    try:
        rows, scan_sets = scan_pair_rows(args.grid_dir, args.overrides)
    except (ValueError, UserError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    table = overlap_table(rows)
    out.mkdir(parents=True, exist_ok=True)
    (out / "scan_pairs_by_overlap.md").write_text(table)
    title = f"Real scan pairs ({scan_sets}): rotation error against overlap"
    png = plot_error_vs_overlap(rows, out / "scan_pairs_error_vs_overlap.png", title)
    print(table)
    print(f"wrote {png}, {out / 'scan_pairs_by_overlap.md'}")
    return 0


def category_rows(grid_dir: Path, experiment: str, sampling: str, partial: str, data: str | None,
                  overrides: Sequence[str] = ()) -> pd.DataFrame:
    """The per-pair rows of a grid's cells of one experiment with each pair's shape ``category`` and the method's
    display ``label``; the test set is rebuilt from the experiment, ``data`` (None: the dataset the cells record)
    and ``overrides`` (the grid's)."""
    from src.pair_sets import build_test_set

    if data is None:  # the data the grid's cells of this experiment ran on
        path = grid_dir / "pairs.parquet"
        ran = read_parquet(path) if path.is_file() else pd.DataFrame(columns=["experiment", "dataset"])
        datasets = ran.loc[ran["experiment"] == experiment, "dataset"].unique()
        data = str(datasets[0]) if len(datasets) == 1 else None
    test_set = build_test_set(experiment, sampling, partial, data, overrides)
    rows = grid_pairs(grid_dir, test_set)
    pairs = test_set.dataset
    names = test_set.categories
    shape_labels = np.asarray(pairs.labels)[np.asarray(pairs.shape_indices)]
    meta = pd.DataFrame({"pair": np.arange(len(pairs)), "category": [names[label] for label in shape_labels]})
    rows = rows.merge(meta, on="pair", validate="many_to_one")
    rows["label"] = rows["method"].map(display_name)
    return rows


def category_table(rows: pd.DataFrame) -> str:
    """Markdown: per category (rows, with its pair count) and method (columns, in grid order), the mean Error(R)."""
    methods = list(dict.fromkeys(rows["label"]))
    means = rows.pivot_table(index="category", columns="label", values=ERROR_R, aggfunc="mean")[methods]
    counts = rows[rows["label"] == methods[0]].groupby("category").size()
    lines = ["**Error(R), mean (degrees), per category**", "", "| Category | pairs | " + " | ".join(methods) + " |",
             "|:---|---:|" + "---:|" * len(methods)]
    for category, values in means.iterrows():
        lines.append(f"| {category} | {counts[category]} | " + " | ".join(f"{v:.2f}" for v in values) + " |")
    overall = rows.groupby("label", sort=False)[ERROR_R].mean()[methods]
    lines.append(f"| all | {int(counts.sum())} | " + " | ".join(f"{v:.2f}" for v in overall) + " |")
    return "\n".join(lines) + "\n"


#: The lowest error the per-category figure draws (a log axis): an exact registration would be off the plot.
FLOOR = 1e-2


def plot_error_by_category(rows: pd.DataFrame, path: Path, title: str) -> Path:
    """Each method's mean Error(R) (log scale) per category, the categories from the easiest to the hardest (the
    median over the methods that register), one colour and marker per method, the identity a dashed grey line."""
    methods = list(dict.fromkeys(rows["label"]))
    means = rows.pivot_table(index="category", columns="label", values=ERROR_R, aggfunc="mean")[methods]
    reference = display_name(REFERENCE)
    registering = [m for m in methods if m != reference] or methods
    means = means.loc[means[registering].median(axis=1).sort_values().index]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(means) + 2), 4.6))
    markers = "os^vDPX*<>"
    colours = plt.get_cmap("tab20" if len(registering) > 10 else "tab10")
    for i, method in enumerate(registering):  # a colour each (up to 20 methods) and a marker each (up to 10)
        ax.plot(range(len(means)), means[method].clip(lower=FLOOR), marker=markers[i % len(markers)], lw=1,
                color=colours(i % colours.N), label=method)
    if reference in methods:
        ax.plot(range(len(means)), means[reference], color="0.5", ls="--", lw=1, label=reference)
    ax.set_xticks(range(len(means)), means.index, rotation=60, ha="right", fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel(f"Error(R), category mean (°; floored at {FLOOR:g})")
    ax.grid(alpha=0.3, which="both", axis="y")
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title, fontsize=10)
    return _save(fig, path)


def categories_main(argv: list[str]) -> int:
    parser = _grid_parser("categories", "Errors of a grid's experiment per shape category: a table and a figure.",
                          "outputs/grid/table1_npy")
    parser.add_argument("--experiment", default="unseen_categories", help="conf/exp/<name>.yaml (default unseen_categories)")
    parser.add_argument("--sampling", default="os")
    parser.add_argument("--partial", default="prnet")
    parser.add_argument("--data", default=None, help="the data config (default: the one the grid's cells ran on)")
    args = parser.parse_args(argv)
    try:
        table, written = write_categories(args.grid_dir, args.experiment, args.sampling, args.partial, args.data,
                                          args.overrides, args.out)
    except (ValueError, UserError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(table)
    print(f"wrote {', '.join(str(path) for path in written)}")
    return 0


def write_categories(grid_dir: Path, experiment: str, sampling: str, partial: str, data: str | None = None,
                     overrides: Sequence[str] = (), out: Path | None = None) -> tuple[str, list[Path]]:
    """``<experiment>_<sampling>_<partial>_by_category.png`` and ``.md`` in ``out`` (default ``grid_dir``): the
    mean Error(R) of every method of the grid's cells per shape category (:func:`category_rows`); the table and
    the files written."""
    out = out or grid_dir
    rows = category_rows(grid_dir, experiment, sampling, partial, data, overrides)
    table = category_table(rows)
    stem = f"{experiment}_{sampling}_{partial}_by_category"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.md").write_text(table)
    title = f"{experiment} ({sampling.upper()}, {partial}): rotation error per category"
    return table, [plot_error_by_category(rows, out / f"{stem}.png", title), out / f"{stem}.md"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["scan-pairs"]:
        return scan_pairs_main(argv[1:])
    if argv[:1] == ["categories"]:
        return categories_main(argv[1:])
    parser = argparse.ArgumentParser(prog="python -m benchmarks.plots", description=__doc__.split("\n\n")[0])
    parser.add_argument("inputs", nargs="+", help="collected frames (.parquet/.csv) or multirun dirs")
    parser.add_argument("--out", type=Path, default=None, help="folder for the figures (default: beside the first input)")
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
        frame, failed = read_sweeps(args.inputs)
        paper = None
        if not args.no_paper:
            try:
                paper = load_paper_tables(args.paper_dir)
            except FileNotFoundError as err:
                print(f"note: {err}; plotting without paper values", file=sys.stderr)
        written, notes = make_figures(frame, args.out or default_out(args.inputs[0]), studies, paper, failed)
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
