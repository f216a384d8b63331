"""Small Open3D helpers shared by the classical baselines (clouds, normals, what a registration found)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from baselines.base import require_found
from src.utils.errors import ConfigError, PointCloudError

#: How estimated normals are signed (Open3D's PCA normals have an arbitrary sign).
NORMAL_ORIENTATIONS = ("centroid", "none", "origin")
#: Fewest points of a cloud that must get a normal: a rigid motion has six unknowns, a point-to-plane residual
#: gives one equation.
MIN_NORMALS = 6


def open3d():
    """Import Open3D lazily (it takes about a second and pulls in TBB threads)."""
    import open3d as o3d

    return o3d


@contextmanager
def one_thread() -> Iterator[None]:
    """Open3D on one thread within the block (its previous limit restored after): a call whose parallel reductions
    make its result depend on the threads' order gives the same result on every run."""
    utility = open3d().utility
    previous = utility.get_max_threads()
    utility.set_max_threads(1)
    try:
        yield
    finally:
        utility.set_max_threads(previous)


def to_pcd(points: np.ndarray):
    """An ``open3d.geometry.PointCloud`` holding ``points`` (N, 3)."""
    o3d = open3d()
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))


def search_param(radius: float | None, max_nn: int):
    """Hybrid (radius + KNN cap) search, or plain KNN when ``radius`` is None."""
    o3d = open3d()
    if radius is None:
        return o3d.geometry.KDTreeSearchParamKNN(knn=int(max_nn))
    return o3d.geometry.KDTreeSearchParamHybrid(radius=float(radius), max_nn=int(max_nn))


def estimate_normals(pcd, radius: float | None, max_nn: int, orientation: str = "centroid") -> np.ndarray:
    """Estimate normals on ``pcd`` in place with Open3D (PCA of the neighbourhood); return them.

    ``orientation``:
      * ``"centroid"`` — flip each normal to point away from the cloud's own centroid
        (outward for roughly convex objects; invariant to a rigid motion of the cloud, so
        source and reference get comparable signs),
      * ``"none"`` — keep Open3D's raw eigenvector sign (arbitrary per point),
      * ``"origin"`` — point towards the coordinate origin (PCL's default viewpoint (0, 0, 0);
        not invariant to the unknown transform).
    """
    if orientation not in NORMAL_ORIENTATIONS:
        raise ConfigError(
            f"unknown normal orientation '{orientation}'; choose one of {', '.join(NORMAL_ORIENTATIONS)}"
        )
    pcd.estimate_normals(search_param(radius, max_nn))
    if orientation == "centroid":
        pts = np.asarray(pcd.points)
        pcd.orient_normals_towards_camera_location(pts.mean(axis=0))
        pcd.normals = open3d().utility.Vector3dVector(-np.asarray(pcd.normals))
    elif orientation == "origin":
        pcd.orient_normals_towards_camera_location(np.zeros(3))
    return np.asarray(pcd.normals).copy()


def with_normals(points: np.ndarray, radius: float | None, max_nn: int) -> int:
    """How many of ``points`` get a normal from :func:`estimate_normals`: those with at least 3 points (themselves
    included) in their neighbourhood (within ``radius``; any, with ``radius`` None), as Open3D needs; it gives the
    others (0, 0, 1)."""
    from scipy.spatial import cKDTree

    if max_nn < 3:
        return 0
    if radius is None:
        return len(points)
    return int((cKDTree(points).query_ball_point(points, radius, return_length=True) >= 3).sum())


def require_normals(method: str, radius: float | None, max_nn: int, **clouds: np.ndarray) -> None:
    """PointCloudError unless each of the named ``clouds`` has :data:`MIN_NORMALS` points that get a normal."""
    within, fix = ("", "") if radius is None else (f" within normal_radius={radius:g} (in the working frame)",
                                                   ", or a larger normal_radius")
    for name, cloud in clouds.items():
        found = with_normals(cloud, radius, max_nn)
        if found < MIN_NORMALS:
            raise PointCloudError(
                f"{method}: only {found} of the {name} cloud's {len(cloud)} distinct points get a normal (3 neighbours"
                f"{within}), {MIN_NORMALS} needed: give a denser cloud{fix}")


def found_transform(method: str, result: Any, solver: str, start: np.ndarray | None = None) -> np.ndarray:
    """The transformation of an Open3D registration ``result``, or RegistrationError where ``solver`` found nothing
    (:func:`~baselines.base.require_found` on its correspondence set; ``start``: a local solver's initial pose)."""
    transform = np.asarray(result.transformation, dtype=np.float64)
    require_found(method, solver, len(result.correspondence_set), start is None or np.array_equal(transform, start))
    return transform
