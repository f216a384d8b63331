"""The golden-file study's helpers (benchmarks/studies/golden): the rotation difference, golden files' round
trip, the spread's summary and report, its one-line errors, and PRNet's and DeepGMR's authors' networks at our width
(against WangYueFt/prnet, wentaoyuan/deepgmr only where PRNET_AUTHORS_DIR, DEEPGMR_AUTHORS_DIR name checkouts)."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from benchmarks.studies.golden import (
    authors_deepgmr,
    authors_prnet,
    golden_file,
    spread,
)
from benchmarks.studies.golden.generate import main as generate_main
from src.utils.errors import ConfigError


def _transforms(degrees: list[float], axis: str = "z") -> np.ndarray:
    out = np.tile(np.eye(4), (len(degrees), 1, 1))
    out[:, :3, :3] = Rotation.from_euler(axis, np.asarray(degrees)[:, None], degrees=True).as_matrix()
    return out


def test_rotation_difference_keeps_tiny_and_large_angles():
    a = _transforms([0.0, 10.0, 0.0, 0.0])
    b = _transforms([1e-9, 10.0 + 3e-7, 90.0, 179.0])
    np.testing.assert_allclose(golden_file.rotation_difference_deg(a, b), [1e-9, 3e-7, 90.0, 179.0], rtol=1e-5)
    b[:, :3, 3] = [[3.0, 4.0, 0.0]] * 4
    np.testing.assert_allclose(golden_file.translation_difference(a, b), 5.0)


def test_golden_files_round_trip_and_refuse_missing_fields(tmp_path, monkeypatch):
    monkeypatch.setattr(golden_file, "GOLDEN_DIR", tmp_path)
    fields = {"dtype": "float64", "authors": "a/b@1", "weights": "", "weights_sha256": "", "pairs_sha256": "x",
              "command": "python -m benchmarks.studies.golden.generate m"}
    golden_file.write_golden("m", _transforms([1.0, 2.0]), **fields)
    read = golden_file.read_golden("m")
    np.testing.assert_array_equal(read.pop("transforms"), _transforms([1.0, 2.0]))
    assert read == {"method": "m", **fields}
    with pytest.raises(ValueError, match="command"):
        golden_file.write_golden("m", _transforms([1.0]), **{k: v for k, v in fields.items() if k != "command"})


def test_the_spread_is_the_largest_difference_between_any_two_settings():
    runs = {"a": _transforms([0.0, 0.0]), "b": _transforms([0.1, 0.0]), "c": _transforms([-0.2, 0.05])}
    summary = spread.summarise(runs, golden=_transforms([0.0, 1.0]))
    assert summary["median"] == pytest.approx(np.median([0.3, 0.05])) and summary["max"] == pytest.approx(0.3)
    assert summary["per_setting"] == pytest.approx({"b": 0.1, "c": 0.2})
    assert summary["golden_max"] == pytest.approx(1.0) and summary["golden_median"] == pytest.approx((0.2 + 1.0) / 2)
    assert "golden_max" not in spread.summarise(runs, golden=None)


def test_the_report_has_a_row_per_method_and_code_and_a_column_per_setting():
    runs = {s: _transforms([0.0]) for s in spread.SETTINGS}
    results = {("m", "ours"): spread.summarise(runs, None), ("m", "authors"): spread.summarise(runs, _transforms([1.0]))}
    text = spread.report(results, 1, "python -m benchmarks.studies.golden.spread --methods m")
    assert "| m | ours | 0.00e+00 | 0.00e+00 | no golden file |" in text
    assert "| m | authors | 0.00e+00 | 0.00e+00 | 1.00e+00 / 1.00e+00 |" in text
    assert all(f"`{s}`" in text for s in list(spread.SETTINGS)[1:])


def test_bad_arguments_are_one_line_errors(capsys):
    with pytest.raises(ConfigError, match="METHOD=CHECKOUT"):
        spread._checkouts(["dcp_v1"])
    assert generate_main(["dcp_v1"]) == 2
    assert capsys.readouterr().err.strip() == "error: dcp_v1: --authors CHECKOUT (a clone of WangYueFt/dcp) is needed"


def test_prnet_authors_literals_are_scaled_as_ours_and_other_channels_kept():
    namespace = authors_prnet._width_nn(0.0625)
    assert namespace.Conv2d(6, 64, kernel_size=1).weight.shape[:2] == (4, 6)  # their DGCNN's conv1 (model.py:286)
    assert namespace.Conv2d(512, 32, kernel_size=1).weight.shape[:2] == (32, 32)  # conv5 into n_emb_dims
    assert namespace.Linear(128, 1).weight.shape == (1, 8) and namespace.BatchNorm2d(256).num_features == 16
    assert namespace.ReLU is torch.nn.ReLU


def test_prnet_authors_network_refuses_what_their_code_cannot_be():
    from benchmarks.studies.lockstep.prnet import AUTHORS_ARGS, FIXED

    network = {**{k: v for k, (_, v) in AUTHORS_ARGS.items()}, **FIXED}  # main.py's defaults
    with pytest.raises(ConfigError, match="their code has"):
        authors_prnet.build_authors(None, {**network, "width": 1.0, "k": 16})
    with pytest.raises(ConfigError, match="embedding size 64 is one of their literals"):
        authors_prnet.build_authors(None, {**network, "width": 0.125})


def test_deepgmr_authors_literals_are_scaled_as_ours_and_every_layer_is_mapped():
    namespace = authors_deepgmr._scaled_nn(0.5, (64, 128, 256, 512, 1024, 2048))
    assert namespace.Conv1d(80, 64, kernel_size=1).weight.shape[:2] == (32, 80)  # their first layer (model.py:124)
    assert namespace.Conv1d(128, 16, kernel_size=1).weight.shape[:2] == (16, 64)  # their last, into the J clusters
    assert namespace.BatchNorm1d(2048).num_features == 1024 and namespace.ReLU is torch.nn.ReLU
    def block() -> torch.nn.Module:
        return torch.nn.Sequential(torch.nn.Conv1d(4, 4, 1), torch.nn.BatchNorm1d(4), torch.nn.ReLU())

    theirs = torch.nn.Module()
    theirs.backbone = torch.nn.Module()
    theirs.backbone.encoder = torch.nn.Sequential(block(), block())
    theirs.backbone.decoder = torch.nn.Sequential(block(), torch.nn.Conv1d(4, 2, 1))
    assert authors_deepgmr.layer_pairs(theirs) == [
        ("backbone.encoder.layers.0", "backbone.encoder.0.0"), ("backbone.encoder.layers.1", "backbone.encoder.0.1"),
        ("backbone.encoder.layers.3", "backbone.encoder.1.0"), ("backbone.encoder.layers.4", "backbone.encoder.1.1"),
        ("backbone.decoder.layers.0", "backbone.decoder.0.0"), ("backbone.decoder.layers.1", "backbone.decoder.0.1"),
        ("backbone.logits", "backbone.decoder.1")]


def test_deepgmr_authors_network_refuses_what_their_code_cannot_be():
    network = {"d_model": 1024, "n_clusters": 16, "use_rri": True, "k": 20, "width": 0.5, "exact_procrustes": False}
    with pytest.raises(ConfigError, match="the golden reference is their code's RRI network"):
        authors_deepgmr.build(None, {**network, "exact_procrustes": True})
    with pytest.raises(ConfigError, match="cannot be told apart"):
        authors_deepgmr.build(None, {**network, "k": 16})  # 4k = 64 inputs, one of their width literals


#: method -> (the variable naming a checkout of the authors' code, their repository).
AUTHORS_CHECKOUTS = {"prnet": ("PRNET_AUTHORS_DIR", "WangYueFt/prnet"), "deepgmr": ("DEEPGMR_AUTHORS_DIR", "wentaoyuan/deepgmr")}


@pytest.mark.shared_data("data/modelnet40_normal_resampled_airplane.zip")
@pytest.mark.parametrize("method", sorted(AUTHORS_CHECKOUTS))
def test_the_authors_code_gives_its_golden_file(method, tmp_path):
    from benchmarks.studies.golden import authors
    from benchmarks.studies.golden.pairs import golden_pairs, prepare_cache

    variable, repo = AUTHORS_CHECKOUTS[method]
    if not os.environ.get(variable):
        pytest.skip(f"{variable} (a checkout of {repo}) not set: their side is not checked")
    pairs = {k: v[:8] for k, v in golden_pairs(prepare_cache(tmp_path)).items()}  # one batch
    estimates = getattr(authors, method)(Path(os.environ[variable]), pairs, torch.float64)
    np.testing.assert_array_equal(estimates, golden_file.read_golden(method)["transforms"][:8])
