"""Tables rank honestly: every header states its unit and direction, and the identity (no registration) is a
reference row, first in its block and never bold or underlined, even where its error is the lowest."""

from __future__ import annotations

import pandas as pd

from benchmarks.grid.report import summary_table, write_tables
from benchmarks.tables.render import build_table, to_latex, to_markdown
from tests.helpers.markdown import markdown_table

IDENTITY = "Identity (no registration)"
# the identity has the lowest errors here, as it does in a block where every method fails
ERRORS = {IDENTITY: 1.0, "ICP": 5.0, "FGR": 3.0, "OMNet": 4.0}


def _tidy() -> pd.DataFrame:
    rows = [dict(method=method, experiment="unseen_shapes", sampling=sampling, partial="prnet", metric=metric,
                 value=value * scale, n_pairs=4, n_failed=0, seconds_per_pair=0.01, dataset="synthetic")
            for method, value in ERRORS.items() for sampling in ("os", "ts")
            for metric, scale in (("Error(R)", 10.0), ("Error(t)", 0.01), ("RMSE(R)", 8.0))]
    return pd.DataFrame(rows)


def test_the_identity_is_a_reference_never_ranked_and_headers_state_units_and_direction():
    table = build_table(_tidy(), "table1", metrics=["Error(R)", "Error(t)", "RMSE(R)"])
    _, frame = markdown_table(to_markdown(table))
    rows = frame.set_index("Method")
    assert list(rows.index[1:3]) == [IDENTITY, "ICP"]  # the block label, then the reference first
    assert all(not cell.startswith(("**", "<u>")) for cell in rows.loc[IDENTITY])
    assert set(rows.loc["FGR", rows.columns]) == {f"**{v}**" for v in ("30.000", "0.0300", "24.000")}
    assert set(rows.loc["OMNet", rows.columns]) == {f"<u>{v}</u>" for v in ("40.000", "0.0400", "32.000")}
    assert list(frame.columns[1:]) == [f"{h} {s}" for h in ("Error(R) (°) ↓", "Error(t) ↓", "RMSE(R) (°) ↓")
                                       for s in ("OS", "TS")]
    assert "Lower is better (↓) in every column" in table.caption
    assert f"{IDENTITY}: the reference, never ranked" in table.caption
    latex = to_latex(table)
    identity_line = next(line for line in latex.splitlines() if line.startswith("Identity"))
    assert "\\textbf" not in identity_line and "\\underline" not in identity_line
    assert "Error($\\mathbf{R}$) ($^\\circ$) $\\downarrow$" in latex and "↓" not in latex


def test_the_grid_report_tables_state_units_and_keep_the_identity_unranked(tmp_path):
    written = write_tables(_tidy(), tmp_path, paper=False)
    _, frame = markdown_table(written[0].read_text())
    assert all(not cell.startswith(("**", "<u>")) for cell in frame.set_index("Method").loc[IDENTITY])
    assert all(("↓" in header) for header in frame.columns[1:])
    header = summary_table(_tidy()).splitlines()[0].split()
    assert {"Error(R)", "(°)", "↓", "ms/pair"} <= set(header)


def test_the_grid_caption_comes_before_the_layouts_in_both_tables(tmp_path):
    markdown, latex = (path.read_text() for path in write_tables(_tidy(), tmp_path, paper=False, caption="Real shapes, 1 CPU hour each"))
    assert markdown.startswith("**Real shapes, 1 CPU hour each. Registration errors")
    assert "\\caption{Real shapes, 1 CPU hour each. Registration errors" in latex
