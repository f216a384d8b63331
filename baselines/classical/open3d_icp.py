"""Point-to-plane ICP (Chen & Medioni 1992) and Generalized ICP (Segal, Haehnel & Thrun 2009) via Open3D,
started from the identity, with :class:`~baselines.classical.icp.ICP`'s convergence settings. Correspondence
distance, from sweeps of {0.2, 0.5, 1.0} on 30 training pairs (``docs/methods/open3d_icp.md``): point-to-plane
0.5 (ICP's; 1.0 lowered the mean rotation error but nearly doubled the translation error), GICP 1.0 (best on
every measure).

Normals (point-to-plane: the reference's are the plane normals) are estimated with Open3D on the clouds as
received, exactly as for FGR (hybrid radius 0.1, at most 30 neighbours, signed away from the centroid; their
sign does not matter here). Point-to-plane ICP runs Open3D on one thread: with several, its result depended on
the threads' order on a pair near a tie (``benchmarks/studies/golden/README.md``). GICP's covariances are Open3D's plane-to-plane ones built from those normals
(``R diag(ε, 1, 1) Rᵀ``, the paper's), ``epsilon = 1e-3`` (Open3D's and the paper's). Raw covariances
estimated by Open3D (``estimate_covariances``) are used unregularised and gave NaN poses on 300-point clouds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from baselines.base import _positive
from baselines.classical._features import NormalsConfig
from baselines.classical._open3d import one_thread, open3d, to_pcd
from baselines.classical.icp import ICP, ICPConfig


@dataclass
class PointToPlaneICPConfig(ICPConfig, NormalsConfig):
    """Settings of :class:`PointToPlaneICP`: ICP's, and the normals' (FGR's)."""

    def __post_init__(self) -> None:
        ICPConfig.__post_init__(self)
        NormalsConfig.__post_init__(self)


@dataclass
class GeneralizedICPConfig(PointToPlaneICPConfig):
    """Settings of :class:`GeneralizedICP`: ICP's, the normals' (FGR's) and the covariances' regularisation."""

    max_correspondence_distance: float = 1.0
    epsilon: float = 1e-3

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "epsilon")


class PointToPlaneICP(ICP):
    """Open3D point-to-plane ICP from the identity, the reference's normals estimated from its points."""

    name = "point_to_plane_icp"
    needs_normals = True  # estimated here from the points
    config_cls = PointToPlaneICPConfig

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        reg = open3d().pipelines.registration
        cfg: PointToPlaneICPConfig = self.config
        with one_thread():  # with several, a pair near a tie ended 72-130 deg apart in 6 of 200 runs (golden study)
            result = reg.registration_icp(to_pcd(src), cfg.cloud_with_normals(ref), float(cfg.max_correspondence_distance),
                                          np.eye(4), reg.TransformationEstimationPointToPlane(), cfg.criteria())
        return np.asarray(result.transformation, dtype=np.float64)


class GeneralizedICP(PointToPlaneICP):
    """Open3D Generalized ICP (plane-to-plane) from the identity, covariances estimated from the points."""

    name = "gicp"
    config_cls = GeneralizedICPConfig

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        reg = open3d().pipelines.registration
        cfg: GeneralizedICPConfig = self.config
        result = reg.registration_generalized_icp(
            cfg.cloud_with_normals(src), cfg.cloud_with_normals(ref), float(cfg.max_correspondence_distance), np.eye(4),
            reg.TransformationEstimationForGeneralizedICP(float(cfg.epsilon)), cfg.criteria(),
        )
        return np.asarray(result.transformation, dtype=np.float64)
