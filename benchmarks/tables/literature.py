"""The partial-ModelNet literature's table (Predator, RegTR and the papers after them): one row per method,
a ModelNet and a ModelLoNet column group of RRE (°), RTE and CD (RPM-Net's modified Chamfer distance), our
grid's values and, below them, the published values (``benchmarks/tables/published/modelnet.csv``), marked as such.

    python -m benchmarks.tables.literature outputs/grid/modelnet_real_airplane/results.csv \\
        --out benchmarks/results/modelnet_real_airplane --compile

Writes ``<out>.csv`` (the table as a pandas frame), ``<out>.md``, ``<out>.tex`` (a fragment) and
``<out>_standalone.tex``, and with ``--compile`` ``<out>.pdf`` (pdflatex). Our rows come from a grid's tidy
table (:mod:`benchmarks.grid`) whose experiments follow one of the protocols (:data:`EXPERIMENT_PROTOCOL`);
the best of ours per column is in bold. A learned method's row is marked † (its weights: the grid's config).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Sequence

import pandas as pd

from baselines.methods import find_method
from benchmarks.tables.render import FRAGMENT_NEEDS, LATEX_PACKAGES, latex_escape, read_inputs
from src.metrics import ERROR_R, ERROR_T, MODIFIED_CHAMFER
from src.utils.errors import UserError

PROTOCOLS = {"modelnet": "ModelNet", "modellonet": "ModelLoNet"}
#: Our experiments of each protocol: the protocol's own (conf/exp/modelnet.yaml, modellonet.yaml) and its stand-ins.
EXPERIMENT_PROTOCOL = {"modelnet": "modelnet", "modellonet": "modellonet",
                       "real_airplane_modelnet": "modelnet", "real_airplane_modellonet": "modellonet",
                       "real_bathtub_modelnet": "modelnet", "real_bathtub_modellonet": "modellonet"}
#: The literature's column -> our metric (src/metrics.py).
METRICS = {"RRE": ERROR_R, "RTE": ERROR_T, "CD": MODIFIED_CHAMFER}
DECIMALS = {"RRE": 3, "RTE": 4, "CD": 5}
UNITS = {"RRE": " (°)"}
PUBLISHED = Path(__file__).with_name("published") / "modelnet.csv"
PUBLISHED_COLUMNS = ("protocol", "method", "metric", "value", "source", "checked")
#: What a published value's ``checked`` says in the table's note (``benchmarks/tables/published/README.md``).
CHECKED_NOTES = {"yes": "", "listing": " (as on a public benchmark listing; not yet read in the paper's table)",
                 "no": " (not yet checked against the source)"}
COLUMNS = pd.MultiIndex.from_tuples([(PROTOCOLS[p], m) for p in PROTOCOLS for m in METRICS])
LEARNED_MARK = " †"


def load_published(path: str | Path = PUBLISHED) -> pd.DataFrame:
    """The published values (:data:`PUBLISHED_COLUMNS`), checked: known protocols and metrics, a source each."""
    frame = pd.read_csv(path)
    missing = [c for c in PUBLISHED_COLUMNS if c not in frame.columns]
    if missing:
        raise ValueError(f"{path}: the published values lack the columns {missing}")
    bad = frame[~frame["protocol"].isin(list(PROTOCOLS)) | ~frame["metric"].isin(list(METRICS))
                | frame["source"].isna() | frame["value"].isna()]
    if len(bad):
        raise ValueError(f"{path}: row {int(bad.index[0]) + 2} needs a protocol of {list(PROTOCOLS)}, a metric of "
                         f"{list(METRICS)}, a value and a source")
    return frame


def our_rows(tidy: pd.DataFrame) -> pd.DataFrame:
    """Our values as the table's rows (index: method label, † for a learned method; :data:`COLUMNS`); a cell
    without a value is NaN. Rows in the grid's order."""
    frame = tidy[tidy["experiment"].isin(list(EXPERIMENT_PROTOCOL)) & tidy["metric"].isin(list(METRICS.values()))]
    if frame.empty:
        raise ValueError(f"no row of the grid is one of the experiments {sorted(EXPERIMENT_PROTOCOL)} with the metrics "
                         f"{sorted(METRICS.values())}")
    name_of = {ours: name for name, ours in METRICS.items()}
    ids = frame["method_id"] if "method_id" in frame else frame["method"]
    labels = [f"{label}{LEARNED_MARK if (m := find_method(key)) and m.kind == 'learned' else ''}"
              for label, key in zip(frame["method"], ids)]
    cells = pd.DataFrame({"method": labels, "protocol": frame["experiment"].map(EXPERIMENT_PROTOCOL).map(PROTOCOLS),
                          "metric": frame["metric"].map(name_of), "value": frame["value"].astype(float)})
    if cells.duplicated(["method", "protocol", "metric"]).any():
        raise ValueError("several experiments of one protocol in the grid: give one of each")
    wide = cells.pivot(index="method", columns=["protocol", "metric"], values="value")
    return wide.reindex(index=list(dict.fromkeys(labels)), columns=COLUMNS)


