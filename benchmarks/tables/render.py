"""Results tables in the paper's layouts, as LaTeX (booktabs) and Markdown.

    python -m benchmarks.tables multirun/sweep_table1/<time> --layout table1 --out results/tables   # default: beside the input
    python -m benchmarks.tables results.parquet --layout table3 --paper --standalone --compile

Input: tidy frames (parquet or CSV) with columns ``method, experiment, sampling, partial, metric,
value`` and optionally ``source`` (several inputs are concatenated), or multirun dirs (collected on
the fly with :mod:`benchmarks.collect`). Cells with several rows (seeds, repeated runs) show their
mean. A method given by several ``source`` values gets one row per source. A file's cell that should hold a number
and does not (``1.2 deg``) is refused naming its row and column (:func:`numbers_checked`; ``NaN`` stays NaN).

Layouts (rows: methods in the paper's order, :func:`baselines.methods.paper_rank`, after the identity, a
reference that is never ranked; best of ours per column in bold, second underlined; every header names
its unit and direction, ↓ lower is better):

* ``table1`` — Table 1: one block per experiment (unseen shapes, unseen categories, Gaussian
  noise, ...), an OS and a TS column per metric.
* ``table2`` — Table 2: one TS column per metric (rows of other samplings are dropped).
* ``table3`` — Table 3: TS columns; component rows (B ... B+M+ML+F+C), then top-k rows, then λ
  rows, separated by rules.

``--paper`` adds, under each of our rows that the paper reports, a row with the paper's published
values (read at run time from ``--paper-dir``, default ``../shared/reference/paper_tables`` beside the repository root;
see :mod:`benchmarks.tables.paper` for when a cell counts as the paper's setting) and a row with the ratio
ours / paper. Those rows are marked ``paper`` and ``ours/paper`` and never take part in the ranking.
"""

from __future__ import annotations

import argparse
import math
import re
import shutil
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import pandas as pd

from baselines.methods import display_name, find_method, paper_rank
from benchmarks.tables.paper import (
    EXPERIMENT_LABELS,
    PAPER_COUNTERPARTS,
    attach_paper,
    canonical_experiment,
    default_paper_dir,
    load_paper_tables,
    method_key,
)
from src.metrics import CHAMFER, ERROR_R, MAE_R, MODIFIED_CHAMFER, PAPER_METRICS, RMSE_R, SCORE, SUCCESS_NAMES
from src.utils.errors import UserError
from src.utils.files import read_parquet, refuse_unwritable_outputs

HIGHER_IS_BETTER = SUCCESS_NAMES
REQUIRED = ("method", "experiment", "sampling", "metric", "value")
LAYOUTS = ("table1", "table2", "table3")
#: The paper's experiments in the order of its sub-tables (a), (b), (c), (d) (Tables 1 and 2 of the paper).
PAPER_EXPERIMENTS = ("unseen_shapes", "unseen_categories", "unseen_shapes_noise", "unseen_categories_noise")
#: The paper's experiments in its order, each followed by our real-data experiments that stand in for it.
EXPERIMENT_ORDER = tuple(e for paper in PAPER_EXPERIMENTS
                         for e in (paper, *(ours for ours, cell in PAPER_COUNTERPARTS.items() if cell == paper)))
ABLATION_ORDER = ("B", "B+M", "B+M+ML", "B+M+ML+F", "B+M+ML+F+C")
MISSING = "--"
#: The method every table shows as a reference row, never ranked.
REFERENCE = "identity"
NOT_A_NUMBER = "NaN"  # a method that ran and gave NaN: never shown as MISSING (not run), and its column is not ranked


def _sub_table_letters(experiments: list[str], partials: list[str]):
    """The sub-table letter of each block: the paper's ((a) unseen shapes, (b) unseen categories, (c) and (d) the
    same with noise) where the blocks are the paper's experiments in one partial manner, so that a table of
    (b) alone is still labelled (b); otherwise (a), (b), ... in order."""
    paper = [PAPER_COUNTERPARTS.get(e, e) for e in experiments]
    if len(partials) == 1 and len(set(paper)) == len(paper) and all(e in PAPER_EXPERIMENTS for e in paper):
        return lambda experiment: "abcd"[PAPER_EXPERIMENTS.index(PAPER_COUNTERPARTS.get(experiment, experiment))]
    letters = iter("abcdefghijklmnopqrstuvwxyz")
    return lambda experiment: next(letters)


