import re

import numpy as np
import pytest

from src.data.mesh import MeshShape
from src.data.readers import (
    PointNetH5Reader, PointShape, PrincetonOffReader, ResampledReader, detect_layout, open_reader, parse_off,
    parse_resampled,
)
from src.utils.errors import DatasetError


def test_parse_off_glued_header_comments_and_polygons():
    vertices, faces = parse_off(b"OFF5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n0 0 1\n3 0 1 4\n4 0 1 2 3\n", "q.off")
    assert vertices.shape == (5, 3) and vertices.dtype == np.float64 and faces.dtype == np.int64
    assert faces.tolist() == [[0, 1, 4], [0, 1, 2], [0, 2, 3]]  # the quad is fan-triangulated
    text = b"# header comment\nOFF\n\n# counts next\n3 1 0\n0 0 0 # a vertex\n1 0 0\n0 1 0\n\n3 0 1 2 255 0 0\n"
    vertices, faces = parse_off(text, "ok.off")  # comments, blank lines and colour columns are skipped
    assert faces.tolist() == [[0, 1, 2]] and vertices[1].tolist() == [1, 0, 0]


@pytest.mark.parametrize(
    ("data", "cause"),
    [
        (b"PLY\n3 1 0\n", "not an OFF file"),
        (b"OFF\n3 1 0\n0 0 0\n1 0 0\n", "truncated OFF file"),
        (b"OFF\n3 1 0\n0 0 x\n1 0 0\n0 1 0\n3 0 1 2\n", "malformed OFF body"),
        (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n", "face index out of range"),
        (b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n5 0 1 2\n", "malformed face line"),
    ],
)
def test_parse_off_errors_name_the_file(data, cause):
    with pytest.raises(DatasetError, match=f"m.off: {cause}"):
        parse_off(data, "m.off")


def _open_source(folder, make_zip, zipped: bool, layout: str, reader_type: type):
    """The reader of ``folder`` (or of its zip): its layout detected as ``layout``, a ``reader_type``
    holding the two categories of the fixtures."""
    source = make_zip(folder) if zipped else folder
    assert detect_layout(source) == layout
    reader = open_reader(source)
    assert isinstance(reader, reader_type) and reader.categories == ["airplane", "chair"]
    return reader


@pytest.mark.parametrize("zipped", [False, True])
def test_princeton_reader(princeton_dir, make_zip, zipped):
    reader = _open_source(princeton_dir, make_zip, zipped, "princeton_off", PrincetonOffReader)
    assert [e.name for e in reader.entries["train"]] == ["airplane_0001", "airplane_0002", "chair_0001"]
    assert [e.name for e in reader.entries["test"]] == ["airplane_0003", "chair_0002"]
    shapes = list(reader.iter_shapes("train", limit=2))
    assert all(isinstance(s, MeshShape) for s in shapes) and [s.faces.shape for s in shapes] == [(4, 3), (12, 3)]
    assert shapes[1].category == "airplane" and shapes[1].split == "train"


def test_princeton_reader_reports_an_empty_split(princeton_dir):
    for f in princeton_dir.glob("*/test/*.off"):
        f.unlink()
    reader = open_reader(princeton_dir)
    assert list(reader.entries) == ["train"] and "has no test shapes" in reader.missing["test"].message


@pytest.mark.parametrize("zipped", [False, True])
def test_pointnet_h5_reader(h5_dir, make_zip, zipped):
    reader = _open_source(h5_dir, make_zip, zipped, "pointnet_h5", PointNetH5Reader)
    assert [(e.name, e.category) for e in reader.entries["train"]] == [
        ("airplane_0001", "airplane"), ("chair_0001", "chair"), ("airplane_0002", "airplane")
    ]
    assert [e.name for e in reader.entries["test"]] == ["chair_test0_0000", "airplane_test0_0001"]  # no json
    shape = reader.load(reader.entries["test"][1])
    assert isinstance(shape, PointShape) and shape.points.shape == shape.normals.shape == (32, 3)


def test_pointnet_h5_reader_needs_shape_names(h5_dir):
    (h5_dir / "shape_names.txt").unlink()
    with pytest.raises(DatasetError, match="shape_names.txt not found"):
        open_reader(h5_dir)


@pytest.mark.parametrize("zipped", [False, True])
def test_resampled_reader_restricts_to_present_categories(resampled_dir, make_zip, zipped):
    # the split lists name bathtub shapes too, but it has no folder
    reader = _open_source(resampled_dir, make_zip, zipped, "pointnet2_resampled", ResampledReader)
    assert [e.name for e in reader.entries["train"]] == ["airplane_0001", "airplane_0002", "chair_0001"]
    assert not reader.missing
    shape = reader.load(reader.entries["test"][1])
    assert (shape.name, shape.category, shape.split) == ("chair_0002", "chair", "test")
    assert shape.points.shape == shape.normals.shape == (20, 3) and shape.points.dtype == np.float32


def test_resampled_split_with_absent_files_is_reported(resampled_dir):
    (resampled_dir / "chair" / "chair_0002.txt").unlink()
    (resampled_dir / "airplane" / "airplane_0003.txt").unlink()
    reader = open_reader(resampled_dir)
    assert list(reader.entries) == ["train"]
    missing = reader.missing["test"]
    assert missing.count == 2 and missing.to_json()["examples"] == ["airplane_0003", "chair_0002"]
    assert missing.by_category == {
        "airplane": {"missing": 1, "listed": 1, "examples": ["airplane_0003"]},
        "chair": {"missing": 1, "listed": 1, "examples": ["chair_0002"]},
    }
    assert missing.message == (
        f"split 'test' is not built: 2 of 2 shapes listed in its split list are missing from {resampled_dir} "
        "(airplane: 1 of 1, first: airplane_0003; chair: 1 of 1, first: chair_0002)"
    )
    with pytest.raises(DatasetError, match="split 'test' is not built"):
        next(reader.iter_shapes("test"))


@pytest.mark.parametrize(
    ("line", "cause"),
    [
        ("1,2,3,4,5", "is malformed, expected 'x,y,z,nx,ny,nz'"),
        ("1,2,3,x,5,6", "is malformed"),
        ("1,2,3,4,5,6,7", "is malformed"),
        ("nan,2,3,4,5,6", "has the non-finite value nan"),
        ("0.1, -1e40,0,0,0,1", r"has the value -1e40, beyond float32's range \(\|v\| <= 3.4e\+38\)"),
    ],
)
def test_resampled_bad_line_names_file_line_and_value(line, cause):
    data = ("0,0,0,0,0,1\n\n" + line + "\n0,0,0,0,0,1\n").encode()
    with pytest.raises(DatasetError, match=f"^airplane/airplane_0001.txt: line 3 {cause}"):
        parse_resampled(data, "airplane/airplane_0001.txt")


def test_malformed_file_in_archive_is_reported_on_load(resampled_dir):
    (resampled_dir / "chair" / "chair_0001.txt").write_text("1,2,3,4,5,6\n1,2\n")
    reader = open_reader(resampled_dir)
    with pytest.raises(DatasetError, match="chair/chair_0001.txt: line 2 is malformed"):
        reader.load(reader.entries["train"][2])


def test_detect_layout_errors(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"matches no known ModelNet40 layout; expected one of: Princeton"):
        detect_layout(tmp_path / "empty")
    with pytest.raises(DatasetError, match="does not exist"):
        detect_layout(tmp_path / "nowhere")
    (tmp_path / "f.zip").write_text("not a zip")
    with pytest.raises(DatasetError, match="neither a folder, a .zip archive nor an .off/.ply scan"):
        detect_layout(tmp_path / "f.zip")


def _truncated(data: bytes) -> bytes:
    return data[: len(data) // 2]


def _zeroed_middle(data: bytes) -> bytes:
    """Zeroes inside a member's compressed data (the central directory stays intact)."""
    middle = len(data) // 3
    return data[:middle] + bytes(64) + data[middle + 64:]


@pytest.mark.parametrize(
    ("damage", "detail"),
    [
        (_truncated, "its end-of-archive record is missing: truncated?"),
        (_zeroed_middle, "Bad CRC-32|Error -3 while decompressing"),
    ],
)
def test_damaged_zip_is_named_as_such(resampled_dir, make_zip, tmp_path, damage, detail):
    damaged = tmp_path / "damaged.zip"
    damaged.write_bytes(damage(make_zip(resampled_dir).read_bytes()))
    with pytest.raises(DatasetError) as error:
        reader = open_reader(damaged)
        for entries in reader.entries.values():
            for entry in entries:
                reader.load(entry)
    message = str(error.value)
    assert message.startswith(f"source {damaged} is a damaged .zip archive (") and "\n" not in message
    assert message.endswith("; download or copy it again") and re.search(detail, message)


def test_scan_meshes_from_a_single_file_and_a_folder(tmp_path, meshes):
    import open3d as o3d

    from tests.helpers.meshes import off_text

    vertices, faces = meshes["cube"]
    scans = tmp_path / "scans"
    scans.mkdir()
    (scans / "bunny.off").write_text(off_text(vertices, faces))
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(faces))
    o3d.io.write_triangle_mesh(str(scans / "dragon.ply"), mesh)
    reader = open_reader(scans)
    assert reader.layout == "scan_meshes" and reader.categories == ["bunny", "dragon"]
    assert list(reader.entries) == ["test"] and not reader.missing
    dragon = reader.load(reader.entries["test"][1])
    np.testing.assert_allclose(dragon.vertices, vertices, atol=1e-6)
    single = open_reader(scans / "bunny.off")
    assert [e.name for e in single.entries["test"]] == ["bunny"]
    (tmp_path / "cloud.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n")
    points_only = open_reader(tmp_path / "cloud.ply")
    with pytest.raises(DatasetError, match="no triangle mesh"):
        points_only.load(points_only.entries["test"][0])
