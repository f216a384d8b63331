"""Deterministic test fixtures for registration code: an asymmetric L-shaped point set,
known rigid motions, error measures, and toy registrators that sleep, raise, crash or
return garbage (for exercising :func:`baselines.runner.run_pairs`).

Lives in the package (not under ``tests/``) so that worker processes started with
``spawn`` can import the toy classes by name.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from baselines.base import Registrator, RegistratorConfig
from src.utils.errors import CheckpointError
from src.geometry.numpy_rigid import apply_transform, rigid_transform, rotation_angle

# --------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------


def l_shape_surface(n: int = 600, seed: int = 0) -> np.ndarray:
    """``n`` random points on the surface of an asymmetric L-shaped solid, unit-sphere scaled.

    The L is the union of two boxes of different lengths (a 1.0 x 0.3 x 0.45 bar and a
    0.3 x 0.8 x 0.45 leg), so it has no rotational or mirror symmetry a rigid registration
    could confuse with the truth. Points are sampled uniformly by area on the outer faces,
    centred on the origin and scaled so the farthest point is at distance 1.
    """
    rng = np.random.default_rng(seed)
    boxes = [((0.0, 0.0, 0.0), (1.0, 0.3, 0.45)), ((0.0, 0.3, 0.0), (0.3, 1.1, 0.45))]
    faces = []  # (origin, u, v) rectangles
    for lo, hi in boxes:
        lo, hi = np.array(lo), np.array(hi)
        size = hi - lo
        for axis in range(3):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            u = np.zeros(3)
            u[u_ax] = size[u_ax]
            v = np.zeros(3)
            v[v_ax] = size[v_ax]
            for side in (lo, hi):
                origin = lo.copy()
                origin[axis] = side[axis]
                faces.append((origin, u, v))
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v in faces])
    pts = []
    # oversample, then drop points inside the other box (the faces where the boxes touch)
    counts = rng.multinomial(3 * n, areas / areas.sum())
    for (origin, u, v), k in zip(faces, counts):
        ab = rng.random((k, 2))
        pts.append(origin + ab[:, :1] * u + ab[:, 1:] * v)
    pts = np.concatenate(pts)
    eps = 1e-9

    def strictly_inside(p, lo, hi):
        return np.all((p > np.array(lo) + eps) & (p < np.array(hi) - eps), axis=1)

    def on_shared_face(p):
        # the leg's bottom face y = 0.3 within x < 0.3 lies inside the bar's top face region
        return (np.abs(p[:, 1] - 0.3) < eps) & (p[:, 0] < 0.3 - eps)

    inside = np.zeros(len(pts), dtype=bool)
    for lo, hi in boxes:
        inside |= strictly_inside(pts, lo, hi)
    pts = pts[~inside & ~on_shared_face(pts)]
    pts = pts[rng.permutation(len(pts))[:n]]
    pts = pts - pts.mean(axis=0)
    return pts / np.linalg.norm(pts, axis=1).max()


def euler_transform(angles_deg: tuple[float, float, float], translation: tuple[float, float, float]) -> np.ndarray:
    """4x4 transform: rotation ``Rz @ Ry @ Rx`` by the given angles (degrees), then translation.

    Multiplied out by hand rather than taken from :func:`src.geometry.numpy_rigid.euler_transform`
    (SciPy's, ``seq="xyz"``: the same rotation within 6e-16, never bit-identical), so that the fixtures stay
    bit-for-bit those the tests' tolerances were set on (an exact symmetric-ICP step is checked to 1e-6°,
    the resolution of one ulp of a rotation's trace).
    """
    ax, ay, az = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rigid_transform(rz @ ry @ rx, translation)


def make_pair(
    transform: np.ndarray, n: int = 600, seed: int = 0, twice_sampled: bool = False, noise: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """``(src, ref)`` with ``ref = transform(src')``; ``src'`` is ``src`` (once-sampled) or an
    independent sample of the same surface (twice-sampled), optionally with Gaussian noise."""
    src = l_shape_surface(n, seed)
    base = l_shape_surface(n, seed + 1000) if twice_sampled else src
    ref = apply_transform(transform, base)
    if noise:
        rng = np.random.default_rng(seed + 7)
        ref = ref + rng.normal(0.0, noise, ref.shape)
    return src, ref


def paper_range_pair(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(src, ref, transform)``: two samplings of ``n`` points of the L-shaped solid, the reference
    moved by Euler angles in [0°, 45°] and a translation in ±0.5 (the paper's range), seeded by
    ``(seed, n)``. Used for timing, where the content of the pair hardly matters."""
    rng = np.random.default_rng([seed, n])
    src = l_shape_surface(n, seed=int(rng.integers(1 << 30)))
    base = l_shape_surface(n, seed=int(rng.integers(1 << 30)))
    transform = euler_transform(tuple(rng.uniform(0.0, 45.0, 3)), tuple(rng.uniform(-0.5, 0.5, 3)))
    return src, apply_transform(transform, base), transform


def rotation_error_deg(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Geodesic angle between the two rotations, in degrees."""
    return rotation_angle(estimate[:3, :3].T @ truth[:3, :3])


def translation_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    return float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


# --------------------------------------------------------------------------------------
# Toy registrators
# --------------------------------------------------------------------------------------


@dataclass
class ToyConfig(RegistratorConfig):
    """Each ``*_on`` lists source-cloud sizes (numbers of points) that trigger a misbehaviour."""

    sleep_s: float = 0.0  # every call sleeps this long first
    raise_on: tuple[int, ...] = ()  # raise ValueError (two-line message)
    hang_on: tuple[int, ...] = ()  # sleep for an hour
    slow_on: tuple[tuple[int, float], ...] = ()  # (size, seconds): sleep that long
    crash_on: tuple[int, ...] = ()  # kill the process: os._exit(3)
    nan_on: tuple[int, ...] = ()  # return a transform containing NaN
    scale_on: tuple[int, ...] = ()  # return a scaling (not a rigid transform)
    setup_error: str = ""  # if set, setup() raises CheckpointError(setup_error)


class ToyRegistrator(Registrator):
    """Returns the centroid-aligning translation; misbehaves for clouds of chosen sizes.

    The *number of source points* selects the pair that misbehaves, so tests can craft
    pairs without any state shared between processes.
    """

    name = "toy"
    config_cls = ToyConfig

    def setup(self) -> None:
        if self.config.setup_error:
            raise CheckpointError(self.config.setup_error)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        cfg: ToyConfig = self.config
        n = len(src)
        if cfg.sleep_s:
            time.sleep(cfg.sleep_s)
        if n in cfg.raise_on:
            raise ValueError(f"toy failure on a {n}-point cloud\nsecond line")
        if n in cfg.hang_on:
            time.sleep(3600)
        time.sleep(dict(cfg.slow_on).get(n, 0.0))
        if n in cfg.crash_on:
            os._exit(3)
        if n in cfg.nan_on:
            out = np.eye(4)
            out[0, 3] = np.nan
            return out
        if n in cfg.scale_on:
            return np.diag([2.0, 2.0, 2.0, 1.0])
        return rigid_transform(np.eye(3), ref.mean(axis=0) - src.mean(axis=0))
