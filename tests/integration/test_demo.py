"""benchmarks.demo on a tiny trained run: the run's own test set, the rows, the files, the errors."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from benchmarks.demo import (
    IDENTITY_LABEL,
    Entry,
    Run,
    data_overrides,
    find_run,
    load_run,
    main,
    own_test_pairs,
    pipeline_check_note,
    precision_note,
    run_demo,
)
from benchmarks.tables.latex_check import check_latex, tabular_rows, tabulars
from src.eval import evaluate
from src.models.pretrained import export
from src.run.resume import best_checkpoint
from src.train import train
from tests.helpers.markdown import markdown_table
from tests.helpers.registration_helpers import TINY, compose_config, tiny_config


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A 2-step run trained in bf16-mixed, forced: trainer.precision=auto trains in bf16 on some CPU kinds and in
    float32 on others, so the comparisons below (the demo's rows, src.eval, the run's own test: all in float32)
    hold on every CPU only if they hold for a bf16-trained run (here bf16 is emulated: slower, same numbers)."""
    tmp = tmp_path_factory.mktemp("demo")
    train(tiny_config(tmp, "+exp=unseen_shapes", "trainer.max_steps=2", "trainer.val_check_interval=1",
                      "trainer.check_val_every_n_epoch=null", "trainer.limit_val_batches=1", "trainer.limit_test_batches=1",
                      "trainer.precision=bf16-mixed", "force_precision=true"))
    return tmp / "run"


def _shipped_for_other_experiment(run_dir: Path, folder: Path) -> Path:
    """The tiny run exported as a shipped checkpoint whose card says it was trained for unseen_categories."""
    export(run_dir, "tiny_uc", folder)
    card_path = folder / "tiny_uc.json"
    card = json.loads(card_path.read_text())
    card["experiment"]["task"] = "unseen_categories"
    card_path.write_text(json.dumps(card))
    return folder


def _rows(tex: str) -> dict[str, list[str]]:
    """The LaTeX table's body rows by label (header aside)."""
    (_, body), = tabulars(tex)
    rows = tabular_rows(body)
    return {row[0]: row[1:] for row in rows if row[0] != "Method"}


def test_demo_compares_five_methods_on_the_runs_own_test_pairs(run_dir, tmp_path, capsys):
    shipped = _shipped_for_other_experiment(run_dir, tmp_path / "shipped")
    markdown, latex = run_demo(run_dir, shipped_dir=shipped)
    assert (markdown, latex) == (run_dir / "demo.md", run_dir / "demo.tex")
    tex, md = latex.read_text(), markdown.read_text()
    assert check_latex(tex) == []
    rows = _rows(tex)
    step = json.loads((run_dir / "metrics.json").read_text())["checkpoint"].rsplit("-", 1)[1].split(".")[0]
    mine, shipped_row = (f"OMNet ({who}: best at step {step} of 2, width 0.0625)" for who in ("this run", "shipped"))
    assert list(rows) == ["Identity (no registration)", "ICP", "FGR", shipped_row, mine]
    assert all(len(values) == 4 for values in rows.values())  # Error(R), Error(t), RMSE(R), ms/pair
    _, table = markdown_table(md)
    assert table.columns.tolist() == ["Method", "Error(R) (°) ↓", "Error(t) ↓", "RMSE(R) (°) ↓", "ms/pair ↓"]
    cells = {row[0]: [re.sub(r"^\*\*(.*)\*\*$|^<u>(.*)</u>$", r"\1\2", cell) for cell in row[1:]]
             for row in table.values.tolist()}
    assert cells == {label: [re.sub(r"^\\(?:textbf|underline)\{(.*)\}$", r"\1", cell) for cell in values]
                     for label, values in rows.items()}  # the same methods and numbers as the LaTeX table
    assert "the 2 test pairs" in md and "the first 2 of the test set's 7 pairs, those the run was tested on" in md
    assert "trained for task=unseen_categories" in md and "synthetic data" in md
    assert "Lower is better" in md

    # the run's own row repeats the run's own test (its first batch of 2 pairs): the same test set, and the same
    # float32 computation although the run trained in bf16
    results = json.loads((run_dir / "metrics.json").read_text())
    expected = results["metrics"]
    assert float(rows[mine][0]) == pytest.approx(expected["Error(R)"], abs=1e-3)
    assert float(rows[mine][1]) == pytest.approx(expected["Error(t)"], abs=1e-4)
    assert (results["trained_precision"], results["test_precision"]) == ("bf16-mixed", "32-true")
    assert (f"precision: every row is evaluated in float32 (32-true); the learned rows were trained in bf16-mixed "
            f"({mine}), bf16-mixed ({shipped_row})") in md
    # the same weights shipped: the same numbers
    assert rows[shipped_row][:3] == rows[mine][:3]
    out = capsys.readouterr().out
    assert "Error(R)" in out and "ms/pair" in out and f"wrote {markdown}" in out