# --- the intermediate table ---------------------------------------------------------------------


@dataclass
class Row:
    label: str
    values: list[float | None]
    kind: str = "ours"  # ours | paper | ratio
    ranks: list[int | None] = field(default_factory=list)
    counts: list[int] = field(default_factory=list)
    group: int = 0  # rule between groups (Table 3)
    reference: bool = False  # the identity (no registration): shown, never ranked


@dataclass
class Block:
    label: str | None
    rows: list[Row]


@dataclass
class Table:
    layout: str
    metrics: list[str]
    samplings: list[str]
    blocks: list[Block]
    caption: str
    label: str
    notes: list[str] = field(default_factory=list)
    header_units: bool = False  # each metric's header names its unit and its direction (lower/higher is better)

    @property
    def columns(self) -> list[tuple[str, str]]:
        return [(m, s) for m in self.metrics for s in self.samplings]


#: Units shown by :attr:`Table.header_units` (rotations in degrees; translations in the shapes' own units).
METRIC_UNITS = {RMSE_R: "°", MAE_R: "°", ERROR_R: "°", "ms/pair": "ms"}


def _direction(metric: str) -> str:
    return "↑" if metric in HIGHER_IS_BETTER else "↓"


def units_sentence(metrics: Sequence[str]) -> str:
    """What the headers' units and arrows mean, for a caption."""
    directions = sorted({_direction(m) for m in metrics}, reverse=True)
    arrows = {"↓": "lower is better (↓)", "↑": "higher is better (↑)"}
    said = " in every column" if len(directions) == 1 else " where marked"
    rotations = [m for m in metrics if METRIC_UNITS.get(m) == "°"]
    translations = [m for m in metrics if m.endswith("(t)")]
    units = ([f"{', '.join(rotations)} in degrees"] if rotations else []) + (
        [f"{', '.join(translations)} in the data's units (ModelNet40 and the synthetic shapes lie in the unit sphere)"]
        if translations else [])
    return (" and ".join(arrows[d] for d in directions).capitalize() + said
            + (": " + "; ".join(units) if units else "") + ".")


def is_reference(method: str) -> bool:
    """Whether ``method`` (a key, display name or table label) is the identity: a reference, never ranked."""
    found = find_method(method) or find_method(method.split(" (")[0])
    return found is not None and found.key == REFERENCE


def decimals(metric: str) -> int:
    if metric == MODIFIED_CHAMFER:  # squared distances: ~1e-3 for a good registration
        return 5
    return 4 if metric.endswith("(t)") or metric in (CHAMFER, SCORE) else 3


def fmt(value: float | None, metric: str) -> str:
    if value is None:
        return MISSING
    if math.isnan(value):
        return NOT_A_NUMBER
    return f"{value:.{decimals(metric)}f}"


# --- from a tidy frame ----------------------------------------------------------------------------


def read_inputs(paths: Sequence[str | Path]) -> pd.DataFrame:
    """Concatenate tidy frames (parquet / CSV files, or multirun dirs collected on the fly)."""
    frames = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            from benchmarks.collect import collect

            frames.append(collect(path).tidy)
        elif path.suffix == ".parquet":
            frames.append(numbers_checked(read_parquet(path), path))  # its page checksums verified: a damaged file is one line
        elif path.suffix in (".csv", ".tsv"):
            frames.append(numbers_checked(pd.read_csv(path, sep="\t" if path.suffix == ".tsv" else ","), path))
        else:
            raise ValueError(f"{path}: expected a .parquet/.csv frame or a multirun directory")
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(REQUIRED))


#: The columns of a tidy frame that hold numbers (``aggregate`` averages ``value`` and compares the others).
NUMERIC_COLUMNS = ("value", "noise_sigma", "overlap_ratio", "num_iters")


def _is_number(value: object) -> bool:
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


