"""Conditioning of a pair before a method registers it, so that no single call gives a wrong result or
runs unbounded on input far from what the methods are tuned for.

* Exact duplicates: repeated points are registered once (:func:`deduplicated`), so that repeating a point
  changes no method's answer.
* The frame a method is tuned for: a classical method's working frame (a pair whose radius lies outside
  :data:`WORKING_RADIUS`, or with a point farther than :data:`WORKING_REACH` from the origin, is registered
  centred and scaled by a power of two: :func:`working_frame`), a network's training frame
  (:class:`TrainingFrame`: a pair in other units or far from the origin is registered in the unit sphere);
  the estimate is mapped back (:class:`Similarity`).
* The point budget: clouds beyond a method's ``point_budget`` are voxel down-sampled with one voxel size
  (:func:`within_budget`).

Used by :meth:`baselines.base.Registrator.register`; the measurements behind the bounds:
``docs/methods/conditioning.md``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from src.data.scans import shared_similarity

#: Pair radii (farthest point from its cloud's centroid, larger cloud) the methods are tuned for.
WORKING_RADIUS = (0.125, 2.0)
#: Farthest distance from the origin of a point of a pair inside the working frame.
WORKING_REACH = 4.0
#: Farthest point from the origin of a shape normalised into the unit sphere, give or take the published point sets'
#: rounding (ModelNet40's resampled airplanes and bathtubs reach 1.0015).
UNIT_SPHERE = 1.01
#: Most points per cloud a method registers by default (the timings behind it: docs/methods/conditioning.md).
POINT_BUDGET = 10_000


@dataclass(frozen=True)
class Similarity:
    """``x -> (x - centre) / scale``, taking a pair into a method's frame."""

    centre: np.ndarray
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.scale

    def map_back(self, transform: np.ndarray) -> np.ndarray:
        """``transform`` (estimated in the frame) in the input's coordinates: the same rotation."""
        out = transform.copy()
        out[:3, 3] = self.centre - transform[:3, :3] @ self.centre + self.scale * transform[:3, 3]
        return out


#: Where a pair is registered: the similarity taking a checked pair into a method's frame, None to take it as given.
FrameRule = Callable[[np.ndarray, np.ndarray], Similarity | None]


def deduplicated(points: np.ndarray) -> np.ndarray:
    """``points`` without exact repeats (each point once, in the order of first appearance); the same array
    when no point repeats."""
    _, first = np.unique(points, axis=0, return_index=True)
    return points if len(first) == len(points) else points[np.sort(first)]


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


@dataclass(frozen=True)
class TrainingFrame:
    """The frame a network was trained in: shapes in the unit sphere (meshes normalised by
    ``bbox_center_unit_sphere``, the published point sets as provided, scan pairs by their union), one cloud of each
    pair then moved by up to ``translation`` along each axis, and noise clipped at ``noise_clip`` per coordinate (a
    card's ``experiment.pair``: ``trans_mag``, ``noise_clip``).

    A pair lies in it when one cloud is within the unit sphere (give or take the noise), the other within the
    reach of a translation, and the pair's radius is at least the working frame's smallest (a pair at 1e-3 lies
    within the sphere too); such a pair (every pair of the protocols) is registered as given. Any other is
    registered after :func:`shared_similarity` (the centroid of both clouds to the origin, their farthest point
    onto the unit sphere: the scan pairs' frame), which preserves its rotation and maps its translation back.
    """

    translation: float = 0.5
    noise_clip: float = 0.05

    @classmethod
    def of_pair(cls, pair: Mapping[str, Any]) -> TrainingFrame:
        """The frame of a training run's pair settings (``data.pair``; a missing key takes the default)."""
        default = cls()
        return cls(float(pair.get("trans_mag", default.translation)), float(pair.get("noise_clip", default.noise_clip)))

    def contains(self, src: np.ndarray, ref: np.ndarray) -> bool:
        """Whether a checked pair lies in this frame."""
        jitter = math.sqrt(3.0) * self.noise_clip
        near, far = sorted((_farthest(src), _farthest(ref)))
        return (near <= UNIT_SPHERE + jitter and far <= UNIT_SPHERE + math.sqrt(3.0) * self.translation + jitter
                and pair_radius(src, ref) >= WORKING_RADIUS[0])

    def __call__(self, src: np.ndarray, ref: np.ndarray) -> Similarity | None:
        """The similarity taking a checked pair into this frame, or None if it lies inside (a :data:`FrameRule`)."""
        if self.contains(src, ref):
            return None
        centre, scale = shared_similarity(src, ref)
        return Similarity(centre, scale)


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


def condition(src: np.ndarray, ref: np.ndarray, *, frame: FrameRule | None = working_frame,
              budget: int | None = POINT_BUDGET) -> tuple[np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """A checked pair as a method registers it: each point once (:func:`deduplicated`), in the method's frame
    (the similarity ``frame`` gives, when it gives one), then within the point ``budget``; with ``undo``, which
    maps a transform estimated on the conditioned pair back into the input's coordinates. A duplicate-free pair
    inside the frame and the budget is returned as the same arrays."""
    src, ref = deduplicated(src), deduplicated(ref)
    similarity = None if frame is None else frame(src, ref)
    if similarity is not None:
        src, ref = similarity.apply(src), similarity.apply(ref)
    src, ref = within_budget(src, ref, budget)
    return src, ref, (_unchanged if similarity is None else similarity.map_back)
