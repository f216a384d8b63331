"""Small Open3D helpers shared by the classical baselines (clouds, normals)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from src.utils.errors import ConfigError

#: How estimated normals are signed (Open3D's PCA normals have an arbitrary sign).
NORMAL_ORIENTATIONS = ("centroid", "none", "origin")


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
