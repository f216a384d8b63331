"""benchmarks/plots/figures.py on a tiny generated scan set: a PNG with the right panels."""

from __future__ import annotations

from pathlib import Path

import pytest

from hydra import compose, initialize_config_dir

from benchmarks.plots.figures import main, pick_pairs
from benchmarks.grid.run import run_grid
from src.utils.errors import ConfigError
from src.models.pretrained import SHIPPED_DIR
from src.utils.paths import REPO_ROOT
from tests.helpers.scan_helpers import write_scan_set

OMNET = next(SHIPPED_DIR.glob("omnet*.ckpt"), None)


@pytest.mark.skipif(OMNET is None, reason="no shipped OMNet checkpoint")
def test_figure_of_two_pairs_has_alignment_and_mask_panels(tmp_path, capsys):
    scans = write_scan_set(tmp_path / "scans")
    out = tmp_path / "figure.png"
    code = main([f"data.source={scans}", "data.pair.num_points=64", "data.pair.min_overlap=0.5", "--pairs", "0,1",
                 "--methods", "identity,icp,omnet", "--checkpoint", str(OMNET), "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size < 1_000_000
    # per pair: source, reference, ground truth, 3 methods; then 4 iterations + truth, on source and reference
    assert "(32 panels" in printed


def test_pick_worst_median_best():
    errors = {3: 10.0, 5: 1.0, 7: 50.0, 9: 5.0}
    assert pick_pairs(errors, ["worst", "median", "best"]) == {7: "worst", 3: "median", 5: "best"}
    assert pick_pairs({1: 2.0}, ["worst", "best"]) == {1: "worst"}
    with pytest.raises(ConfigError, match="--pick takes worst, median, best"):
        pick_pairs(errors, ["middle"])


def test_pairs_picked_from_a_grid_cell(tmp_path, capsys):
    data = [f"data.source={write_scan_set(tmp_path / 'scans')}", "data.pair.num_points=64", "data.pair.min_overlap=0.5"]
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("benchmark_grid", overrides=[
            "+benchmark=scan_pairs", "benchmark.methods=[identity]", "benchmark.overrides=[" + ",".join(f'"{o}"' for o in data) + "]",
            "workers=0", "progress=false", "paper=false", f"output_dir={tmp_path / 'grid'}"])
    errors = run_grid(cfg).pairs.set_index("pair")["Error(R)"]
    args = [*data, "--grid", str(tmp_path / "grid"), "--pick", "worst,best", "--methods", "identity", "--out", str(tmp_path / "f.png")]
    assert main([*args, "--by", "identity"]) == 0 and "(8 panels" in capsys.readouterr().out  # 2 pairs x 4 panels
    assert errors.idxmax() != errors.idxmin()
    assert main([*args, "--by", "icp"]) == 2
    assert "has no icp cell on scan_pairs/ts/prnet" in capsys.readouterr().err


def test_bad_pair_index_is_one_error_line(tmp_path, capsys):
    scans = write_scan_set(tmp_path / "scans")
    code = main([f"data.source={scans}", "data.pair.min_overlap=0.5", "--pairs", "2", "--methods", "identity",
                 "--out", str(tmp_path / "f.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --pairs 2: the test set scan_pairs/ts/prnet has pairs 0..1") and err.count("\n") == 1
    assert not Path(tmp_path / "f.png").exists()
