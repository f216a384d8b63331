"""What registering a pair gives back: :class:`RegistrationResult`, in the spirit of Open3D's
``RegistrationResult``: the transform, the time, whether the method failed or timed out and why, and
the inlier fit of the moved source against the reference.

    >>> result = get_registrator("icp").register_result(src, ref)      # one pair
    >>> result.transform, result.seconds, result.failed, result.timed_out, result.reason
    >>> result.fitness, result.inlier_rmse                             # within FIT_THRESHOLD
    >>> results = run_pairs(icp, pairs, timeout_s=60)                  # the same type, one per pair

One type for a single call (:meth:`baselines.base.Registrator.register_result`) and for the runners
(:func:`baselines.runner.run_pairs`, :func:`baselines.learned.adapter.run_batches`); the grid writes
its fields to its per-pair parquet. A failed pair carries the identity as its estimate (that is how
the grid counts it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from src.utils.errors import ConfigError
from src.geometry.numpy_rigid import apply_transform

__all__ = ["FIT_THRESHOLD", "RegistrationResult", "inlier_fit", "one_line", "transform_problem"]

#: Default inlier distance of :attr:`RegistrationResult.fitness` and ``inlier_rmse``, in the clouds'
#: units: 0.05 is the translation bound of the paper's coarser success criterion, the clip of its
#: noise and about the point spacing of a unit-sphere object of 700-2,048 points, so that the
#: overlapping points of a well-aligned pair count as inliers also when the clouds are two samplings.
FIT_THRESHOLD = 0.05


def transform_problem(transform: Any, atol: float = 1e-4) -> str | None:
    """Why ``transform`` is not a proper rigid 4x4 transform, or ``None`` if it is.

    Checks the shape, finiteness, the bottom row ``[0, 0, 0, 1]``, ``R^T R = I`` and
    ``det R = +1`` (all to ``atol``).
    """
    try:
        arr = np.asarray(transform, dtype=np.float64)
    except (TypeError, ValueError):
        return f"estimate is not numeric ({type(transform).__name__})"
    if arr.shape != (4, 4):
        return f"estimate has shape {tuple(arr.shape)}, expected (4, 4)"
    if not np.isfinite(arr).all():
        return "estimate contains NaN or infinite entries"
    if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        return f"estimate's bottom row is {np.round(arr[3], 6).tolist()}, expected [0, 0, 0, 1]"
    rot = arr[:3, :3]
    ortho = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if ortho > atol:
        return f"estimate's rotation is not orthonormal (max |R^T R - I| = {ortho:.2e})"
    det = float(np.linalg.det(rot))
    if abs(det - 1.0) > atol:
        return f"estimate's rotation has det {det:+.4f}, expected +1 (a reflection)"
    return None


def one_line(exc: BaseException) -> str:
    """``<ExceptionType>: <first line of its message>``: a failure's reason."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def check_threshold(threshold: float | None) -> None:
    """ConfigError unless ``threshold`` is None or a positive finite number."""
    if threshold is not None and not (isinstance(threshold, (int, float)) and not isinstance(threshold, bool)
                                      and math.isfinite(threshold) and threshold > 0):
        raise ConfigError(f"threshold must be a distance > 0 (or None: no fit), got {threshold!r}")


def inlier_fit(src: np.ndarray, ref: np.ndarray, transform: np.ndarray, threshold: float) -> tuple[float, float]:
    """``(fitness, inlier_rmse)`` of ``src`` moved by ``transform`` against ``ref``, as Open3D's
    ``evaluate_registration``: the share of moved source points whose nearest reference point lies
    within ``threshold``, and the root mean square of those distances (0 when there is none); ConfigError for a
    threshold that is no positive distance (a negative one would count every point an inlier)."""
    from scipy.spatial import cKDTree

    check_threshold(threshold)
    distances, _ = cKDTree(ref).query(apply_transform(transform, src), distance_upper_bound=threshold)
    inliers = distances[np.isfinite(distances)]
    rmse = math.sqrt(float(np.mean(inliers**2))) if len(inliers) else 0.0
    return len(inliers) / len(src), rmse


@dataclass(frozen=True)
class RegistrationResult:
    """The outcome of registering one pair.

    Attributes:
        transform: the estimate ``T`` (4, 4) with ``ref ≈ T[:3, :3] @ src + T[:3, 3]``; the identity
            when the pair failed.
        seconds: registration time (not the method's one-off set-up, nor the input checks or the fit).
        failed: the method raised, crashed, timed out or gave no proper rigid transform.
        timed_out: failed by taking longer than the time limit.
        reason: why it failed, one line (``""`` when it did not).
        fitness: share of the moved source points within the threshold of a reference point (Open3D's
            ``fitness``); None when failed or not evaluated.
        inlier_rmse: root mean square distance of those inliers (Open3D's ``inlier_rmse``); None likewise.
    """

    transform: np.ndarray = field(repr=False)
    seconds: float
    failed: bool = False
    timed_out: bool = False
    reason: str = ""
    fitness: float | None = None
    inlier_rmse: float | None = None

    @classmethod
    def failure(cls, reason: str, seconds: float, timed_out: bool = False) -> RegistrationResult:
        """A failed pair: the identity as its estimate."""
        return cls(np.eye(4), seconds, failed=True, timed_out=timed_out, reason=reason)

    @classmethod
    def of_estimate(cls, estimate: Any, seconds: float, timeout_s: float | None = None) -> RegistrationResult:
        """A method's raw estimate as a result: a failure if it is not a finite proper rigid 4x4, or
        if it took longer than ``timeout_s``."""
        problem = transform_problem(estimate)
        if problem is not None:
            return cls.failure(f"non-rigid estimate: {problem}", seconds)
        if timeout_s is not None and seconds > timeout_s:
            return cls.failure(f"timed out: took {seconds:.1f} s > {timeout_s:g} s", seconds, timed_out=True)
        return cls(np.asarray(estimate, dtype=np.float64), seconds)

    def with_fit(self, src: np.ndarray, ref: np.ndarray, threshold: float | None = FIT_THRESHOLD) -> RegistrationResult:
        """This result with :func:`inlier_fit` at ``threshold`` (unchanged when failed or ``threshold`` is None)."""
        if self.failed or threshold is None:
            return self
        fitness, rmse = inlier_fit(src, ref, self.transform, threshold)
        return dataclasses.replace(self, fitness=fitness, inlier_rmse=rmse)
