"""benchmarks.tables.literature: the partial-ModelNet literature's table from a grid's tidy rows and the published values."""

import math

import pandas as pd
import pytest

from benchmarks.tables import literature
from benchmarks.tables.latex_check import check_latex
from src.metrics import ERROR_R, ERROR_T, MODIFIED_CHAMFER
from tests.helpers.markdown import markdown_table


def _tidy() -> pd.DataFrame:
    rows = []
    for method, method_id, base in (("ICP", "icp", 1.0), ("OMNet", "omnet", 2.0)):
        for experiment, scale in (("real_airplane_modelnet", 1.0), ("real_airplane_modellonet", 3.0)):
            for metric, unit in ((ERROR_R, 1.0), (ERROR_T, 0.01), (MODIFIED_CHAMFER, 0.001), ("RMSE(R)", 9.0)):
                rows.append({"method": method, "method_id": method_id, "experiment": experiment, "sampling": "OS",
                             "partial": "rpmnet", "metric": metric, "value": base * scale * unit})
    rows.append({**rows[0], "experiment": "real_airplane", "value": 99.0})  # another protocol's row: left out
    return pd.DataFrame(rows)


def _published(tmp_path, rows=None):
    path = tmp_path / "published.csv"
    pd.DataFrame(rows or [
        {"protocol": "modelnet", "method": "RegTR", "metric": "RRE", "value": 1.5, "source": "Paper A, Table 1", "checked": "yes"},
        {"protocol": "modellonet", "method": "RegTR", "metric": "CD", "value": 0.004, "source": "Paper A, Table 1", "checked": "yes"},
    ]).to_csv(path, index=False)
    return path


def test_our_rows_map_protocols_and_metrics():
    ours = literature.our_rows(_tidy())
    assert list(ours.index) == ["ICP", "OMNet †"]  # learned methods marked
    assert ours.loc["ICP", ("ModelNet", "RRE")] == 1.0 and ours.loc["ICP", ("ModelLoNet", "RRE")] == 3.0
    assert ours.loc["OMNet †", ("ModelLoNet", "RTE")] == pytest.approx(0.06)
    assert ours.loc["OMNet †", ("ModelNet", "CD")] == pytest.approx(0.002)
    assert list(ours.columns) == list(literature.COLUMNS)


def test_bad_published_rows_are_refused(tmp_path):
    with pytest.raises(ValueError, match="source"):
        literature.load_published(_published(tmp_path, [{"protocol": "modelnet", "method": "X", "metric": "RRE",
                                                          "value": 1.0, "source": None, "checked": "no"}]))
    with pytest.raises(ValueError, match="protocol"):
        literature.load_published(_published(tmp_path, [{"protocol": "kitti", "method": "X", "metric": "RRE",
                                                          "value": 1.0, "source": "S", "checked": "no"}]))


def test_source_notes_name_every_method_of_a_source_and_how_it_was_checked():
    published = pd.DataFrame([
        {"protocol": "modelnet", "method": "RegTR", "metric": "RRE", "value": 1.5, "source": "Paper A, Table 1", "checked": "yes"},
        {"protocol": "modelnet", "method": "RPM-Net", "metric": "RRE", "value": 1.7, "source": "Paper A, Table 1", "checked": "yes"},
        {"protocol": "modellonet", "method": "RegTR", "metric": "RRE", "value": 3.9, "source": "Paper A, Table 1", "checked": "yes"},
        {"protocol": "modelnet", "method": "Predator", "metric": "RRE", "value": 1.8, "source": "Listing B", "checked": "listing"},
        {"protocol": "modelnet", "method": "X", "metric": "CD", "value": 0.1, "source": "Paper C", "checked": None},
    ])
    assert literature.source_notes(published) == [
        "RegTR, RPM-Net: Paper A, Table 1",
        "Predator: Listing B" + literature.CHECKED_NOTES["listing"],
        "X: Paper C" + literature.CHECKED_NOTES["no"],
    ]


def test_bathtub_stand_ins_map_to_the_protocols():
    tidy = _tidy()
    tidy["experiment"] = tidy["experiment"].str.replace("airplane", "bathtub")
    ours = literature.our_rows(tidy)
    assert ours.loc["ICP", ("ModelNet", "RRE")] == 1.0 and ours.loc["ICP", ("ModelLoNet", "RRE")] == 3.0


def test_shipped_published_values_name_their_sources():
    published = literature.load_published()
    assert published["source"].str.len().min() > 10 and set(published["checked"]) <= {"yes", "listing", "no"}


def test_command_writes_the_table_with_the_published_values_beside_ours(tmp_path):
    results = tmp_path / "results.csv"
    _tidy().to_csv(results, index=False)
    out = tmp_path / "table"
    assert literature.main([str(results), "--out", str(out), "--published", str(_published(tmp_path))]) == 0
    _, table = markdown_table(out.with_suffix(".md").read_text())
    assert list(table["Method"]) == ["ICP", "OMNet †", "*RegTR (paper)*"]
    assert table.loc[0, "ModelNet RRE (°)"] == "**1.000**"  # the best of ours in bold
    assert table.loc[1, "ModelLoNet RTE"] == "0.0600"
    assert table.loc[2, "ModelNet RRE (°)"] == "*1.500*" and table.loc[2, "ModelLoNet CD"] == "*0.00400*"
    assert table.loc[2, "ModelNet RTE"] == "--"
    text = out.with_suffix(".md").read_text()
    assert "Paper A, Table 1" in text and "† learned" in text
    frame = pd.read_csv(out.with_suffix(".csv"), header=[0, 1], index_col=[0, 1])
    assert frame.loc[("paper", "RegTR (paper)"), ("ModelNet", "RRE")] == 1.5
    assert math.isnan(frame.loc[("paper", "RegTR (paper)"), ("ModelNet", "CD")])
    for tex in (out.with_suffix(".tex"), tmp_path / "table_standalone.tex"):
        assert check_latex(tex.read_text()) == []
    assert r"\textit{1.500}" in out.with_suffix(".tex").read_text()


def test_command_refuses_a_grid_without_the_protocols(tmp_path, capsys):
    results = tmp_path / "results.csv"
    _tidy().assign(experiment="real_airplane").to_csv(results, index=False)
    assert literature.main([str(results), "--out", str(tmp_path / "t"), "--published", str(_published(tmp_path))]) == 2
    assert capsys.readouterr().err.startswith("error: no row of the grid")
