"""Settings shared by the classical baselines that estimate normals or FPFH features (FGR, RANSAC, the
Open3D ICP variants), and the one pipeline that computes them; the defaults are FGR's (see ``fgr.py``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from baselines.base import RegistratorConfig, _positive
from baselines.classical._open3d import NORMAL_ORIENTATIONS, estimate_normals, open3d, search_param, to_pcd
from src.errors import ConfigError


@dataclass
class NormalsConfig(RegistratorConfig):
    """Open3D PCA normals over a hybrid neighbourhood (radius, at most ``normal_max_nn`` neighbours),
    signed by ``normal_orientation`` (:func:`~baselines.classical._open3d.estimate_normals`)."""

    normal_radius: float = 0.1
    normal_max_nn: int = 30
    normal_orientation: str = "centroid"

    def __post_init__(self) -> None:
        _positive(self, "normal_radius", "normal_max_nn")
        if self.normal_orientation not in NORMAL_ORIENTATIONS:
            raise ConfigError(
                f"{type(self).__qualname__}.normal_orientation must be one of {', '.join(NORMAL_ORIENTATIONS)}, "
                f"got {self.normal_orientation!r}"
            )

    def cloud_with_normals(self, points: np.ndarray):
        """An Open3D cloud of ``points`` with its estimated normals."""
        pcd = to_pcd(points)
        estimate_normals(pcd, self.normal_radius, self.normal_max_nn, self.normal_orientation)
        return pcd


@dataclass
class FPFHConfig(NormalsConfig):
    """Normals, then FPFH (Rusu 2009) over ``feature_radius`` (at most ``feature_max_nn`` neighbours), after an
    optional voxel down-sampling (``voxel_size``; None: the clouds as given); ``seed`` seeds Open3D's sampling."""

    voxel_size: float | None = None
    feature_radius: float = 0.25
    feature_max_nn: int = 100
    seed: int | None = 0  # Open3D's random sampling (FGR's tuples, RANSAC's samples): None leaves it unseeded

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "feature_radius", "feature_max_nn")
        if self.voxel_size is not None:
            _positive(self, "voxel_size")

    def features(self, points: np.ndarray):
        """(Open3D cloud with normals, its FPFH feature) of ``points``."""
        pcd = to_pcd(points)
        if self.voxel_size is not None:
            pcd = pcd.voxel_down_sample(float(self.voxel_size))
        estimate_normals(pcd, self.normal_radius, self.normal_max_nn, self.normal_orientation)
        fpfh = open3d().pipelines.registration.compute_fpfh_feature(
            pcd, search_param(self.feature_radius, self.feature_max_nn)
        )
        return pcd, fpfh

    def pair_features(self, src: np.ndarray, ref: np.ndarray) -> tuple:
        """Open3D's sampler seeded with ``seed``, then :meth:`features` of both clouds: ``(src, ref)`` pairs."""
        if self.seed is not None:
            open3d().utility.random.seed(int(self.seed))
        return self.features(src), self.features(ref)
