"""Point-cloud input checks, one place for all: the datasets (:mod:`src.data.dataset`,
:mod:`src.data.scan_pairs`), every registration method (:mod:`baselines.base`) and the grid's test sets.

They take NumPy arrays, torch tensors (on any device; recognised without importing torch) or nested
lists, and refuse a bad cloud with one line, a :class:`~src.utils.errors.PointCloudError` that starts with the
cloud's name: not real numbers (bool, complex, object or text arrays are refused, never converted), not
(N, 3), fewer than :data:`MIN_POINTS` points, NaN or infinite coordinates, coordinates beyond
:data:`MAX_COORDINATE` (their squared distances overflow float32), and (unless allowed) all points
on one line, within the precision of the input's own dtype (a line stored in float32 is a line).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from src.utils.errors import PointCloudError

#: Fewest points a cloud may have: a rigid transform is not determined by fewer than 3.
MIN_POINTS = 3
#: Relative size under which the second singular value of a centred float64 cloud counts as zero (a line).
_COLLINEAR_RTOL = 1e-9
#: The same in units of the input dtype's machine epsilon, for less precise inputs (float32: 1.9e-6).
_COLLINEAR_EPS = 16
#: Largest coordinate magnitude whose squared distances stay finite in float32 (nearest neighbours, Chamfer
#: distance, the learned methods' similarity matrices): sqrt(float32 max) / 4, about 4.6e18.
MAX_COORDINATE = float(np.sqrt(np.finfo(np.float32).max)) / 4
#: dtype kinds of real numbers: signed and unsigned integers, floats.
_REAL_KINDS = "iuf"


def _as_float64(points: Any, name: str) -> tuple[np.ndarray, float]:
    """``points`` as float64, and the relative precision of the dtype it came in."""
    if hasattr(points, "detach"):  # a torch tensor: on the CPU, without its graph
        points = points.detach().cpu()
        if points.is_floating_point() and points.element_size() < 4:  # (b)float16: no NumPy twin for bfloat16
            points = points.float()
    try:
        arr = np.asarray(points)
    except (TypeError, ValueError) as exc:
        raise PointCloudError(f"{name}: cannot be read as an array of numbers ({exc})") from None
    if arr.dtype.kind not in _REAL_KINDS:
        raise PointCloudError(f"{name}: expected real numbers (integers or floats), got a {arr.dtype} array: convert it "
                              "explicitly, e.g. points.astype(float)")
    eps = float(np.finfo(arr.dtype).eps) if arr.dtype.kind == "f" else 0.0
    return arr.astype(np.float64), max(_COLLINEAR_RTOL, _COLLINEAR_EPS * eps)


def check_cloud(points: Any, name: str = "points", allow_degenerate: bool = False) -> np.ndarray:
    """``points`` as a C-contiguous float64 ``(N, 3)`` array, or PointCloudError.

    ``allow_degenerate`` skips the collinearity test (an SVD: a fifth of the time of making a pair), for
    clouds that are not registered as they are checked: normals, and the datasets' samples (registration
    methods check their input again).
    """
    arr, rtol = _as_float64(points, name)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise PointCloudError(f"{name}: expected an (N, 3) array of points, got shape {tuple(arr.shape)}")
    if arr.shape[0] < MIN_POINTS:
        raise PointCloudError(f"{name}: needs at least {MIN_POINTS} points, got {arr.shape[0]}")
    bad = ~np.isfinite(arr)
    if bad.any():
        n_bad = int(bad.any(axis=1).sum())
        raise PointCloudError(f"{name}: {n_bad} of {arr.shape[0]} points have NaN or infinite coordinates")
    largest = float(np.abs(arr).max())
    if largest > MAX_COORDINATE:
        raise PointCloudError(f"{name}: coordinates up to {largest:.3g}, beyond {MAX_COORDINATE:.3g}, where squared "
                              "distances overflow single precision: rescale the cloud (e.g. to the unit sphere)")
    if not allow_degenerate:
        _check_not_degenerate(arr, name, rtol)
    return np.ascontiguousarray(arr)


def _check_not_degenerate(arr: np.ndarray, name: str, rtol: float = _COLLINEAR_RTOL) -> None:
    """Raise PointCloudError if all points lie on one line (fewer than 3 distinct points included) to
    the relative precision ``rtol``: the rotation about that line is then undetermined."""
    singular = np.linalg.svd(arr - arr.mean(axis=0), compute_uv=False)
    if singular[1] > rtol * singular[0]:
        return
    distinct = len(np.unique(arr, axis=0))
    shape = "all the same point" if distinct == 1 else f"all on one line ({distinct} distinct)"
    raise PointCloudError(
        f"{name}: degenerate cloud, its {arr.shape[0]} points are {shape}: a rigid transform needs at least "
        f"{MIN_POINTS} points not on one line"
    )


def check_batch(points: Any, name: str = "points") -> np.ndarray:
    """``points`` as a float64 ``(B, N, 3)`` array of checked clouds, or PointCloudError."""
    arr, _ = _as_float64(points, name)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise PointCloudError(f"{name}: expected a (B, N, 3) batch of point clouds, got shape {tuple(arr.shape)}")
    if arr.shape[0] == 0:
        raise PointCloudError(f"{name}: the batch is empty (B = 0)")
    for b in range(arr.shape[0]):
        check_cloud(points[b], f"{name}[{b}]")  # (in the input's dtype, for its precision)
    return np.ascontiguousarray(arr)