def numbers_checked(frame: pd.DataFrame, path: Path) -> pd.DataFrame:
    """``frame`` with its :data:`NUMERIC_COLUMNS` as numbers (NaN stays NaN: a run without the number); ValueError
    naming the file, the row (1 = the first under the header, and its method, experiment, sampling, metric) and the
    column of the first cell that is not a number."""
    for column in (c for c in NUMERIC_COLUMNS if c in frame.columns):
        bad = [i for i, v in enumerate(frame[column]) if not pd.isna(v) and not _is_number(v)]
        if bad:
            row = frame.iloc[bad[0]]
            label = ", ".join(f"{k} {row[k]}" for k in ("method", "experiment", "sampling", "metric") if k in frame.columns)
            raise ValueError(f"{path}: row {bad[0] + 1} ({label}), column {column}: {row[column]!r} is not a number; "
                             "write the number, or NaN for a run that gave none")
        frame[column] = pd.to_numeric(frame[column])
    return frame


def normalise(frame: pd.DataFrame) -> pd.DataFrame:
    """Check the columns; upper-case sampling, canonical experiment names, ``partial`` defaulted."""
    missing = [c for c in REQUIRED if c not in frame.columns]
    if missing:
        raise ValueError(f"the frame lacks the columns {missing} (needs {', '.join(REQUIRED)}[, partial, source])")
    out = frame.copy()
    if "partial" not in out.columns:
        warnings.warn("no 'partial' column: assuming the PRNet manner")
        out["partial"] = "prnet"
    out["sampling"] = out["sampling"].astype(str).str.upper()
    out["partial"] = out["partial"].fillna("prnet").astype(str).str.lower()
    out["experiment"] = out["experiment"].map(canonical_experiment)
    out["method"] = out["method"].astype(str)
    if "source" in out.columns:
        sources = out.groupby("method")["source"].nunique()
        several = set(sources[sources > 1].index)
        out["method"] = [f"{m} ({s})" if m in several else m for m, s in zip(out["method"], out["source"])]
    return out


def aggregate(frame: pd.DataFrame) -> pd.DataFrame:
    """One value per (method, experiment, sampling, partial, metric): the mean, with ``n``; the
    columns the paper matching looks at (dataset, noise_sigma, ...) are kept when constant."""
    keys = ["method", "experiment", "sampling", "partial", "metric"]
    extra = [c for c in ("dataset", "noise_sigma", "overlap_ratio", "num_iters") if c in frame.columns]
    grouped = frame.groupby(keys, dropna=False, sort=False)
    out = grouped["value"].agg(value=lambda v: v.mean(skipna=False), n="size").reset_index()  # a NaN run stays NaN
    for col in extra:
        firsts = grouped[col].agg(lambda v: v.iloc[0] if v.nunique(dropna=False) <= 1 else "<mixed>")
        out[col] = firsts.to_numpy()
    return out


def _method_sort_key(name: str) -> tuple:
    """The paper's row order (:func:`baselines.methods.paper_rank`; a label's `` (...)`` suffix aside),
    after the identity: its baselines, then methods it does not have (alphabetically), then OMNet."""
    return (not is_reference(name), *paper_rank(name.split(" (")[0]), name.lower())


def table3_group(name: str) -> tuple[int, float, str]:
    """(group, order within it) of a Table 3 row: components, top-k (k descending), λ (descending)."""
    key = method_key(name.split(" (")[0])
    components = [method_key(m) for m in ABLATION_ORDER]
    if key in components:
        return (0, components.index(key), name)
    match = re.match(r"topk(?:k=)?(\d+)$", key)
    if match:
        return (1, -float(match.group(1)), name)
    if key.startswith("lambda="):
        return (2, -float(key.split("=", 1)[1]), name)
    return (3, 0.0, name)


