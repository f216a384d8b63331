"""Families of bad input found by a probe of new-user cases, checked without training: data that is not what
the record says, settings accepted but unused, results that misreport, tracebacks and misleading messages."""

from __future__ import annotations

import math
import signal

import numpy as np
import pandas as pd
import pytest
import torch

from baselines.result import check_threshold, inlier_fit
from benchmarks.tables import render as tables
from src.data.datamodule import RegistrationDataModule
from src.data.point_files import read_points
from src.data.prepare import prepare
from src.data.readers import _lines
from src.data.scan_pairs import dropped_pairs
from src.data.scans import parse_ply_points, read_scans, scan_pairs
from src.utils.errors import ConfigError, DatasetError, PointCloudError, exit_code_of
from src.geometry.clouds import MAX_COORDINATE, check_cloud
from src.models.omnet import OMNet
from src.run.recorded import refuse_unread_overrides, refuse_unknown_monitor
from src.run.reporting import refuse_non_finite_metrics
from src.validation import validate_config, validate_grid_config
from tests.helpers.registration_helpers import compose_config
from tests.helpers.scan_helpers import write_scan_set

# --- 1. scored data that is not what the record says --------------------------------------------------


def test_a_shape_whose_points_are_identical_is_refused_by_prepare(resampled_dir, tmp_path):
    (resampled_dir / "chair" / "chair_0001.txt").write_text("0.5,0.5,0.5,0,0,1\n" * 20)  # was: prepared and scored
    with pytest.raises(PointCloudError, match=r"^shape chair_0001: degenerate cloud, its 20 points are all the same"):
        prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path)


def test_a_shape_scaled_beyond_float32_distances_is_refused(resampled_dir, tmp_path):
    path = resampled_dir / "airplane" / "airplane_0002.txt"
    values = np.loadtxt(path, delimiter=",") * np.array([1e30] * 3 + [1] * 3)  # was: exit 0, NaN Chamfer distance
    path.write_text("".join(",".join(f"{v:.6g}" for v in row) + "\n" for row in values))
    with pytest.raises(PointCloudError, match=r"^shape airplane_0002: coordinates up to .*e\+29, beyond 4.61e\+18"):
        prepare("modelnet40_resampled", source=resampled_dir, cache_root=tmp_path)
    assert check_cloud(np.eye(3) * MAX_COORDINATE).shape == (3, 3)  # the bound itself passes


def test_non_finite_metrics_are_never_written():
    refuse_non_finite_metrics({"Error(R)": 1.0, "chamfer": 0.1}, "synthetic")
    with pytest.raises(DatasetError, match=r"^the test gave non-finite metrics \(chamfer=nan\) on synthetic data"):
        refuse_non_finite_metrics({"Error(R)": 1.0, "chamfer": math.nan}, "synthetic")


def test_scans_that_form_no_pair_are_counted_and_named(tmp_path):
    source = read_scans(write_scan_set(tmp_path / "scans"))
    pairs = scan_pairs(source.scan_sets, 0.3, 2.0)
    dropped = dropped_pairs(source.scan_sets, pairs, 0.3)
    assert dropped["pairs"] == 6 - len(pairs) > 0 and dropped["reason"] == "overlap <= data.pair.min_overlap=0.3"
    assert all(name.split(":")[1] in "abc" for name in dropped["scans_in_no_pair"])
    everything = dropped_pairs(source.scan_sets, scan_pairs(source.scan_sets, 0.999, 2.0), 0.999)
    assert everything["pairs"] == 6 and len(everything["scans_in_no_pair"]) == 3


# --- 3. settings accepted but unused -------------------------------------------------------------------


@pytest.mark.parametrize("flag", ["mask_loss", "connection"])
def test_mask_settings_without_the_mask_module_are_refused(flag):
    flags = {"mask_loss": False, "connection": False} | {flag: True}
    with pytest.raises(ValueError, match=f"^{flag}=true needs the mask module, which mask_module=false removes"):
        OMNet(width=0.0625, mask_module=False, fusion=False, **flags)


def test_topk_at_least_the_cloud_size_is_refused_at_the_first_pass():
    model = OMNet(width=0.0625, num_iters=3, mask_mode="topk", topk=16).eval()
    src, ref = torch.randn(1, 16, 3), torch.randn(1, 16, 3)
    with pytest.raises(ConfigError, match=r"^model.network.topk=16 keeps every one of the 16 points of a cloud"):
        model(src, ref)  # was: every point kept, the masks silently off
    model.topk = 15
    assert len(model(src, ref)["transforms"]) == 3


def test_topk_under_argmax_masks_is_refused():
    cfg = compose_config("model.network.topk=100")
    with pytest.raises(ConfigError, match=r"^model.network.topk=100 cannot take effect: it is read only with "
                                          r"model.network.mask_mode=topk"):
        refuse_unread_overrides(cfg, ["model.network.topk=100"])
    refuse_unread_overrides(compose_config("model.network.mask_mode=topk", "model.network.topk=100"),
                            ["model.network.mask_mode=topk", "model.network.topk=100"])


# --- 4. results that misreport themselves --------------------------------------------------------------


