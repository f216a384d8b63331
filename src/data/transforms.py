"""Composable pair transforms (RPMNet style): plain callables on a dict sample.

Every transform is ``transform(sample, rng) -> sample`` where ``rng`` is the sample's own
``numpy.random.Generator``; nothing reads global NumPy state, so a fixed test set is the same for
any worker count or order. A sample starts as ``{"shape_points": (S, P, 3), ...}`` and ends with
``points_src`` (N, 3), ``points_ref`` (M, 3) and ``transform_gt`` (4, 4), the source→reference
transform (``ref ≈ R @ src + t``).

Every pipeline that starts with :class:`PickPair` also carries ``points_raw``: the reference's clean full
cloud (before crop, resampling and noise), moved with the reference, so in the reference's final frame;
RPM-Net's modified Chamfer distance (:func:`src.metrics.modified_chamfer`) reads it. It draws no random
numbers and nothing crops it, so the pairs are the same with it as without.

Normals are optional: a sample that starts with ``"shape_normals"`` (S, P, 3) ends with unit
``normals_src`` (N, 3) and ``normals_ref`` (M, 3), row ``i`` the normal of point ``i``. They are
rotated with their cloud and cropped, resampled and shuffled with it; noise moves points only (as
RPMNet's ``src/data_loader/transforms.py`` does, l. 204-208 and 106-110, and the official OMNet
code's ``dataset/transformations.py``, l. 241-244, 343-346 and 140-143). Normals draw no random
numbers, so the points and ground truth of a pair are the same with or without them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from src.utils.errors import ConfigError, DatasetError
from src.geometry.numpy_rigid import apply_transform, euler_transform, inverse_transform

Sample = dict[str, Any]
Transform = Callable[[Sample, np.random.Generator], Sample]

SAMPLINGS = ("os", "ts", "halves")
"""``os``: one sampling for both clouds; ``ts``: two samplings (the paper's); ``halves``: the two disjoint
random halves of the OS cloud (what a dataset of one sampling a shape offers instead of TS; never the paper's TS)."""
PARTIAL_MANNERS = ("prnet", "rpmnet", "none")
PAIR_SAMPLINGS = ("independent_samplings", "single_sampling", "disjoint_subsets")
PERTURBATIONS = ("euler", "twist")
CLOUDS = ("src", "ref")
NORMALS = ("none", "cache")
"""``data.normals``: ``none`` (points only) or ``cache`` (the cache's normals travel with the points
as ``normals_src``/``normals_ref``)."""


def move_cloud(sample: Sample, cloud: str, transform: np.ndarray) -> None:
    """Move one cloud by a rigid transform (its points, and its normals by the rotation if any) and keep
    ``transform_gt`` mapping source to reference: moving the source composes the transform's inverse on the
    right, moving the reference composes the transform on the left."""
    sample[f"points_{cloud}"] = apply_transform(transform, sample[f"points_{cloud}"]).astype(np.float32)
    if f"normals_{cloud}" in sample:
        sample[f"normals_{cloud}"] = (sample[f"normals_{cloud}"] @ transform[:3, :3].T).astype(np.float32)
    if cloud == "ref" and "points_raw" in sample:
        sample["points_raw"] = apply_transform(transform, sample["points_raw"]).astype(np.float32)
    if cloud == "src":
        sample["transform_gt"] = sample["transform_gt"] @ inverse_transform(transform)
    else:
        sample["transform_gt"] = transform @ sample["transform_gt"]


def _take(sample: Sample, cloud: str, index: np.ndarray) -> None:
    """Keep rows ``index`` (indices or a mask) of one cloud: its points, and its normals if any."""
    for key in (f"points_{cloud}", f"normals_{cloud}"):
        if key in sample:
            sample[key] = sample[key][index]


def _unit(normals: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length, float32 (PointNet++'s resampled files hold a few (1, 1, 1) rows)."""
    normals = np.asarray(normals, dtype=np.float32)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    if not np.all(length > 0):
        raise DatasetError("the cache holds zero-length or NaN normals: rebuild it with `python -m src.data.prepare`")
    return normals / length


@dataclass
class Compose:
    """Apply transforms in order with the same per-sample generator."""

    transforms: Sequence[Transform]

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        for transform in self.transforms:
            sample = transform(sample, rng)
        return sample


@dataclass
class PickPair:
    """Choose the source and reference clouds of a shape.

    ``ts`` (twice-sampled): two different samplings of the CAD model (``independent_samplings``),
    or two disjoint random subsets of its dense points (``disjoint_subsets``, the closest offline
    equivalent for the PointNet++ resampled layout). ``os`` (once-sampled): one sampling for both.
    ``halves``: the OS cloud's points split into two disjoint random halves, one a cloud.
    The optional ``shape_normals`` are picked with the same rows and made unit length; ``points_raw`` is
    a copy of the reference's points.
    """

    sampling: str
    pair_sampling: str
    num_points: int = 2048

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLINGS:
            raise ConfigError(f"data.sampling must be one of {SAMPLINGS}, got {self.sampling!r}")
        if self.pair_sampling not in PAIR_SAMPLINGS:
            raise DatasetError(f"unknown pair_sampling {self.pair_sampling!r} in the cache manifest")
        if self.sampling == "ts" and self.pair_sampling == "single_sampling":
            raise DatasetError(
                "this cache holds one sampling per shape, so twice-sampled (TS) pairs are impossible: use sampling=os, "
                "or sampling=halves (two disjoint halves of a shape's points, not the paper's TS), or prepare a cache "
                "from the ModelNet40 meshes or the PointNet++ resampled archive"
            )

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        shape = sample.pop("shape_points")
        normals = sample.pop("shape_normals", None)
        for cloud, (sampling, rows) in zip(CLOUDS, self._rows(shape, rng)):
            sample[f"points_{cloud}"] = np.array(shape[sampling][rows], dtype=np.float32)
            if normals is not None:
                sample[f"normals_{cloud}"] = _unit(normals[sampling][rows])
        sample["points_raw"] = sample["points_ref"].copy()
        sample["transform_gt"] = np.eye(4)
        return sample

    def _rows(self, shape: np.ndarray, rng: np.random.Generator) -> list[tuple[int, np.ndarray | slice]]:
        """(sampling index, rows) of the source, then of the reference."""
        if self.sampling == "halves":
            (sampling, rows), _ = PickPair("os", self.pair_sampling, self.num_points)._rows(shape, rng)
            rows = np.arange(shape.shape[1])[rows]
            perm = rng.permutation(len(rows))
            half = len(rows) // 2
            return [(sampling, np.sort(rows[perm[:half]])), (sampling, np.sort(rows[perm[half:2 * half]]))]
        if self.pair_sampling == "disjoint_subsets":
            dense = shape.shape[1]
            needed = self.num_points * (2 if self.sampling == "ts" else 1)
            if dense < needed:
                raise DatasetError(f"shape has {dense} points, {needed} needed for {self.sampling} pairs")
            perm = rng.permutation(dense)[:needed]
            return [(0, np.sort(perm[: self.num_points])), (0, np.sort(perm[-self.num_points :]))]
        i, j = rng.choice(shape.shape[0], size=2, replace=False) if self.sampling == "ts" else (0, 0)
        return [(i, slice(None)), (j, slice(None))]


@dataclass
class RandomRigidTransform:
    """Euler angles uniform in [0, rot_mag] degrees (R = Rx·Ry·Rz), translation uniform in ±trans_mag.

    ``apply_to="ref"`` moves the reference (``ref = R·src + t``, ground truth = the drawn transform:
    the official OMNet code's PRNet manner, ``dataset/transformations.py`` class ``PRNet``, and DCP's
    ``data.py``); ``"src"`` moves the source and the ground truth is the drawn transform's inverse
    (RPMNet's ``RandomTransformSE3``, which the official OMNet code uses for its RPMNet manner).
    ``transform_gt`` always maps source to reference. The moved cloud's normals are rotated by R.
    """

    rot_mag: float = 45.0
    trans_mag: float = 0.5
    apply_to: str = "ref"

    def __post_init__(self) -> None:
        if self.apply_to not in ("src", "ref"):
            raise ConfigError(f"apply_to must be 'src' or 'ref', got {self.apply_to!r}")

    def sample_transform(self, rng: np.random.Generator) -> np.ndarray:
        angles = rng.uniform(0.0, self.rot_mag, size=3)  # about x, y, z
        return euler_transform(angles[::-1], rng.uniform(-self.trans_mag, self.trans_mag, size=3), "zyx")  # Rx·Ry·Rz

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        move_cloud(sample, self.apply_to, self.sample_transform(rng))
        return sample


@dataclass
class PRNetCrop:
    """PRNet's partial manner: keep the ``num_keep`` nearest neighbours of one far random point.

    The point is U[0,1)³ + 500·s·(1,1,1) with one random sign s, the same point for both clouds
    (official OMNet code); each cloud keeps its own nearest neighbours of it.
    """

    num_keep: int = 768

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        far = rng.random(3) + 500.0 * rng.choice([1.0, -1.0])
        for cloud in CLOUDS:
            points = sample[f"points_{cloud}"]
            if points.shape[0] < self.num_keep:
                raise DatasetError(f"points_{cloud} has {points.shape[0]} points, PRNet crop keeps {self.num_keep}")
            _take(sample, cloud, np.sort(nearest_indices(points, far, self.num_keep)))
        return sample


@dataclass
class RPMNetCrop:
    """RPMNet's partial manner: a random half-space through the centroid, shifted to keep ``p_keep``.

    Source and reference are cropped independently (each with its own random direction). At ``p_keep``
    0.5 the plane goes through the centroid unshifted (the points on its positive side, however many),
    as RPM-Net's ``RandomCrop.crop`` (``src/data_loader/transforms.py``, l. 144-147) and the
    ModelLoNet test sets of Predator and RegTR do.
    """

    p_keep: float = 0.7

    def __post_init__(self) -> None:
        if not 0.0 < self.p_keep <= 1.0:
            raise ConfigError(f"p_keep must be in (0, 1], got {self.p_keep}")

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        if self.p_keep >= 1.0:
            return sample
        for cloud in CLOUDS:
            points = sample[f"points_{cloud}"]
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
            dist = (points - points.mean(axis=0)) @ direction
            threshold = 0.0 if self.p_keep == 0.5 else np.percentile(dist, (1.0 - self.p_keep) * 100)
            _take(sample, cloud, dist > threshold)
        return sample


@dataclass
class Resample:
    """Random subset of each cloud: ``num_points`` for an uncropped cloud, ⌈p_keep·num_points⌉ after
    an RPMNet crop (1024 → 717), or exactly ``size`` points when given, with replacement only if a
    cloud is too small."""

    num_points: int = 1024
    p_keep: float = 1.0
    size: int | None = None

    @property
    def target(self) -> int:
        return self.size if self.size is not None else math.ceil(self.p_keep * self.num_points)

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        for cloud in CLOUDS:
            size = sample[f"points_{cloud}"].shape[0]
            _take(sample, cloud, rng.choice(size, size=self.target, replace=size < self.target))
        return sample


@dataclass
class GaussianNoise:
    """Add N(0, sigma²) noise clipped to ±clip to every coordinate of both clouds (points only:
    normals stay as they are, as RPMNet's and OMNet's ``RandomJitter``)."""

    sigma: float = 0.01
    clip: float = 0.05

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        if self.sigma <= 0:
            return sample
        for key in ("points_src", "points_ref"):
            noise = np.clip(rng.normal(0.0, self.sigma, size=sample[key].shape), -self.clip, self.clip)
            sample[key] = (sample[key] + noise).astype(np.float32)
        return sample


@dataclass
class Shuffle:
    """Permute the points (and normals) of each cloud independently."""

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        for cloud in CLOUDS:
            _take(sample, cloud, rng.permutation(sample[f"points_{cloud}"].shape[0]))
        return sample


def median_spacing(points: np.ndarray) -> float:
    """Median distance from a point to its nearest other point of the same cloud."""
    return float(np.median(cKDTree(points).query(points, k=2)[0][:, 1]))


def overlap_fraction(points: np.ndarray, other: np.ndarray, radius: float) -> float:
    """Fraction of ``points`` within ``radius`` of ``other`` (both in the same frame)."""
    return float((cKDTree(other).query(points, distance_upper_bound=radius)[0] < radius).mean())


def nearest_indices(points: np.ndarray, centre: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` points nearest to ``centre``, nearest first (a partial sort: O(n), about
    4x faster than building a KD-tree for one query)."""
    dist = np.sum((points - centre) ** 2, axis=1)
    if k >= len(points):
        return np.argsort(dist, kind="stable")
    idx = np.argpartition(dist, k - 1)[:k]
    return idx[np.argsort(dist[idx], kind="stable")]


def _nearest(points: np.ndarray, candidates: np.ndarray, seed: np.ndarray, k: int) -> np.ndarray:
    """The ``k`` entries of index array ``candidates`` whose points are nearest to ``seed``."""
    if k <= 0:
        return candidates[:0]
    return candidates[nearest_indices(points[candidates], seed, k)]


@dataclass
class OverlapRatioCrop:
    """The paper's overlap-ratio protocol ("Different Overlapping Ratio", Sec. 4): partial X, then
    build Y from two adjacent parts of the overlapping and non-overlapping regions.

    1. X (source) keeps the ``num_keep`` nearest neighbours of a far random point p (PRNet's
       crop): the part of the shape inside a ball around p whose radius is the distance to the
       farthest kept point.
    2. The overlapping region O of the full reference is the same ball around p carried into the
       reference frame by the ground truth (the surface X covers); N is the rest. The ball is
       huge (p is ~500 away), so O and N meet along an almost flat border.
    3. A seed on that border (the point of O nearest to a random point of N); Y takes the
       ``round(ratio·num_keep)`` points of O and the ``num_keep - round(ratio·num_keep)`` points of
       N nearest to the seed: two adjacent parts, a fraction ``ratio`` of Y overlapping X.

    With once-sampled data the fraction of Y with an exact counterpart in X is exactly
    ``round(ratio·num_keep) / num_keep``. When a region holds too few points (twice-sampled data
    at ratio 1.0: O has num_keep ± a few points), Y is built at the same ratio from what there is
    and topped up to ``num_keep`` by repeating random points of each part in that ratio.
    """

    ratio: float
    num_keep: int = 768

    def __post_init__(self) -> None:
        if not 0.0 <= self.ratio <= 1.0:
            raise ConfigError(f"overlap_ratio must be in [0, 1], got {self.ratio}")

    def __call__(self, sample: Sample, rng: np.random.Generator) -> Sample:
        src, ref = sample["points_src"], sample["points_ref"]
        for key, points in (("points_src", src), ("points_ref", ref)):
            if points.shape[0] < self.num_keep:
                raise DatasetError(f"{key} has {points.shape[0]} points, the overlap-ratio crop keeps {self.num_keep}")
        far = rng.random(3) + 500.0 * rng.choice([1.0, -1.0])
        dist, idx = cKDTree(src).query(far, k=self.num_keep)
        gt = np.asarray(sample["transform_gt"], dtype=np.float64)
        far_ref = gt[:3, :3] @ far + gt[:3, 3]  # float64: distances of ~500 must stay exact to ~1e-7
        inside = np.linalg.norm(ref.astype(np.float64) - far_ref, axis=1) <= float(np.max(dist)) + 1e-6
        over, non = np.flatnonzero(inside), np.flatnonzero(~inside)
        if over.size == 0:
            raise DatasetError("no reference point lies in the part of the shape the partial source covers")
        want_over = int(round(self.ratio * self.num_keep))
        want_non = self.num_keep - want_over
        scale = min(1.0, over.size / want_over if want_over else 1.0, non.size / want_non if want_non else 1.0)
        n_over, n_non = min(over.size, int(round(want_over * scale))), min(non.size, int(round(want_non * scale)))
        if non.size:
            seed = ref[_nearest(ref, over, ref[rng.choice(non)], 1)[0]]
        else:
            seed = ref[rng.choice(over)]
        part_over, part_non = _nearest(ref, over, seed, n_over), _nearest(ref, non, seed, n_non)
        keep = [part_over, part_non]
        if n_over < want_over and part_over.size:
            keep.append(rng.choice(part_over, size=want_over - n_over))
        if n_non < want_non and part_non.size:
            keep.append(rng.choice(part_non, size=want_non - n_non))
        keep = np.sort(np.concatenate(keep))
        if keep.size != self.num_keep:  # a ratio that one empty part cannot give (e.g. 0.0 without N)
            keep = np.sort(np.concatenate([keep, rng.choice(keep, size=self.num_keep - keep.size)]))
        _take(sample, "src", np.sort(np.atleast_1d(idx)))
        _take(sample, "ref", keep)
        return sample
