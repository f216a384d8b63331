"""benchmarks.tables --compile with a stand-in pdflatex (no TeX needed): the PDF is kept, a missing
package is named in one line; the fragment names what it needs."""

import os
import stat
from pathlib import Path

import pandas as pd
import pytest

from benchmarks.tables.latex_check import check_latex, latex_failure
from benchmarks.tables.render import LATEX_PACKAGES, build_table, main, to_latex

MISSING_BOOKTABS = "! LaTeX Error: File `booktabs.sty' not found.\n\nType X to quit or <RETURN> to proceed,"


def _fake_pdflatex(folder: Path, fails: bool) -> None:
    """A ``pdflatex`` on PATH that writes table.pdf, or prints TeX's missing-package error and fails."""
    folder.mkdir()
    (folder / "log.txt").write_text(MISSING_BOOKTABS)
    script = folder / "pdflatex"
    body = f"cat '{folder / 'log.txt'}'; exit 1" if fails else "printf '%%PDF-1.5 fake' > table.pdf"
    script.write_text(f"#!/bin/sh\n{body}\n")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)


def _frame(tmp_path: Path) -> Path:
    rows = [dict(method=m, experiment="unseen_shapes", sampling=s, partial="prnet", metric="Error(R)", value=v)
            for m, v in (("ICP", 3.0), ("OMNet", 1.0)) for s in ("os", "ts")]
    pd.DataFrame(rows).to_csv(tmp_path / "ours.csv", index=False)
    return tmp_path / "ours.csv"


@pytest.mark.parametrize("fails", [False, True])
def test_compile_keeps_the_pdf_or_names_the_missing_package(tmp_path, monkeypatch, capsys, fails):
    _fake_pdflatex(tmp_path / "bin", fails)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    out = tmp_path / "t"
    code = main([str(_frame(tmp_path)), "--metrics", "Error(R)", "--out", str(out), "--compile"])
    captured = capsys.readouterr()
    pdf = out / "table1_standalone.pdf"
    if not fails:
        assert code == 0 and pdf.read_bytes().startswith(b"%PDF") and str(pdf) in captured.out
        return
    errors = captured.err.strip().splitlines()
    assert code == 1 and not pdf.exists() and len(errors) == 1, errors
    assert "the LaTeX package booktabs is not installed (booktabs.sty not found)" in errors[0]
    assert "tlmgr install booktabs" in errors[0] and errors[0].startswith("error: ")


def test_latex_failure_without_a_missing_package_gives_the_first_error_line():
    assert latex_failure("This is pdfTeX\n! Undefined control sequence.\nl.12 \\foo\n") == "! Undefined control sequence."
    assert latex_failure("no errors here") == "pdflatex failed (no error line in its log)"


def test_a_fragment_names_the_packages_it_needs_and_the_standalone_document_loads_them(tmp_path):
    table = build_table(pd.read_csv(_frame(tmp_path)), metrics=["Error(R)"])
    fragment, document = to_latex(table), to_latex(table, standalone=True)
    needs = fragment.splitlines()[1]
    assert needs.startswith("%") and all(package in needs for package in LATEX_PACKAGES)
    assert all(f"\\usepackage{{{package}}}" in document for package in LATEX_PACKAGES)
    assert check_latex(fragment) == [] and check_latex(document) == []


def test_compile_without_pdflatex_is_one_error_line_and_writes_nothing(tmp_path, monkeypatch, capsys):
    """It exited 0 after a note, having written results/ into the working directory."""
    (tmp_path / "bin").mkdir()
    monkeypatch.setenv("PATH", str(tmp_path / "bin"))
    frame = _frame(tmp_path)
    code = main([str(frame), "--metrics", "Error(R)", "--compile"])
    errors = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(errors) == 1 and errors[0].startswith("error: --compile needs pdflatex")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin", "ours.csv"]


def test_tables_go_beside_the_frame_they_were_made_from(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the old default wrote results/tables here
    (tmp_path / "grid").mkdir()
    frame = _frame(tmp_path / "grid")
    assert main([str(frame), "--metrics", "Error(R)"]) == 0
    assert {"table1.tex", "table1.md"} <= {p.name for p in frame.parent.iterdir()}
    assert not (tmp_path / "results").exists()
