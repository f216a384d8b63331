"""The scripts of examples/ run as documented (as subprocesses, with small arguments) and print real results."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from baselines.testing import euler_transform, make_pair
from tests.helpers.paths import ROOT

EXAMPLES = ROOT / "examples"
NUMBER = r"(-?\d+\.\d+)"


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("examples_cache")  # the synthetic data is built there on first use


def run_example(name: str, *args: str, cache: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMNET_CACHE_DIR": str(cache), "OMP_NUM_THREADS": "1"}
    result = subprocess.run([sys.executable, str(EXAMPLES / name), *args], cwd=ROOT, env=env, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def floats(pattern: str, text: str) -> list[float]:
    values = [float(v) for v in re.findall(pattern, text)]
    assert values and all(math.isfinite(v) for v in values), (pattern, text)
    return values


def test_every_example_has_a_docstring_saying_how_to_run_it():
    scripts = sorted(EXAMPLES.glob("*.py"))
    assert len(scripts) >= 3
    for script in scripts:
        text = script.read_text()
        assert text.startswith('"""') and f"python examples/{script.name}" in text, script.name
        assert len(text.splitlines()) <= 60, f"{script.name}: an example is short"


def test_register_pair_recovers_the_built_in_transform(cache_dir):
    out = run_example("register_pair.py", "--method", "icp", "--points", "400", cache=cache_dir)
    assert "method: icp" in out and "(400 -> 400 points)" in out
    rows = [line for line in out.splitlines() if line.strip().startswith("[")]
    assert len(rows) == 4 and rows[-1].split() == ["[", "0.", "0.", "0.", "1.", "]]"]  # a 4x4 rigid transform
    (rot_err,) = floats(rf"Error\(R\): {NUMBER} deg", out)
    (trans_err,) = floats(rf"Error\(t\): {NUMBER}", out)
    assert rot_err < 5.0 and trans_err < 0.1  # the truth is 30°/20°/10°: ICP recovers it, the identity would not
    assert 0.0 < floats(rf"fitness: {NUMBER}", out)[0] <= 1.0


def test_register_pair_reads_files(tmp_path, cache_dir):
    src, ref = make_pair(euler_transform((10.0, 0.0, 5.0), (0.1, 0.0, 0.0)), 300, seed=3)
    np.savetxt(tmp_path / "a.xyz", src)
    np.savetxt(tmp_path / "b.xyz", ref)
    out = run_example("register_pair.py", "--src", str(tmp_path / "a.xyz"), "--ref", str(tmp_path / "b.xyz"),
                      cache=cache_dir)
    assert "(300 -> 300 points)" in out and "Error(R)" not in out  # no truth is known for files
    assert floats(rf"inlier RMSE: {NUMBER}", out)[0] < 0.01  # the same points moved: aligned exactly


def test_evaluate_checkpoint_scores_the_shipped_model_and_icp(cache_dir):
    out = run_example("evaluate_checkpoint.py", "--pairs", "4", cache=cache_dir)
    assert "omnet_unseen_categories_synthetic_ts_prnet: unseen_categories on synthetic (ts, prnet), 4 test pairs" in out
    for label in ("ICP", "OMNet"):
        line = next(line for line in out.splitlines() if line.startswith(label))
        rot, trans, rmse, ms = floats(NUMBER, line)
        assert 0.0 < rot < 180.0 and 0.0 < trans < 2.0 and rmse > 0.0 and ms > 0.0, line


def test_small_grid_writes_its_tables(tmp_path, cache_dir):
    out_dir = tmp_path / "grid"
    out = run_example("small_grid.py", "--methods", "icp", "--pairs", "2", "--out", str(out_dir), cache=cache_dir)
    assert "4 cells (4 computed, 0 reused)" in out  # ICP and the identity row x OS/TS
    table = (out_dir / "table.md").read_text()
    icp = next(line for line in table.splitlines() if line.startswith("| ICP"))
    assert len(floats(NUMBER, icp)) == 12  # six metrics x OS/TS
    assert "Identity (no registration)" in table and (out_dir / "results.csv").is_file()
    assert "\\begin{table*}" in (out_dir / "table.tex").read_text()
    again = run_example("small_grid.py", "--methods", "icp", "--pairs", "2", "--out", str(out_dir), cache=cache_dir)
    assert "4 cells (0 computed, 4 reused)" in again and (out_dir / "table.md").read_text() == table