def published_rows(published: pd.DataFrame) -> pd.DataFrame:
    """The published values as rows (index: ``<method> (paper)``; :data:`COLUMNS`)."""
    cells = published.assign(protocol=published["protocol"].map(PROTOCOLS), row=published["method"] + " (paper)")
    wide = cells.pivot(index="row", columns=["protocol", "metric"], values="value")
    return wide.reindex(index=list(dict.fromkeys(cells["row"])), columns=COLUMNS)


def source_notes(published: pd.DataFrame) -> list[str]:
    """One note per source and way it was checked: ``<methods>: <source><how checked>`` (methods in order)."""
    checked = published["checked"].astype(str).str.lower().where(published["checked"].notna(), "no")
    groups = published.assign(checked=checked).groupby(["source", "checked"], sort=False)["method"]
    return [f"{', '.join(dict.fromkeys(methods))}: {source}{CHECKED_NOTES.get(how, CHECKED_NOTES['no'])}"
            for (source, how), methods in groups]


def _tex(text: str) -> str:
    return latex_escape(text).replace("†", r"$^\dagger$")


def _fmt(value: float, metric: str) -> str:
    return "--" if value is None or math.isnan(value) else f"{value:.{DECIMALS[metric]}f}"


def _best(ours: pd.DataFrame) -> dict[tuple[str, str], float]:
    return {column: ours[column].min() for column in COLUMNS if ours[column].notna().any()}


def to_markdown(ours: pd.DataFrame, paper: pd.DataFrame, caption: str, notes: Sequence[str]) -> str:
    best = _best(ours)
    header = ["Method"] + [f"{p} {m}{UNITS.get(m, '')}" for p, m in COLUMNS]
    lines = [f"**{caption}**", "", "| " + " | ".join(header) + " |", "|" + "|".join([":---"] + ["---:"] * len(COLUMNS)) + "|"]
    for label, row in ours.iterrows():
        cells = [f"**{_fmt(row[c], c[1])}**" if best.get(c) == row[c] else _fmt(row[c], c[1]) for c in COLUMNS]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    for label, row in paper.iterrows():
        cells = [_fmt(row[c], c[1]) if math.isnan(row[c]) else f"*{_fmt(row[c], c[1])}*" for c in COLUMNS]
        lines.append(f"| *{label}* | " + " | ".join(cells) + " |")
    return "\n".join(lines + [""] + [f"- {note}" for note in notes]) + "\n"


