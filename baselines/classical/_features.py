"""Settings shared by the classical baselines that estimate normals or FPFH features (FGR, RANSAC, the
Open3D ICP variants), the one pipeline that computes them (defaults: FGR's, see ``fgr.py``), and the base of
the methods that match the features of both clouds."""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from baselines.base import Registrator, RegistratorConfig, _positive
from baselines.classical._open3d import (
    NORMAL_ORIENTATIONS,
    estimate_normals,
    found_transform,
    open3d,
    require_normals,
    search_param,
    to_pcd,
)
from baselines.conditioning import voxel_down_sample
from src.utils.errors import ConfigError


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


class FPFHMatcher(Registrator):
    """A method that matches the FPFH features of both clouds in one Open3D pipeline (FGR, RANSAC): the
    features come from :meth:`FPFHConfig.pair_features`, the match from :meth:`_match` (its ``solver`` name)."""

    needs_normals = True  # estimated here from the points; none need to be supplied
    planar_blind = "its FPFH features are all alike (the normals are parallel), so no match tells the points apart"
    solver = "feature matching"

    def setup(self) -> None:
        open3d()

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """A planar cloud, or one with fewer than six normals (on the clouds the features are computed on)."""
        super()._refuse_undetermined(src, ref)
        cfg: FPFHConfig = self.config
        src, ref = (c if cfg.voxel_size is None else voxel_down_sample(c, cfg.voxel_size) for c in (src, ref))
        require_normals(self.name, cfg.normal_radius, cfg.normal_max_nn, src=src, ref=ref)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        (src_pcd, src_fpfh), (ref_pcd, ref_fpfh) = self.config.pair_features(src, ref)
        result = self._match(open3d().pipelines.registration, src_pcd, ref_pcd, src_fpfh, ref_fpfh)
        return self._refine(found_transform(self.name, result, self.solver), src, ref)

    @abstractmethod
    def _match(self, reg: Any, src_pcd: Any, ref_pcd: Any, src_fpfh: Any, ref_fpfh: Any) -> Any:
        """The Open3D registration result (``.transformation``) of the two featured clouds."""

    def _refine(self, transform: np.ndarray, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """The transform after an optional refinement (none by default)."""
        return transform
