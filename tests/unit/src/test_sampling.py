import numpy as np
import pytest

from src.data.mesh import MeshShape
from src.data.sampling import normalize_mesh, sample_shape, sample_surface
from src.utils.errors import DatasetError


def test_normalize_mesh_centres_bbox_and_scales_to_unit_sphere(meshes):
    v = normalize_mesh(meshes["tetra"][0] * 7 + [3, -2, 10])
    assert np.allclose(v.min(0) + v.max(0), 0)
    assert np.isclose(np.linalg.norm(v, axis=1).max(), 1)


def test_normalize_mesh_rejects_collapsed_vertices():
    with pytest.raises(DatasetError, match="shape dot: all vertices coincide"):
        normalize_mesh(np.ones((4, 3)), name="dot")


def test_points_lie_on_the_surface_with_face_normals(meshes):
    points, normals = sample_surface(*meshes["cube"], 2000, np.random.default_rng(0))
    assert points.shape == normals.shape == (2000, 3) and points.dtype == normals.dtype == np.float32
    assert np.allclose(np.abs(points).max(axis=1), 1, atol=1e-6)  # on a face of [-1, 1]^3
    axis = np.abs(points).argmax(axis=1)
    assert np.allclose(np.abs(normals[np.arange(2000), axis]), 1)  # normal = that face's axis


def test_area_weighting_and_uniform_barycentric():
    # two triangles of areas 1 and 3 (disjoint); mean of the points inside one = its centroid
    vertices = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [10, 0, 0], [16, 0, 0], [10, 1, 0]], dtype=float)
    points, _ = sample_surface(vertices, np.array([[0, 1, 2], [3, 4, 5]]), 40000, np.random.default_rng(1))
    small = points[:, 0] < 5
    assert small.mean() == pytest.approx(0.25, abs=0.01)
    assert np.allclose(points[~small].mean(axis=0), vertices[3:].mean(axis=0), atol=0.03)


def test_zero_area_faces_are_never_drawn():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], dtype=float)
    faces = np.array([[3, 3, 3], [0, 1, 2], [3, 3, 3]])
    points, _ = sample_surface(vertices, faces, 5000, np.random.default_rng(2))
    assert np.all(points[:, 2] == 0)


@pytest.mark.parametrize(("faces", "cause"), [(np.zeros((0, 3), int), "no triangle faces"), ([[0, 1, 1]], "zero")])
def test_degenerate_meshes_name_the_shape(meshes, faces, cause):
    with pytest.raises(DatasetError, match=f"shape bad_0001: mesh has {cause}"):
        sample_surface(meshes["tetra"][0], np.array(faces), 10, np.random.default_rng(0), name="bad_0001")


def test_sample_shape_is_deterministic_and_shares_one_frame(meshes):
    vertices, faces = meshes["tetra"]
    shape = MeshShape("a_0001", "a", "train", vertices, faces)
    points, normals = sample_shape(shape, 3, 256, seed=5, shape_index=7)
    assert points.shape == normals.shape == (3, 256, 3) and points.dtype == np.float32
    again, _ = sample_shape(shape, 3, 256, seed=5, shape_index=7)
    assert np.array_equal(points, again)
    assert not np.array_equal(points[0], points[1])  # samplings differ ...
    assert np.allclose(points.mean(axis=1), points.mean(axis=(0, 1)), atol=0.05)  # ... but share one frame
    assert not np.array_equal(points, sample_shape(shape, 3, 256, seed=6, shape_index=7)[0])
    assert not np.array_equal(points, sample_shape(shape, 3, 256, seed=5, shape_index=8)[0])
    moved = MeshShape("a_0001", "a", "train", vertices * 4 - 1, faces)
    assert np.allclose(sample_shape(moved, 3, 256, seed=5, shape_index=7)[0], points, atol=1e-6)
    assert np.linalg.norm(points, axis=-1).max() <= 1 + 1e-6