def _rank(rows: list[Row], n_columns: int, metrics: list[str]) -> None:
    ours = [r for r in rows if r.kind == "ours" and not r.reference]
    for r in ours:
        r.ranks = [None] * n_columns
    for c in range(n_columns):
        metric = metrics[c]
        shown = {round(r.values[c], decimals(metric)) for r in ours if r.values[c] is not None and not math.isnan(r.values[c])}
        if len(shown) < 2 or any(r.values[c] is not None and math.isnan(r.values[c]) for r in ours):
            continue
        distinct = sorted(shown, reverse=metric in HIGHER_IS_BETTER)  # ties as printed share a rank
        for r in ours:
            v = r.values[c]
            if v is None or math.isnan(v):
                continue
            position = distinct.index(round(v, decimals(metric)))
            r.ranks[c] = position + 1 if position < 2 else None


def build_table(
    frame: pd.DataFrame,
    layout: str = "table1",
    metrics: Sequence[str] = PAPER_METRICS,
    paper: pd.DataFrame | None = None,
    any_dataset: bool = False,
    experiments: Sequence[str] | None = None,
    caption: str | None = None,
) -> Table:
    """The table of ``layout`` for a tidy frame (see the module docstring)."""
    if layout not in LAYOUTS:
        raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
    data = normalise(frame)
    data = data[data["metric"].isin(metrics)]
    notes: list[str] = []
    samplings = ["OS", "TS"] if layout == "table1" else ["TS"]
    dropped = data[~data["sampling"].isin(samplings)]
    if not dropped.empty:
        notes.append(f"{len(dropped)} rows of sampling {sorted(dropped['sampling'].unique())} are not part of this layout")
        data = data[data["sampling"].isin(samplings)]
    if layout == "table1" and data["sampling"].nunique() == 1:  # e.g. data with one sampling a shape: OS only
        samplings = list(data["sampling"].unique())
    if experiments:
        wanted = [canonical_experiment(e) for e in experiments]
        data = data[data["experiment"].isin(wanted)]
    if data.empty:
        raise ValueError(f"no rows left for layout {layout} (metrics {list(metrics)}, samplings {samplings})")
    cells = aggregate(data)
    if paper is not None:
        cells = attach_paper(cells, paper, any_dataset=any_dataset)
    metrics = [m for m in metrics if m in set(cells["metric"])]
    columns = [(m, s) for m in metrics for s in samplings]
    column_metrics = [m for m, _ in columns]

    partials = sorted(cells["partial"].unique())
    experiments_present = list(dict.fromkeys(cells["experiment"]))
    order = [e for e in EXPERIMENT_ORDER if e in experiments_present] + sorted(e for e in experiments_present if e not in EXPERIMENT_ORDER)
    blocks = []
    letter = _sub_table_letters(order, partials)
    for partial in partials:
        for experiment in order:
            part = cells[(cells["partial"] == partial) & (cells["experiment"] == experiment)]
            if part.empty:
                continue
            methods = list(dict.fromkeys(part["method"]))
            methods.sort(key=table3_group if layout == "table3" else _method_sort_key)
            rows: list[Row] = []
            for method in methods:
                sub = part[part["method"] == method].set_index(["metric", "sampling"])
                get = lambda col, key: (float(sub.loc[key, col]) if key in sub.index and (col == "value" or pd.notna(sub.loc[key, col]))
                                        else None)  # noqa: E731 - a value that ran is kept, NaN included
                group = table3_group(method)[0] if layout == "table3" else 0
                ours = Row(method, [get("value", k) for k in columns], "ours", group=group,
                           counts=[int(sub.loc[k, "n"]) if k in sub.index else 0 for k in columns],
                           reference=is_reference(method))
                rows.append(ours)
                if paper is not None:
                    published = [get("paper_value", k) for k in columns]
                    if any(v is not None for v in published):
                        rows.append(Row("paper", published, "paper", group=group))
                        rows.append(Row("ours/paper", [get("ratio", k) for k in columns], "ratio", group=group))
            _rank(rows, len(columns), column_metrics)
            label = EXPERIMENT_LABELS.get(experiment, experiment.replace("_", " "))
            if len(partials) > 1 or partial != "prnet":
                label += f", {'RPMNet' if partial == 'rpmnet' else 'PRNet'} manner"
            if layout == "table1" or len(order) > 1 or len(partials) > 1:
                label = f"({letter(experiment)}) {label}"
                blocks.append(Block(label, rows))
            else:
                blocks.append(Block(None, rows))

    if (cells["n"] > 1).any():
        notes.append(f"cells with several runs show their mean (up to {int(cells['n'].max())} runs)")
    if "dataset" in cells.columns:
        datasets = sorted(str(d) for d in cells["dataset"].dropna().unique())
        if datasets and datasets != ["modelnet40"]:
            notes.append(f"dataset: {', '.join(datasets)}" + (" (synthetic data, not ModelNet40 results)" if "synthetic" in datasets else ""))
    if paper is not None:
        matched = cells["paper_value"].notna().sum()
        notes.append(f"rows 'paper': the paper's published values ({matched} of {len(cells)} cells matched); "
                     "rows 'ours/paper': our value divided by the paper's")
        reasons = cells.loc[cells["paper_value"].isna(), "paper_note"].value_counts()
        for reason, count in reasons.items():
            notes.append(f"no paper value for {count} cells: {reason}")
    titles = {
        "table1": (f"Registration errors, {' and '.join(samplings)} columns per metric (layout of the paper's Table 1"
                   + ("" if len(samplings) == 2 else f", {samplings[0]} data only") + ")"),
        "table2": "Registration errors on twice-sampled (TS) data (layout of the paper's Table 2)",
        "table3": "Ablation studies on TS data (layout of the paper's Table 3)",
    }
    references = sorted({display_name(r.label) for b in blocks for r in b.rows if r.reference})
    ranked = (f"{' and '.join(references)}: the reference, never ranked; best" if references else "Best")
    caption = (f"{caption.rstrip('.')}. " if caption else "") + titles[layout] + (
        f". {units_sentence(metrics)} {ranked} of ours per column in bold, second underlined.")
    return Table(layout, list(metrics), samplings, blocks, caption, f"tab:{layout}", notes, header_units=True)


