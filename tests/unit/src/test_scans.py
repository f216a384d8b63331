"""Range scans with a Stanford-style .conf (src/data/scans.py) and the scan-pair test set (src/data/scan_pairs.py)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import hydra
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from src.config import register_resolvers
from src.data.scan_pairs import ScanPairsDataModule
from src.data.scans import normalise_pair, parse_ply_points, read_scans, scan_pairs
from src.utils.errors import ConfigError, DatasetError, exit_code_of
from src.geometry.numpy_rigid import apply_transform
from src.utils.paths import REPO_ROOT, shared_path
from tests.helpers.scan_helpers import COLUMNS, ply_text, surface, write_scan_set

register_resolvers()
BUNNY_ZIP = shared_path("data", "stanford", "stanford_bunny_scans.zip")


@pytest.fixture
def scan_dir(tmp_path: Path) -> Path:
    return write_scan_set(tmp_path / "scans")


def test_poses_map_each_scan_into_the_common_frame_and_compose_into_relative_poses(scan_dir):
    [scan_set] = read_scans(scan_dir).scan_sets
    assert [s.name for s in scan_set.scans] == ["a", "b", "c"]
    for scan in scan_set.scans:
        np.testing.assert_allclose(scan.in_common_frame(), surface(COLUMNS[scan.name]), atol=1e-9)
    pairs = {(p.source, p.reference): p for p in scan_pairs([scan_set], min_overlap=0.0, overlap_spacing=0.5)}
    a, b = scan_set.scans[0].points, scan_set.scans[1].points
    # grid column k of a is column k - 10 of b (10 rows per column)
    np.testing.assert_allclose(apply_transform(pairs[0, 1].transform, a[100:]), b[:200], atol=1e-9)
    np.testing.assert_allclose(apply_transform(pairs[1, 0].transform, b[:200]), a[100:], atol=1e-9)


def test_overlap_is_the_smaller_overlapping_fraction_and_selects_the_pairs(scan_dir):
    scan_sets = read_scans(scan_dir).scan_sets
    pairs = scan_pairs(scan_sets, min_overlap=0.1, overlap_spacing=0.5)  # radius: half the spacing
    assert [(p.source, p.reference) for p in pairs] == [(0, 1), (1, 0), (1, 2), (2, 1)]
    np.testing.assert_allclose([p.overlap for p in pairs], [2 / 3, 2 / 3, 5 / 30, 5 / 30])
    assert [(p.source, p.reference) for p in scan_pairs(scan_sets, 0.2, 0.5)] == [(0, 1), (1, 0)]
    # a radius of 1.5 spacings also counts the next column of the other scan
    np.testing.assert_allclose(scan_pairs(scan_sets, 0.2, 1.5)[0].overlap, 21 / 30)


def test_normalisation_is_one_similarity_for_both_clouds(scan_dir):
    scans = read_scans(scan_dir).scan_sets[0].scans
    [pair] = [p for p in scan_pairs([read_scans(scan_dir).scan_sets[0]], 0.5, 0.5) if p.source == 0]
    src, ref, transform = normalise_pair(scans[0].points, scans[1].points, pair.transform)
    union = np.concatenate([src, ref])
    np.testing.assert_allclose(union.mean(axis=0), 0.0, atol=1e-12)
    assert np.linalg.norm(union, axis=1).max() == pytest.approx(1.0)
    np.testing.assert_array_equal(transform[:3, :3], pair.transform[:3, :3])
    np.testing.assert_allclose(apply_transform(transform, src[100:]), ref[:200], atol=1e-9)
    scale = np.linalg.norm(scans[0].points[0] - scans[0].points[-1]) / np.linalg.norm(src[0] - src[-1])
    assert np.linalg.norm(scans[1].points[0] - scans[1].points[5]) / np.linalg.norm(ref[0] - ref[5]) == pytest.approx(scale)


def test_samples_are_perturbed_seeded_and_carry_their_overlap(scan_dir):
    dm = ScanPairsDataModule(source=str(scan_dir), pair={"num_points": 300, "min_overlap": 0.5, "overlap_spacing": 0.5})
    dm.setup("test")
    dataset = dm.datasets["test"]
    assert len(dataset) == 2 and dataset.names(1) == ("b", "a")
    sample = dataset[0]
    src, ref, gt = (sample[k].double().numpy() for k in ("points_src", "points_ref", "transform_gt"))
    assert src.shape == ref.shape == (300, 3)
    near = cKDTree(ref).query(apply_transform(gt, src))[0] < 1e-5  # every point kept: the exact overlap shows
    assert near.mean() == pytest.approx(2 / 3) and float(sample["overlap"]) == pytest.approx(2 / 3)
    _, _, relative = normalise_pair(*(s.points for s in dm.cache.scan_sets[0].scans[:2]), dataset.pairs[0].transform)
    perturbation = gt @ np.linalg.inv(relative)
    angles = Rotation.from_matrix(perturbation[:3, :3]).as_euler("zyx", degrees=True)[::-1]
    assert np.all((angles > 0) & (angles < 45)) and np.all(np.abs(perturbation[:3, 3]) < 0.5)
    torch.testing.assert_close(dataset[0]["points_ref"], sample["points_ref"])
    other = ScanPairsDataModule(source=str(scan_dir), pair={"min_overlap": 0.5}, seed=7)
    other.setup("test")
    assert not torch.equal(other.datasets["test"][0]["transform_gt"], sample["transform_gt"])


def test_binary_ply_with_extra_properties_reads_as_ascii(scan_dir):
    points = parse_ply_points((scan_dir / "b.ply").read_bytes(), "b.ply")
    rows = np.zeros(len(points), dtype=[("intensity", "u1"), ("x", ">f8"), ("y", ">f8"), ("z", ">f8")])
    rows["x"], rows["y"], rows["z"] = points.T
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 300\nproperty uchar intensity\nproperty double x\n"
              "property double y\nproperty double z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    np.testing.assert_array_equal(parse_ply_points(header.encode() + rows.tobytes(), "binary.ply"), points)


def test_a_zip_reads_as_its_folder(scan_dir, make_zip):
    folder, archive = read_scans(scan_dir), read_scans(make_zip(scan_dir))
    assert archive.content_hash == folder.content_hash
    assert archive.scan_sets[0].name == "scans/scans.conf" and folder.scan_sets[0].name == "scans.conf"


def test_exp_scan_pairs_composes_the_scan_datamodule(scan_dir):
    with initialize_config_dir(config_dir=str(REPO_ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["+exp=scan_pairs", f"data.source={scan_dir}", "data.pair.min_overlap=0.5",
                                           f"output_dir={scan_dir.parent / 'unused'}"])
    dm = hydra.utils.instantiate(cfg.data)
    dm.setup("test")
    assert len(dm.datasets["test"]) == 2 and cfg.partial == "prnet"
    assert dm.cache.manifest["content_hash"] == read_scans(scan_dir).content_hash


def _replace_line(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new))


MALFORMED = {
    "no .conf": (lambda d: (d / "scans.conf").unlink(), "holds no .conf file"),
    "scan file missing": (lambda d: (d / "c.ply").unlink(), r"names scans missing from .*: c\.ply"),
    "scan without entry": (lambda d: (d / "extra.ply").write_text(ply_text(np.eye(3))), r"extra\.ply: no bmesh line"),
    "short bmesh line": (lambda d: _replace_line(d / "scans.conf", "bmesh a.ply 0.0 ", "bmesh a.ply "),
                         r"scans\.conf line 2: expected 'bmesh <file> tx ty tz qx qy qz qw'"),
    "no bmesh line": (lambda d: (d / "scans.conf").write_text("camera 0 0 0 0 0 0 1\n"), "has no 'bmesh"),
    "not a unit quaternion": (lambda d: _replace_line(d / "scans.conf", " 0.0 0.0 0.0 1.0", " 0.0 0.0 0.5 1.0"),
                              r"line 2: the quaternion .* has norm 1\.11803, not a unit quaternion"),
    "ply without vertices": (lambda d: (d / "b.ply").write_text(ply_text(np.zeros((0, 3)))), r"b\.ply: no vertices"),
    "truncated ply": (lambda d: _replace_line(d / "b.ply", "element vertex 300", "element vertex 301"),
                      r"b\.ply: truncated, 300 of the 301 vertices"),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_scan_sets_stop_with_one_error_line(scan_dir, case, capsys):
    corrupt, message = MALFORMED[case]
    corrupt(scan_dir)
    with pytest.raises(DatasetError, match=message):
        read_scans(scan_dir)
    assert exit_code_of(lambda: read_scans(scan_dir)) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1


def test_bad_pair_settings_and_stages_are_config_errors(scan_dir):
    with pytest.raises(ConfigError, match=r"unknown keys \['noise_sigma'\]"):
        ScanPairsDataModule(pair={"noise_sigma": 0.01})
    with pytest.raises(ConfigError, match="min_overlap must be in"):
        ScanPairsDataModule(pair={"min_overlap": 1.0})
    with pytest.raises(ConfigError, match="test set only"):
        ScanPairsDataModule(source=str(scan_dir)).setup("fit")
    with pytest.raises(DatasetError, match=r"no two scans of .* overlap by more than data\.pair\.min_overlap=0\.9"):
        ScanPairsDataModule(source=str(scan_dir), pair={"min_overlap": 0.9, "overlap_spacing": 0.5}).setup("test")


@pytest.mark.shared_data("data/stanford/stanford_bunny_scans.zip")
def test_bunny_ground_truth_aligns_two_real_scans_to_a_millimetre(tmp_path):
    """bun045 → bun000 with the relative pose of bun.conf, before normalisation (scans in metres)."""
    root = tmp_path / "two_scans"
    root.mkdir()
    with zipfile.ZipFile(BUNNY_ZIP) as archive:
        conf = archive.read("bunny_scans/data/bun.conf").decode()
        for name in ("bun000.ply", "bun045.ply"):
            (root / name).write_bytes(archive.read(f"bunny_scans/data/{name}"))
    (root / "two.conf").write_text("".join(line + "\n" for line in conf.splitlines()
                                           if line.startswith(("camera", "bmesh bun000", "bmesh bun045"))))
    scan_sets = read_scans(root).scan_sets
    [pair] = [p for p in scan_pairs(scan_sets, 0.5, 2.0) if scan_sets[0].scans[p.source].name == "bun045"]
    source, reference = scan_sets[0].scans[pair.source].points, scan_sets[0].scans[pair.reference].points
    residual = cKDTree(reference).query(apply_transform(pair.transform, source))[0]
    assert np.median(residual) < 0.0005 and (residual < 0.001).mean() > 0.85 and pair.overlap > 0.85
    assert np.median(cKDTree(reference).query(source)[0]) > 0.005  # without the ground truth: centimetres apart