def to_latex(ours: pd.DataFrame, paper: pd.DataFrame, caption: str, notes: Sequence[str], standalone: bool = False) -> str:
    best = _best(ours)
    k = len(METRICS)
    lines = ["% generated by python -m benchmarks.tables.literature"]
    if not standalone:
        lines.append(FRAGMENT_NEEDS)
    if standalone:
        lines += [r"\documentclass{article}", r"\usepackage[margin=1.5cm,landscape]{geometry}",
                  *(f"\\usepackage{{{package}}}" for package in LATEX_PACKAGES), r"\begin{document}"]
    lines += [r"\begin{table*}[t]", r"\centering", r"\resizebox{\linewidth}{!}{%",
              f"\\begin{{tabular}}{{l*{{{len(COLUMNS)}}}{{c}}}}", r"\toprule",
              " & ".join(["Method"] + [f"\\multicolumn{{{k}}}{{c}}{{{p}}}" for p in PROTOCOLS.values()]) + r" \\",
              " ".join(f"\\cmidrule(lr){{{2 + i * k}-{1 + (i + 1) * k}}}" for i in range(len(PROTOCOLS))),
              " & ".join([""] + [m + (" ($^\\circ$)" if m in UNITS else "") for _, m in COLUMNS]) + r" \\", r"\midrule"]
    for label, row in ours.iterrows():
        cells = [f"\\textbf{{{_fmt(row[c], c[1])}}}" if best.get(c) == row[c] else _fmt(row[c], c[1]) for c in COLUMNS]
        lines.append(" & ".join([_tex(str(label))] + cells) + r" \\")
    if len(paper):
        lines.append(r"\midrule")
    for label, row in paper.iterrows():
        cells = [_fmt(row[c], c[1]) if math.isnan(row[c]) else f"\\textit{{{_fmt(row[c], c[1])}}}" for c in COLUMNS]
        lines.append(" & ".join([f"\\textit{{{latex_escape(str(label))}}}"] + cells) + r" \\")
    text = _tex(" ".join([caption, *notes]))
    lines += [r"\bottomrule", r"\end{tabular}%", "}", f"\\caption{{{text}}}",
              r"\label{tab:modelnet_literature}", r"\end{table*}"]
    if standalone:
        lines.append(r"\end{document}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.tables.literature", description=__doc__.split("\n\n")[0])
    parser.add_argument("inputs", nargs="+", help="tidy tables of a grid (results.csv / results.parquet)")
    parser.add_argument("--out", required=True, help="output prefix: <out>.csv, .md, .tex, _standalone.tex (.pdf)")
    parser.add_argument("--published", default=str(PUBLISHED), help="the published values (default: %(default)s)")
    parser.add_argument("--caption", default="Partial ModelNet40 protocol of Predator and RegTR: mean RRE, RTE and "
                        "RPM-Net's modified Chamfer distance (CD) over the test pairs; ours, then the published values.")
    parser.add_argument("--note", action="append", default=[], help="a note under the table (repeatable)")
    parser.add_argument("--compile", action="store_true", help="compile the standalone document with pdflatex")
    args = parser.parse_args(argv)
    from benchmarks.tables.latex_check import check_latex, compile_latex

    try:
        ours, paper = our_rows(read_inputs(args.inputs)), load_published(args.published)
    except (OSError, ValueError, UserError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    paper_rows = published_rows(paper)
    notes = [*args.note, "Published values (paper rows, in italics): " + "; ".join(source_notes(paper))]
    if any(label.endswith(LEARNED_MARK) for label in ours.index):
        notes.append("† learned; its weights as the grid's config names them.")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    frame = pd.concat({"ours": ours, "paper": paper_rows}, names=["source", "method"])
    frame.to_csv(out.with_suffix(".csv"))
    out.with_suffix(".md").write_text(to_markdown(ours, paper_rows, args.caption, notes))
    fragment, document = (to_latex(ours, paper_rows, args.caption, notes, standalone) for standalone in (False, True))
    problems = check_latex(fragment)
    if problems:
        print("error: " + problems[0], file=sys.stderr)
        return 2
    out.with_suffix(".tex").write_text(fragment)
    standalone_path = out.parent / f"{out.name}_standalone.tex"
    standalone_path.write_text(document)
    written = [out.with_suffix(s) for s in (".csv", ".md", ".tex")] + [standalone_path]
    if args.compile:
        ok, reason = compile_latex(document, out.with_suffix(".pdf"))
        if not ok:
            print(f"error: not compiled ({reason})", file=sys.stderr)
            return 2
        written.append(out.with_suffix(".pdf"))
    print("wrote " + ", ".join(map(str, written)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
