"""Mesh normalisation and area-weighted uniform surface sampling (fully vectorised)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from src.data.mesh import MeshShape
from src.utils.errors import DatasetError

NORMALIZATION = "bbox_center_unit_sphere"
"""Name recorded in cache manifests for :func:`normalize_mesh`."""
METHOD = "area_weighted_uniform"
"""Name recorded in cache manifests for :func:`sample_surface`."""


def normalize_mesh(vertices: np.ndarray, name: str = "mesh") -> np.ndarray:
    """Centre on the bounding-box centre and scale so the farthest vertex has norm 1.

    Applied once per mesh, before sampling, so that every sampling of a shape shares one frame.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or not np.isfinite(v).all():
        raise DatasetError(f"shape {name}: vertices must be a non-empty finite (V, 3) array, got {v.shape}")
    v = v - (v.min(axis=0) + v.max(axis=0)) / 2
    radius = np.linalg.norm(v, axis=1).max()
    if radius == 0:
        raise DatasetError(f"shape {name}: all vertices coincide, cannot normalise")
    return v / radius


@dataclass(frozen=True)
class _Surface:
    """Per-face data needed to draw surface points: corners, cumulative areas, unit normals."""

    corners: np.ndarray  # (F, 3, 3)
    cumulative_area: np.ndarray  # (F,)
    normals: np.ndarray  # (F, 3)

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray, name: str) -> _Surface:
        faces = np.asarray(faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise DatasetError(f"shape {name}: mesh has no triangle faces (faces shape {faces.shape})")
        if faces.min() < 0 or faces.max() >= len(vertices):
            raise DatasetError(f"shape {name}: face indices out of range for {len(vertices)} vertices")
        corners = np.asarray(vertices, dtype=np.float64)[faces]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        double_area = np.linalg.norm(cross, axis=1)
        total = double_area.sum()
        if not np.isfinite(total) or total <= 0:
            raise DatasetError(f"shape {name}: mesh has zero (or non-finite) surface area, cannot sample")
        normals = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
        return cls(corners, np.cumsum(double_area), normals)

    def sample(self, num_points: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        # side="right" never lands on a zero-area face (its cumulative area equals its predecessor's).
        u = rng.random(num_points) * self.cumulative_area[-1]
        face = np.minimum(np.searchsorted(self.cumulative_area, u, side="right"), len(self.corners) - 1)
        r1, r2 = rng.random((2, num_points, 1))
        s = np.sqrt(r1)
        a, b, c = self.corners[face].transpose(1, 0, 2)
        points = (1 - s) * a + s * (1 - r2) * b + s * r2 * c
        return points.astype(np.float32), self.normals[face].astype(np.float32)


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, num_points: int, rng: np.random.Generator, name: str = "mesh"
) -> tuple[np.ndarray, np.ndarray]:
    """Draw ``num_points`` points uniformly on the surface (face chosen ∝ area, uniform barycentric).

    Returns ``(points, normals)``, both ``(P, 3)`` float32; normals are the face normals.
    Raises :class:`DatasetError` naming the shape for meshes without faces or without area.
    """
    return _Surface.of(vertices, faces, name).sample(num_points, rng)


def sample_shape(
    shape: MeshShape, num_samplings: int, num_points: int, seed: int, shape_index: int
) -> tuple[np.ndarray, np.ndarray]:
    """Normalise the mesh once, then sample it ``num_samplings`` times.

    Sampling ``s`` uses ``np.random.default_rng([seed, shape_index, s])``. Returns ``(points,
    normals)``, both ``(S, P, 3)`` float32.
    """
    surface = _Surface.of(normalize_mesh(shape.vertices, shape.name), shape.faces, shape.name)
    draws = [surface.sample(num_points, np.random.default_rng([seed, shape_index, s])) for s in range(num_samplings)]
    return np.stack([p for p, _ in draws]), np.stack([n for _, n in draws])