def test_without_a_shipped_checkpoint_its_row_is_left_out_with_a_note(run_dir, tmp_path):
    """Also: every test pair (demo.pairs=all), the same numbers as src.eval on them, and the identity's row
    kept when the user's benchmark.methods leaves it out."""
    (tmp_path / "none").mkdir()
    overrides = ["benchmark.methods=[]", "demo.pairs=all"]
    markdown, latex = run_demo(run_dir, overrides, shipped_dir=tmp_path / "none")
    rows = _rows(latex.read_text())
    assert [label.split(" (")[0] for label in rows] == ["Identity", "OMNet"]
    assert "no shipped checkpoint" in markdown.read_text() and "the 7 test pairs" in markdown.read_text()
    expected = evaluate(compose_config(*TINY, f"data.cache_root={run_dir.parent / 'cache'}", "+exp=unseen_shapes",
                                       f"output_dir={run_dir.parent / 'eval'}", f"ckpt_path={best_checkpoint(run_dir)}"))
    mine = next(values for label, values in rows.items() if label.startswith("OMNet"))
    assert float(mine[0]) == pytest.approx(expected["Error(R)"], abs=1e-3)
    assert float(mine[2]) == pytest.approx(expected["RMSE(R)"], abs=1e-3)
    assert json.loads((run_dir.parent / "eval" / "metrics.json").read_text())["test_precision"] == "32-true"


def test_a_table_says_when_its_models_were_not_all_trained_in_float32():
    assert precision_note({"A (this run)": "32-true", "A (shipped)": "32-true"}) is None
    assert precision_note({"A (this run)": "bf16-mixed", "A (shipped)": "unrecorded"}) == (
        "precision: every row is evaluated in float32 (32-true); the learned rows were trained in bf16-mixed "
        "(A (this run)), unrecorded (A (shipped))")


def test_data_overrides_recompose_the_runs_test_set(tmp_path):
    cfg = compose_config("+exp=unseen_shapes", "data=synthetic", "sampling=os", "data.pair.noise_sigma=0.02",
                         "data.build.num_samplings=3", "data.batch_size=5", f"data.cache_root={tmp_path / 'a b'}",
                         f"output_dir={tmp_path}")
    overrides = data_overrides(Run(tmp_path, cfg, "unseen_shapes", tmp_path / "best.ckpt"))
    assert sorted(overrides) == sorted(["data.pair.noise_sigma=0.02", "data.build.num_samplings=3",
                                        f"data.cache_root='{tmp_path / 'a b'}'"])  # loader settings aside


@pytest.mark.parametrize("limit, pairs", [(1, 2), (3, 6), (1.0, None), (0.5, 4), (0.1, 2)])
def test_tested_pairs_are_those_of_the_runs_own_test(run_dir, limit, pairs):
    """Lightning's limit_test_batches: an int counts batches (of 2 here), a float a fraction of the 4 batches of 7 pairs."""
    run = load_run(run_dir)
    run.cfg.trainer.limit_test_batches = limit
    assert own_test_pairs(run, data_overrides(run)) == pairs


