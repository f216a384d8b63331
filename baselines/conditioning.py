"""Conditioning of a pair before a method registers it, so that no single call gives a wrong result or
runs unbounded on input far from what the methods are tuned for.

* The working frame: a pair whose radius lies outside :data:`WORKING_RADIUS`, or with a point farther than
  :data:`WORKING_REACH` from the origin, is registered centred and scaled by a power of two
  (:func:`working_frame`, :class:`Similarity`), the estimate mapped back.
* The point budget: clouds beyond a method's ``point_budget`` are voxel down-sampled with one voxel size
  (:func:`within_budget`).

Used by :meth:`baselines.base.Registrator.register`; the measurements behind the bounds:
``docs/methods/conditioning.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: Pair radii (farthest point from its cloud's centroid, larger cloud) the methods are tuned for.
WORKING_RADIUS = (0.125, 2.0)
#: Farthest distance from the origin of a point of a pair inside the working frame.
WORKING_REACH = 4.0
#: Most points per cloud a method registers by default (the timings behind it: docs/methods/conditioning.md).
POINT_BUDGET = 10_000


@dataclass(frozen=True)
class Similarity:
    """``x -> (x - centre) / scale``, taking a pair into the working frame."""

    centre: np.ndarray
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale

    def map_back(self, transform: np.ndarray) -> np.ndarray:
        """``transform`` (estimated in the working frame) in the input's coordinates."""
        out = transform.copy()
        out[:3, 3] = self.centre - transform[:3, :3] @ self.centre + self.scale * transform[:3, 3]
        return out


def _farthest(points: np.ndarray, centre: np.ndarray | float = 0.0) -> float:
    """Distance from ``centre`` of the farthest of ``points``."""
    offsets = points - centre
    return math.sqrt(float(np.einsum("ij,ij->i", offsets, offsets).max()))


def pair_radius(src: np.ndarray, ref: np.ndarray) -> float:
    """Distance from its cloud's centroid of the farthest point, the larger of the two clouds."""
    return max(_farthest(c, c.mean(axis=0)) for c in (src, ref))


def working_frame(src: np.ndarray, ref: np.ndarray) -> Similarity | None:
    """The similarity taking a checked pair into the working frame, or None if it lies inside."""
    radius = pair_radius(src, ref)
    reach = max(_farthest(src), _farthest(ref))
    if WORKING_RADIUS[0] <= radius <= WORKING_RADIUS[1] and reach <= WORKING_REACH:
        return None
    return Similarity(0.5 * (src.mean(axis=0) + ref.mean(axis=0)), float(2.0 ** round(math.log2(radius))))


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """Each point's voxel (cube of side ``voxel``) as one integer."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    return np.ravel_multi_index(tuple(keys.T), tuple(keys.max(axis=0) + 1))


def voxel_down_sample(points: np.ndarray, voxel: float) -> np.ndarray:
    """The centroid of the points of each occupied voxel (Open3D's ``voxel_down_sample`` rule)."""
    _, inverse, counts = np.unique(_voxel_keys(points, voxel), return_inverse=True, return_counts=True)
    sums = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return sums / counts[:, None]


#: Ratio of neighbouring voxel sizes tried by :func:`budget_voxel_size` (~1.4x in a surface's voxel count).
_VOXEL_STEP = 2.0**0.25


def _fits(clouds: Sequence[np.ndarray], voxel: float, budget: int) -> bool:
    return max(len(np.unique(_voxel_keys(c, voxel))) for c in clouds) <= budget


def budget_voxel_size(clouds: Sequence[np.ndarray], budget: int) -> float:
    """The smallest voxel size at which each cloud occupies at most ``budget`` voxels, on a ladder
    of ratio ``_VOXEL_STEP`` from the guess for a surface (``extent / sqrt(budget)``), not below
    ``extent / budget``. The ladder is walked on a fixed random subset of ``4 x budget`` points
    per cloud (fast at any size), then the full clouds confirm the size (or enlarge it)."""
    extent = max(float(np.ptp(c, axis=0).max()) for c in clouds)
    rng = np.random.default_rng(0)
    subsets = [c[rng.choice(len(c), 4 * budget, replace=False)] if len(c) > 4 * budget else c for c in clouds]
    voxel = extent / math.sqrt(budget)
    while not _fits(subsets, voxel, budget):  # ends: one voxel holds a cloud once voxel > extent
        voxel *= _VOXEL_STEP
    while voxel / _VOXEL_STEP >= extent / budget and _fits(subsets, voxel / _VOXEL_STEP, budget):
        voxel /= _VOXEL_STEP
    while not _fits(clouds, voxel, budget):
        voxel *= _VOXEL_STEP
    return voxel


def within_budget(src: np.ndarray, ref: np.ndarray, budget: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The pair as given, or voxel down-sampled with one voxel size if a cloud has more than ``budget`` points."""
    if budget is None or max(len(src), len(ref)) <= budget:
        return src, ref
    voxel = budget_voxel_size((src, ref), budget)
    return voxel_down_sample(src, voxel), voxel_down_sample(ref, voxel)


def _unchanged(transform: np.ndarray) -> np.ndarray:
    return transform


def condition(src: np.ndarray, ref: np.ndarray, *, normalise_frame: bool = True, budget: int | None = POINT_BUDGET
              ) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """A checked pair as a method registers it: in the working frame (when ``normalise_frame`` and it lies
    outside), then within the point ``budget``; with ``undo``, which maps a transform estimated on the
    conditioned pair back into the input's coordinates."""
    frame = working_frame(src, ref) if normalise_frame else None
    if frame is not None:
        src, ref = frame.apply(src), frame.apply(ref)
    src, ref = within_budget(src, ref, budget)
    return src, ref, (_unchanged if frame is None else frame.map_back)