# --- rendering --------------------------------------------------------------------------------------

#: What a table fragment needs in the including document's preamble (the standalone document loads them).
LATEX_PACKAGES = ("booktabs", "graphicx")
FRAGMENT_NEEDS = (f"% a table* fragment: \\input it in a document that loads \\usepackage{{{','.join(LATEX_PACKAGES)}}} "
                  "(booktabs: the rules; graphicx: \\resizebox)")

_LATEX_SPECIAL = {"&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{", "}": r"\}",
                  "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "\\": r"\textbackslash{}"}

_LATEX_SYMBOLS = {"×": r"$\times$", "↓": r"$\downarrow$", "↑": r"$\uparrow$", "°": r"$^\circ$"}


def latex_escape(text: str) -> str:
    """Escape LaTeX specials; λ / ``lambda=`` become ``$\\lambda$=``."""
    match = re.match(r"^\s*(?:\$\\lambda\$|\\lambda|λ|lambda)\s*=\s*(.+)$", text)
    if match:
        return r"$\lambda$=" + latex_escape(match.group(1))
    return "".join(_LATEX_SPECIAL.get(ch, _LATEX_SYMBOLS.get(ch, ch)) for ch in text)


def _metric_tex(metric: str, units: bool = False) -> str:
    match = re.match(r"^(.*)\((R|t)\)$", metric)
    text = f"{latex_escape(match.group(1))}($\\mathbf{{{match.group(2)}}}$)" if match else latex_escape(metric)
    if not units:
        return text
    unit = " ($^\\circ$)" if METRIC_UNITS.get(metric) == "°" else ""
    arrow = r"$\uparrow$" if _direction(metric) == "↑" else r"$\downarrow$"
    return f"{text}{unit} {arrow}"


def metric_header(metric: str) -> str:
    """A metric's plain-text header with its unit and direction, e.g. ``Error(R) (°) ↓``."""
    return _metric_md(metric, units=True)


def _metric_md(metric: str, units: bool) -> str:
    unit = METRIC_UNITS.get(metric) if units and metric != "ms/pair" else None
    return f"{metric}{f' ({unit})' if unit else ''}{f' {_direction(metric)}' if units else ''}"


def _cell_tex(row: Row, c: int, metric: str) -> str:
    value = row.values[c]
    if row.kind == "ratio":
        return MISSING if value is None or math.isnan(value) else f"{value:.2f}$\\times$"
    text = fmt(value, metric)
    if row.kind == "paper":
        return text if text == MISSING else f"\\textit{{{text}}}"
    rank = row.ranks[c] if row.ranks else None
    return f"\\textbf{{{text}}}" if rank == 1 else f"\\underline{{{text}}}" if rank == 2 else text


def _row_label_tex(row: Row) -> str:
    if row.kind == "paper":
        return r"\quad\textit{paper}"
    if row.kind == "ratio":
        return r"\quad\textit{ours/paper}"
    return latex_escape(row.label)


def to_latex(table: Table, standalone: bool = False) -> str:
    columns = table.columns
    n = len(columns) + 1
    lines = [f"% generated by python -m benchmarks.tables --layout {table.layout}"]
    if standalone:
        lines += [r"\documentclass{article}", r"\usepackage[margin=1.5cm,landscape]{geometry}",
                  *(f"\\usepackage{{{package}}}" for package in LATEX_PACKAGES), r"\begin{document}"]
    else:
        lines.append(FRAGMENT_NEEDS)
    lines += [r"\begin{table*}[t]", r"\centering", r"\resizebox{\linewidth}{!}{%", f"\\begin{{tabular}}{{l*{{{len(columns)}}}{{c}}}}",
              r"\toprule"]
    if len(table.samplings) > 1:
        k = len(table.samplings)
        head = ["Method"] + [f"\\multicolumn{{{k}}}{{c}}{{{_metric_tex(m, table.header_units)}}}" for m in table.metrics]
        lines.append(" & ".join(head) + r" \\")
        lines.append(" ".join(f"\\cmidrule(lr){{{2 + i * k}-{1 + (i + 1) * k}}}" for i in range(len(table.metrics))))
        lines.append(" & ".join([""] + [s for _ in table.metrics for s in table.samplings]) + r" \\")
    else:
        lines.append(" & ".join(["Method"] + [_metric_tex(m, table.header_units) for m in table.metrics]) + r" \\")
    for block in table.blocks:
        lines.append(r"\midrule")
        if block.label:
            lines.append(f"\\multicolumn{{{n}}}{{l}}{{\\textit{{{latex_escape(block.label)}}}}} \\\\")
        previous = None
        for row in block.rows:
            if previous is not None and row.group != previous and row.kind == "ours":
                lines.append(r"\midrule")
            previous = row.group
            cells = [_row_label_tex(row)] + [_cell_tex(row, c, m) for c, (m, _) in enumerate(columns)]
            lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}%", "}"]
    caption = latex_escape(table.caption) + "".join(" " + latex_escape(note[0].upper() + note[1:]) + "." for note in table.notes)
    lines += [f"\\caption{{{caption}}}", f"\\label{{{table.label}}}", r"\end{table*}"]
    if standalone:
        lines.append(r"\end{document}")
    return "\n".join(lines) + "\n"


