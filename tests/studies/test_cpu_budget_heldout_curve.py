"""benchmarks.studies.cpu_budget.heldout_curve: test points placed at the CPU hours of their step, beside a grid's row."""

import json

import pandas as pd
import pytest
import torch

from benchmarks.studies.cpu_budget import heldout_curve as tc
from src.utils.errors import ConfigError


def _run(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "csv" / "version_0").mkdir(parents=True)
    pd.DataFrame([{"step": 99, "time/cpu_hours": 1.0, "val/Error(R)": 20.0},
                  {"step": 199, "time/cpu_hours": 2.0, "val/Error(R)": 10.0},
                  {"step": 299, "time/cpu_hours": 4.0, "val/Error(R)": 8.0}]).to_csv(
        run_dir / "csv" / "version_0" / "metrics.csv", index=False)
    checkpoints = []
    for step in (249, 149):
        path = tmp_path / f"best-{step + 1}.ckpt"
        torch.save({"global_step": step}, path)
        checkpoints.append(path)
    grid = tmp_path / "results.csv"
    pd.DataFrame([{"method": m, "experiment": e, "metric": "Error(R)", "value": v}
                  for m, e, v in (("ICP", "unseen_categories", 8.5), ("ICP", "unseen_shapes", 10.0),
                                  ("FGR", "unseen_categories", 2.0))]).to_csv(grid, index=False)
    return run_dir, checkpoints, grid


def test_each_checkpoint_is_tested_once_and_drawn_at_the_cpu_hours_of_its_step(tmp_path, monkeypatch):
    run_dir, checkpoints, grid = _run(tmp_path)
    evaluated = []

    def fake_eval(checkpoint, overrides, work):
        evaluated.append(checkpoint.name)
        step = tc.checkpoint_step(checkpoint)
        return {"metrics": {"Error(R)": 2000.0 / step, "Error(t)": 0.1}}

    monkeypatch.setattr(tc, "evaluate", fake_eval)
    out = tmp_path / "out"
    assert tc.main(["--run", str(run_dir), "--checkpoints", *map(str, checkpoints), "--eval", "+exp=unseen_categories",
                    "--grid", str(grid), "--experiment", "unseen_categories", "--work", str(tmp_path / "w"),
                    "--out", str(out)]) == 0
    curve = pd.read_csv(out / "test_curve.csv")
    assert list(curve["step"]) == [149, 249] and evaluated == ["best-250.ckpt", "best-150.ckpt"]
    assert curve["cpu_hours"].tolist() == pytest.approx([1.5, 3.0])  # halfway between the logged rows
    assert curve["Error(R)"].tolist() == pytest.approx([2000 / 149, 2000 / 249])
    assert (out / "test_curve.png").stat().st_size > 0 and len(pd.read_csv(out / "validation_curve.csv")) == 3


def test_evaluation_is_reused_and_the_reference_row_must_be_one(tmp_path):
    record = tmp_path / "w" / "best-150" / "metrics.json"
    record.parent.mkdir(parents=True)
    record.write_text(json.dumps({"metrics": {"Error(R)": 3.0}}))
    assert tc.evaluate(tmp_path / "best-150.ckpt", [], tmp_path / "w")["metrics"]["Error(R)"] == 3.0  # no src.eval run
    _, _, grid = _run(tmp_path)
    assert tc.reference_error(grid, "ICP", "unseen_shapes") == 10.0
    with pytest.raises(ConfigError, match="0 Error\\(R\\) rows of 'Go-ICP'"):
        tc.reference_error(grid, "Go-ICP", "unseen_categories")
