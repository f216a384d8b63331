"""python -m baselines register: a user's two scans (PLY, PCD, XYZ) with any method, on two of the shared
Stanford Bunny scans; the readers; the shipped checkpoint of a learned method."""

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from baselines import get_registrator
from baselines.__main__ import main
from src.data.point_files import read_points, write_ply
from src.data.scans import parse_conf, relative_pose
from src.utils.paths import shared_path

SCANS = shared_path("data", "stanford", "stanford_bunny_scans.zip")
MEMBERS = "bunny_scans/data/"
BUNNY = pytest.mark.shared_data("data/stanford/stanford_bunny_scans.zip")  # the tests of the `bunny` fixture


@pytest.fixture(scope="module")
def bunny(tmp_path_factory) -> tuple[Path, Path, np.ndarray]:
    """bun045.ply and bun000.ply extracted, and the true transform bun045 -> bun000 (from bun.conf)."""
    folder = tmp_path_factory.mktemp("bunny")
    with zipfile.ZipFile(SCANS) as archive:
        for name in ("bun045.ply", "bun000.ply"):
            (folder / name).write_bytes(archive.read(MEMBERS + name))
        poses = parse_conf(archive.read(MEMBERS + "bun.conf").decode(), "bun.conf")
    return folder / "bun045.ply", folder / "bun000.ply", relative_pose(poses["bun045.ply"], poses["bun000.ply"])


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a[:3, :3] @ b[:3, :3].T).magnitude()))


@BUNNY
def test_fgr_registers_two_real_scans_and_writes_transform_fit_aligned_cloud_and_picture(bunny, tmp_path, capsys):
    source, reference, truth = bunny
    assert main(["register", str(source), str(reference), "--method", "fgr", "--out", str(tmp_path / "out")]) == 0
    record = json.loads((tmp_path / "out" / "result.json").read_text())
    transform = np.asarray(record["transform"])
    assert _angle(transform, truth) < 2.0 and np.linalg.norm(transform[:3, 3] - truth[:3, 3]) < 0.005  # metres
    assert np.allclose(np.loadtxt(tmp_path / "out" / "transform.txt"), transform, atol=1e-6)
    assert record["fitness"] > 0.8 and 0 < record["inlier_rmse"] < record["threshold"]
    assert record["normalisation"] is None  # the bunny (metres) lies inside the unit sphere
    aligned = read_points(tmp_path / "out" / "bun045_aligned.ply")
    moved = read_points(source) @ transform[:3, :3].T + transform[:3, 3]
    assert np.allclose(aligned, moved, atol=1e-6)
    assert (tmp_path / "out" / "before_after.png").read_bytes().startswith(b"\x89PNG")
    out = capsys.readouterr().out
    assert out.startswith("FGR: ") and "fitness" in out and "inlier RMSE" in out and "before_after.png" in out


def _write(path: Path, points: np.ndarray) -> Path:
    """``points`` in the format of ``path``'s suffix (.ply binary, .xyz text, .pcd binary)."""
    if path.suffix == ".ply":
        write_ply(path, points)
    elif path.suffix == ".xyz":
        np.savetxt(path, points, fmt="%.6f", header="x y z")
    else:
        header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                  f"WIDTH {len(points)}\nHEIGHT 1\nPOINTS {len(points)}\nDATA binary\n")
        body = np.concatenate([points, np.ones((len(points), 1))], axis=1).astype("<f4").tobytes()
        path.write_bytes(header.encode() + body)
    return path


@BUNNY
def test_a_learned_method_takes_the_shipped_checkpoint_and_one_similarity_whatever_the_units(bunny, tmp_path):
    """The same scans in millimetres (PCD, XYZ) and in decimetres (PLY): one similarity into the unit sphere
    each, so the same rotation and the translation in each pair's units."""
    rng = np.random.default_rng(0)
    clouds = [read_points(p) for p in bunny[:2]]
    clouds = [c[rng.choice(len(c), 2000, replace=False)] for c in clouds]
    records = {}
    for scale, suffixes in ((1000.0, (".pcd", ".xyz")), (10.0, (".ply", ".ply"))):
        paths = [_write(tmp_path / f"{name}_{scale:g}{suffix}", scale * cloud)
                 for name, suffix, cloud in zip(("a", "b"), suffixes, clouds)]
        assert np.allclose(read_points(paths[0]), scale * clouds[0], rtol=1e-6, atol=1e-3 * scale)
        out = tmp_path / f"out_{scale:g}"
        assert main(["register", *map(str, paths), "--method", "omnet", "--out", str(out)]) == 0
        records[scale] = json.loads((out / "result.json").read_text())
    big, small = (np.asarray(records[s]["transform"]) for s in (1000.0, 10.0))
    assert _angle(big, small) < 1e-3 and np.allclose(big[:3, 3], 100 * small[:3, 3], rtol=1e-3, atol=1e-2)
    assert all(r["normalisation"] is not None and r["registered_points"] == [768, 768] for r in records.values())
    shipped = get_registrator("omnet")
    assert records[10.0]["checkpoint"] == shipped.config.checkpoint and shipped.label.startswith("OMNet (shipped: ")


@pytest.mark.parametrize("name, content, message", [
    ("cloud.obj", b"v 0 0 0\n", "unknown point-cloud format .obj"),
    ("cloud.pcd", b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 3\nDATA binary_compressed\n", "binary_compressed is not"),
    ("cloud.xyz", b"0 0 0\n1 1\n", "fewer than 3 numbers"),
    ("missing.ply", None, "does not exist"),
])
def test_unreadable_files_stop_with_one_error_line(tmp_path, capsys, name, content, message):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    assert main(["register", str(tmp_path / name), str(tmp_path / name)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err


def test_without_arguments_it_still_lists_the_methods(capsys):
    assert main([]) == 0 and "| `fgr` |" in capsys.readouterr().out


def test_ascii_pcd_and_text_with_a_header_line_are_read(tmp_path):
    expected = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.5]])
    rows = "\n".join(" ".join(f"{v:g}" for v in row) for row in expected)
    (tmp_path / "a.pcd").write_text("# .PCD v.7\nVERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                    f"WIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n{rows}\n")
    (tmp_path / "a.csv").write_text("x,y,z,intensity\n" + "\n".join(",".join(f"{v:g}" for v in [*r, 7]) for r in expected))
    assert np.array_equal(read_points(tmp_path / "a.pcd"), expected)
    assert np.array_equal(read_points(tmp_path / "a.csv"), expected)
