"""The embedded synthetic dataset: API, determinism, mesh validity and no axisymmetric categories."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from src.data import synthetic
from src.data.categories import AXISYMMETRIC_CATEGORIES
from src.data.mesh import MeshShape
from src.data.sampling import normalize_mesh, sample_shape, sample_surface
from src.data.synthetic import SYNTHETIC_CATEGORIES, SYNTHETIC_HALVES, generate_shapes
from src.utils.errors import ConfigError

NUM_TRAIN, NUM_TEST = 6, 2


@pytest.fixture(scope="module")
def shapes() -> list[MeshShape]:
    return list(generate_shapes(NUM_TRAIN, NUM_TEST, seed=0))


def test_halves_partition_the_categories() -> None:
    first, second = SYNTHETIC_HALVES["1"], SYNTHETIC_HALVES["2"]
    assert set(SYNTHETIC_HALVES) == {"1", "2"}
    assert first and second and not set(first) & set(second)
    assert SYNTHETIC_CATEGORIES == tuple(first + second)
    assert len(set(SYNTHETIC_CATEGORIES)) == len(SYNTHETIC_CATEGORIES)
    # Name-based filtering of ModelNet40's axisymmetric categories must never drop a synthetic one.
    assert not set(SYNTHETIC_CATEGORIES) & set(AXISYMMETRIC_CATEGORIES)
    # Synthetic-trained models are evaluated on real airplanes: airplanes must be in the training half.
    assert "airplane" in first


def test_counts_names_and_order(shapes: list[MeshShape]) -> None:
    expected = [(c, split, i) for c in SYNTHETIC_CATEGORIES
                for split, n in (("train", NUM_TRAIN), ("test", NUM_TEST)) for i in range(n)]
    assert [(s.category, s.split) for s in shapes] == [(c, split) for c, split, _ in expected]
    assert [s.name for s in shapes] == [f"synthetic_{c}_{split}_{i:04d}" for c, split, i in expected]
    assert [s.split for s in generate_shapes(0, 2, seed=0)] == ["test", "test"] * len(SYNTHETIC_CATEGORIES)


def test_deterministic_and_seeded(shapes: list[MeshShape]) -> None:
    state = np.random.get_state()
    again = list(generate_shapes(NUM_TRAIN, NUM_TEST, seed=0))
    assert all(np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
               for a, b in zip(shapes, again))
    assert np.array_equal(np.random.get_state()[1], state[1])  # global numpy state is never used
    # A shape depends on (seed, category, split, index) only, not on the requested counts.
    first = {s.name: s for s in generate_shapes(1, 1, seed=0)}
    assert all(np.array_equal(first[s.name].vertices, s.vertices) for s in shapes if s.name in first)
    other = list(generate_shapes(NUM_TRAIN, NUM_TEST, seed=1))
    assert all(a.vertices.shape != b.vertices.shape or not np.allclose(a.vertices, b.vertices)
               for a, b in zip(shapes, other))


def test_no_two_shapes_alike(shapes: list[MeshShape]) -> None:
    for category in SYNTHETIC_CATEGORIES:
        extents = [np.ptp(s.vertices, axis=0) for s in shapes if s.category == category]
        ratios = {tuple(np.round(e / e.max(), 6)) for e in extents}
        assert len(ratios) == len(extents), category


@pytest.mark.parametrize("bad", [dict(num_train_per_category=-1), dict(num_test_per_category=1.5), dict(seed=-3)])
def test_invalid_arguments(bad: dict) -> None:
    args = dict(num_train_per_category=1, num_test_per_category=1, seed=0) | bad
    with pytest.raises(ConfigError):
        next(generate_shapes(**args))


def test_meshes_are_valid_closed_and_outward(shapes: list[MeshShape]) -> None:
    for s in shapes:
        v, f = s.vertices, s.faces
        assert v.dtype == np.float64 and f.dtype == np.int64 and v.shape[1] == 3 and f.shape[1] == 3, s.name
        assert np.isfinite(v).all() and f.min() >= 0 and f.max() < len(v), s.name
        assert np.unique(f).size == len(v), s.name  # no stray vertices
        assert 100 <= len(f) <= 5000, (s.name, len(f))
        corners = v[f]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        assert np.linalg.norm(cross, axis=1).min() > 1e-9 * np.ptp(v, axis=0).max() ** 2, s.name
        # A union of closed, consistently oriented parts: every directed edge once, with its reverse.
        edges = f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        forward, backward = edges[:, 0] * len(v) + edges[:, 1], edges[:, 1] * len(v) + edges[:, 0]
        assert np.unique(forward).size == len(forward), s.name
        assert np.array_equal(np.sort(forward), np.sort(backward)), s.name
        # ... and each part encloses positive volume, i.e. its faces point outwards.
        graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(len(v), len(v)))
        count, label = connected_components(graph, directed=False)
        volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6
        assert (np.bincount(label[f[:, 0]], volume, minlength=count) > 0).all(), s.name


def _rotational_symmetry(vertices: np.ndarray, faces: np.ndarray) -> tuple[float, float]:
    """(Chamfer to itself rotated about its principal axes / sampling-noise Chamfer, min/max inertia eigenvalue).

    The first value is the smallest over 30, 45 and 72 degree turns about each principal axis; it
    is about 1 for an axisymmetric shape, whose turn about its axis is indistinguishable from a
    fresh sampling.
    """
    v = normalize_mesh(vertices)
    p, q = (sample_surface(v, faces, 2048, np.random.default_rng(s))[0].astype(np.float64) for s in (1, 2))

    def chamfer(a: np.ndarray, b: np.ndarray) -> float:
        return cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean()

    center = p.mean(axis=0)
    eigenvalues, axes = np.linalg.eigh(np.cov((p - center).T))
    turned = min(chamfer(q - center, Rotation.from_rotvec(np.radians(angle) * axes[:, k]).apply(p - center))
                 for k in range(3) for angle in (30, 45, 72))
    return turned / chamfer(p, q), eigenvalues[0] / eigenvalues[-1]


def test_symmetry_check_flags_axisymmetric_shapes() -> None:
    ring = synthetic._torus(1.0, 0.3, n_major=48)
    vase = synthetic._stack(synthetic._superellipse(32), np.linspace(0, 2, 8),
                            (0.5 + 0.3 * np.sin(np.linspace(0, 3, 8)))[:, None])
    for part in (ring, vase):
        assert _rotational_symmetry(part.vertices, part.faces)[0] < 1.15


def test_no_category_is_axisymmetric(shapes: list[MeshShape]) -> None:
    for s in shapes:
        if s.split == "train" and int(s.name[-4:]) < 3:
            turned, isotropy = _rotational_symmetry(s.vertices, s.faces)
            assert turned > 1.3 and isotropy < 0.9, (s.name, turned, isotropy)


def test_sampled_face_normals_are_unit_and_point_outwards(shapes: list[MeshShape]) -> None:
    """The normals the generator's meshes give their samplings (``sample_shape``, what a cache with
    normals stores) point out of the solid: by the divergence theorem the surface mean of n·p is
    3·volume/area > 0 (inward normals would give its negative)."""
    for index, s in enumerate(s for s in shapes if s.name.endswith("test_0000")):
        points, normals = sample_shape(s, 1, 20000, seed=0, shape_index=index)
        np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-6)
        corners = normalize_mesh(s.vertices)[s.faces]
        volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6
        area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum() / 2
        flux = np.einsum("ij,ij->i", points[0], normals[0])
        assert abs(flux.mean() - 3 * volume / area) < 5 * flux.std() / np.sqrt(flux.size), s.name