def _md_escape(text: str) -> str:
    return text.replace("|", r"\|")


def to_markdown(table: Table) -> str:
    columns = table.columns
    multi = len(table.samplings) > 1
    header = ["Method"] + [f"{_metric_md(m, table.header_units)} {s}" if multi else _metric_md(m, table.header_units)
                           for m, s in columns]
    lines = [f"**{table.caption}**", "", "| " + " | ".join(_md_escape(h) for h in header) + " |",
             "|" + "|".join([":---"] + ["---:"] * len(columns)) + "|"]
    for block in table.blocks:
        if block.label:
            lines.append(f"| ***{_md_escape(block.label)}*** |" + " |" * len(columns))
        for row in block.rows:
            if row.kind == "ours":
                label = _md_escape(row.label.replace("lambda=", "λ=") if row.label.startswith("lambda=") else row.label)
            else:
                label = "↳ *paper*" if row.kind == "paper" else "↳ *ours/paper*"
            cells = []
            for c, (metric, _) in enumerate(columns):
                value = row.values[c]
                if row.kind == "ratio":
                    cells.append(MISSING if value is None or math.isnan(value) else f"{value:.2f}×")
                    continue
                text = fmt(value, metric)
                rank = row.ranks[c] if row.kind == "ours" and row.ranks else None
                if row.kind == "paper" and text != MISSING:
                    text = f"*{text}*"
                cells.append(f"**{text}**" if rank == 1 else f"<u>{text}</u>" if rank == 2 else text)
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if table.notes:
        lines += [""] + [f"- {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


# --- command line -------------------------------------------------------------------------------------

LATEX_ENGINE = "pdflatex"


def default_out(first_input: str | Path) -> Path:
    """Where the tables go without ``--out``: beside the input they were made from (a multirun dir: inside it)."""
    path = Path(first_input)
    return path if path.is_dir() else path.parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.tables", description=__doc__.split("\n\n")[0])
    parser.add_argument("inputs", nargs="+", help="tidy frames (.parquet/.csv) or multirun dirs")
    parser.add_argument("--layout", choices=LAYOUTS, default="table1")
    parser.add_argument("--out", type=Path, default=None,
                        help="folder for <name>.tex and <name>.md (default: beside the first input, in its folder)")
    parser.add_argument("--name", default=None, help="file name stem (default: the layout)")
    parser.add_argument("--metrics", default=",".join(PAPER_METRICS), help="comma-separated metrics (default: the paper's six)")
    parser.add_argument("--experiments", default=None, help="comma-separated experiments to keep (default: all)")
    parser.add_argument("--paper", action="store_true", help="add the paper's published values and ours/paper ratios")
    parser.add_argument("--paper-dir", type=Path, default=None, help=f"paper CSV folder (default: $OMNET_PAPER_TABLES or {default_paper_dir()})")
    parser.add_argument("--paper-any-dataset", action="store_true",
                        help="compare with the paper even for non-ModelNet40 rows (a real-data experiment with its counterpart)")
    parser.add_argument("--caption", default=None, help="the table's own words (data, budget), put before the layout's caption")
    parser.add_argument("--standalone", action="store_true", help="also write <name>_standalone.tex (a full document)")
    parser.add_argument("--compile", action="store_true", help="compile the standalone document with pdflatex (needs it installed)")
    args = parser.parse_args(argv)
    if args.compile and shutil.which(LATEX_ENGINE) is None:
        print(f"error: --compile needs {LATEX_ENGINE}, which is not installed: install a TeX distribution (Debian: "
              "apt-get install texlive-latex-recommended), or leave out --compile", file=sys.stderr)
        return 2
    args.out = args.out or default_out(args.inputs[0])
    name = args.name or args.layout
    try:
        refuse_unwritable_outputs(args.out, [name + end for end in (".tex", ".md", "_standalone.tex", "_standalone.pdf")],
                                  "--out")
        frame = read_inputs(args.inputs)
        paper = load_paper_tables(args.paper_dir) if args.paper else None
        table = build_table(frame, args.layout, [m.strip() for m in args.metrics.split(",") if m.strip()], paper,
                            any_dataset=args.paper_any_dataset,
                            experiments=args.experiments.split(",") if args.experiments else None, caption=args.caption)
    except (ValueError, FileNotFoundError, UserError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    from benchmarks.tables.latex_check import check_latex, compile_latex

    args.out.mkdir(parents=True, exist_ok=True)
    tex, markdown = to_latex(table), to_markdown(table)
    (args.out / f"{name}.tex").write_text(tex)
    (args.out / f"{name}.md").write_text(markdown)
    written = [args.out / f"{name}.tex", args.out / f"{name}.md"]
    problems = check_latex(tex)
    if args.standalone or args.compile:
        document = to_latex(table, standalone=True)
        (args.out / f"{name}_standalone.tex").write_text(document)
        written.append(args.out / f"{name}_standalone.tex")
        if args.compile:
            pdf = args.out / f"{name}_standalone.pdf"
            ok, reason = compile_latex(document, pdf, engine=LATEX_ENGINE)
            if ok:
                written.append(pdf)
            else:
                problems.append(f"{LATEX_ENGINE}: {reason}")
    print(markdown)
    print("wrote " + ", ".join(map(str, written)))
    for problem in problems:
        print(f"error: LaTeX check: {problem}", file=sys.stderr)
    return 1 if problems else 0