def _frame(icp_error: float) -> pd.DataFrame:
    rows = [("icp", icp_error), ("fgr", 3.0), ("go_icp", 5.0)]
    return pd.DataFrame([{"method": m, "experiment": "unseen_shapes", "sampling": "ts", "partial": "prnet",
                          "metric": "Error(R)", "value": v} for m, v in rows])


def test_a_nan_cell_is_shown_as_nan_and_its_column_is_not_ranked():
    table = tables.build_table(_frame(math.nan), "table1", metrics=["Error(R)"])
    rows = {r.label: r for b in table.blocks for r in b.rows}
    icp = next(r for label, r in rows.items() if label.lower().startswith("icp"))
    ts = table.columns.index(("Error(R)", "TS"))
    assert tables.fmt(icp.values[ts], "Error(R)") == "NaN" and tables.fmt(None, "Error(R)") == tables.MISSING
    assert all(rank is None for r in rows.values() for rank in r.ranks)  # was: "--", and fgr marked best
    ranked = tables.build_table(_frame(1.0), "table1", metrics=["Error(R)"])
    assert any(rank == 1 for b in ranked.blocks for r in b.rows for rank in r.ranks)


@pytest.mark.parametrize("threshold", [-1.0, 0.0, math.nan, math.inf, True])
def test_a_threshold_that_is_no_distance_is_refused(threshold):
    with pytest.raises(ConfigError, match="threshold must be a distance > 0"):
        check_threshold(threshold)
    points = np.random.default_rng(0).normal(size=(50, 3))
    with pytest.raises(ConfigError):  # was: fitness 1.000 for --threshold -1
        inlier_fit(points, points, np.eye(4), threshold)


# --- 6. one line instead of a traceback ----------------------------------------------------------------


@pytest.mark.parametrize("override, message", [
    ("seed=-1", "seed=-1 is invalid: it must be an integer in [0, 4294967295]"),
    ("data.seed=-5", "data.seed=-5 is invalid: it must be an integer in [0, 4294967295]"),
    ("callbacks.checkpoint.mode=avg", "callbacks.checkpoint.mode='avg' is invalid: it must be one of min, max"),
])
def test_values_lightning_or_numpy_would_reject_deep_inside_are_refused(override, message):
    with pytest.raises(ConfigError) as info:
        validate_config(compose_config(override))
    assert str(info.value) == message


@pytest.mark.parametrize("key", ["foo", "noise"])
def test_an_unknown_data_pair_key_nested_or_not_is_one_line(key):
    with pytest.raises(ConfigError, match=rf"^data.pair.{key} is not a pair setting \(nothing reads it\)"):
        RegistrationDataModule(pair={key: {"bar": 1}})  # was: TypeError from build_pair_transforms


@pytest.mark.parametrize("override, message", [
    ("workers=-2", "workers=-2 is invalid: it must be an integer >= 0 (or null)"),
    ("timeout_s=0", "timeout_s=0 is invalid: it must be a number > 0 (or null)"),
    ("benchmark.max_pairs=abc", "benchmark.max_pairs='abc' is invalid: it must be an integer >= 1 (or null)"),
    ("+benchmark.max_pairs_by_method.icp=0", "benchmark.max_pairs_by_method.icp=0 is invalid: it must be an integer >= 1"),
])
def test_grid_values_are_one_line(override, message):
    from hydra import compose, initialize_config_dir

    from benchmarks.grid.plan import GRID_CONFIG  # (stores the grid's primary config)
    from src.utils.paths import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(GRID_CONFIG, overrides=[override])
    with pytest.raises(ConfigError) as info:
        validate_grid_config(cfg)
    assert str(info.value) == message


def test_a_monitor_no_validation_logs_is_refused_before_training():
    refuse_unknown_monitor("val/score", "src.models.module.RegistrationModule")
    refuse_unknown_monitor("train/loss", "src.models.module.RegistrationModule")
    with pytest.raises(ConfigError, match=r"^callbacks.checkpoint.monitor=val/scor is never logged.*did you mean val/score"):
        refuse_unknown_monitor("val/scor", "src.models.module.RegistrationModule")


def test_ctrl_c_in_a_command_is_one_line_and_status_130(capsys):
    def interrupted() -> None:
        raise KeyboardInterrupt

    assert exit_code_of(interrupted) == 128 + signal.SIGINT
    assert capsys.readouterr().err.strip() == "error: interrupted by SIGINT"


# --- 7. misleading messages ----------------------------------------------------------------------------


def test_a_byte_order_mark_is_not_part_of_the_first_name(tmp_path):
    assert _lines("\ufeffairplane_0001\nchair_0001\n".encode("utf-8"), "names.txt") == ["airplane_0001", "chair_0001"]
    path = tmp_path / "cloud.xyz"
    path.write_text("\ufeff0 0 0\n1 0 0\n0 1 0\n", encoding="utf-8")
    assert read_points(path).shape == (3, 3)


def test_a_ply_element_line_without_its_count_is_named():
    text = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" \
           b"element face\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    with pytest.raises(DatasetError, match=r"^scan.ply: malformed PLY header line 'element face': expected 'element "
                                           r"<name> <count>'"):
        parse_ply_points(text, "scan.ply")
    assert parse_ply_points(text.replace(b"element face\n", b"element face 0\n"), "scan.ply").shape == (3, 3)