def _fake_run(folder: Path, checkpoint: str | None, started: float) -> Path:
    folder.mkdir(parents=True)
    (folder / "config_resolved.yaml").write_text("task_name: unseen_shapes\n")
    os.utime(folder / "config_resolved.yaml", (started, started))
    if checkpoint:
        (folder / "checkpoints").mkdir()
        (folder / "checkpoints" / checkpoint).write_bytes(b"")
    return folder


def test_find_run_takes_the_last_started_run_with_a_best_checkpoint(tmp_path):
    _fake_run(tmp_path / "unseen_shapes" / "old", "best-8.ckpt", 1_000)
    newest = _fake_run(tmp_path / "unseen_shapes" / "new", "best-16.ckpt", 2_000)
    _fake_run(tmp_path / "eval" / "no_checkpoint", None, 3_000)
    _fake_run(tmp_path / "train" / "last_only", "last.ckpt", 3_000)
    assert find_run(tmp_path) == newest


@pytest.mark.parametrize("case, message", [
    ("missing", "run directory .*missing does not exist"),
    ("no_runs", "no src.train run with a best checkpoint under .*no_runs/: train one first"),
    ("no_config", "is not a src.train run \\(no config_resolved.yaml\\)"),
    ("no_best", "has no best checkpoint"),
    ("threads", "--threads must be >= 1, got 0"),
])
def test_bad_runs_stop_with_one_error_line(tmp_path, capsys, case, message):
    import re

    if case == "no_runs":
        (tmp_path / case).mkdir()
        argv = ["--outputs", str(tmp_path / case)]
    else:
        if case == "no_config":
            (tmp_path / case).mkdir()
        elif case == "no_best":
            _fake_run(tmp_path / case, "last.ckpt", 1_000)
        argv = ["--run", str(tmp_path / case), *(["--threads", "0"] if case == "threads" else [])]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and re.search(message, err[0]), err


@pytest.mark.parametrize("override, message", [
    ("demo.pairs=some", "error: demo.pairs must be one of tested, all, got 'some'"),
    ("no_such_setting=1", "error: bad grid override in ['no_such_setting=1']: Could not override 'no_such_setting'"),
])
def test_bad_demo_settings_stop_with_one_error_line(run_dir, capsys, override, message):
    assert main(["--run", str(run_dir), override]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(message), err


def _tidy(errors: dict[str, float]):
    import pandas as pd

    return pd.DataFrame([{"method": label, "metric": "Error(R)", "value": value} for label, value in errors.items()])


@pytest.mark.parametrize("own, expected", [(80.0, "pipeline check"), (30.0, None)])
def test_a_run_that_does_not_beat_the_identity_is_labelled_a_pipeline_check(run_dir, own, expected):
    """With the shipped card: its budget, its CPU hours and the step its validation first beat the identity."""
    run = load_run(run_dir)
    mine = Entry("omnet", "OMNet (this run)")
    card = {"name": "shipped_x", "note": "... one thread, 1.5 CPU hours in two resumed runs ...",
            "training": {"steps_run": 600, "batch_size": 16,
                         "validation": [{"step": 199, "Error(R)": 50.0}, {"step": 399, "Error(R)": 35.0},
                                        {"step": 599, "Error(R)": 30.0}]}}
    note = pipeline_check_note(_tidy({IDENTITY_LABEL: 40.0, mine.label: own}), mine, run, card)
    if expected is None:
        assert note is None
        return
    assert note.startswith("OMNet (this run) is a pipeline check, not a result: 2 steps of batch 2")
    assert "(Error(R) 80.0° against the identity's 40.0°)" in note
    assert "the shipped one trained 600 steps of batch 16 (1.5 CPU-h)" in note
    assert "first fell below 40.0° after 400 steps" in note and "50.0° at 200, 35.0° at 400, 30.0° at 600" in note
    assert pipeline_check_note(_tidy({IDENTITY_LABEL: 40.0, mine.label: own}), mine, run, None).endswith("identity's 40.0°)")
