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

from baselines.base import Registrator, _positive, refuse_planar
from baselines.classical._features import NormalsConfig
from baselines.classical._open3d import found_transform, one_thread, open3d, require_normals, to_pcd
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
    planar_blind = "the residuals along the reference's normals, all parallel, do not see a motion within the plane"

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """A planar reference, or one with fewer than six normals (only the reference's are used)."""
        cfg: PointToPlaneICPConfig = self.config
        refuse_planar(self.name, self.planar_blind, ref=ref)
        require_normals(self.name, cfg.normal_radius, cfg.normal_max_nn, ref=ref)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        reg = open3d().pipelines.registration
        cfg: PointToPlaneICPConfig = self.config
        start = np.eye(4)
        with one_thread():  # with several, a pair near a tie ended 72-130 deg apart in 6 of 200 runs (golden study)
            result = reg.registration_icp(to_pcd(src), cfg.cloud_with_normals(ref), float(cfg.max_correspondence_distance),
                                          start, reg.TransformationEstimationPointToPlane(), cfg.criteria())
        return found_transform(self.name, result, "point-to-plane ICP", start)


class GeneralizedICP(PointToPlaneICP):
    """Open3D Generalized ICP (plane-to-plane) from the identity, covariances estimated from the points."""

    name = "gicp"
    config_cls = GeneralizedICPConfig
    planar_blind = ""  # its plane-to-plane covariances still weigh a motion within the plane

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """Nothing beyond the interface's check: where a point has no normal its covariance falls back to a
        point's, and GICP registers planar and few-point clouds."""
        Registrator._refuse_undetermined(self, src, ref)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        reg = open3d().pipelines.registration
        cfg: GeneralizedICPConfig = self.config
        start = np.eye(4)
        result = reg.registration_generalized_icp(
            cfg.cloud_with_normals(src), cfg.cloud_with_normals(ref), float(cfg.max_correspondence_distance), start,
            reg.TransformationEstimationForGeneralizedICP(float(cfg.epsilon)), cfg.criteria(),
        )
        return found_transform(self.name, result, "GICP", start)
