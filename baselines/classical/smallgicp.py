"""GICP and VGICP of ``small_gicp`` (Koide 2024, the fastest CPU fine-registration library of the field;
GICP: Segal, Haehnel & Thrun 2009; VGICP: Koide, Yokozuka, Oishi & Banno 2021), started from the identity.

Backend: PyPI's ``small-gicp`` (MIT), an optional dependency (``pip install small-gicp`` or the ``classical``
extra); without it, constructing :class:`SmallGICP` raises a ConfigError naming the install. small_gicp's own
pipeline is used: a voxel-grid down-sampling at ``downsampling_resolution`` (its default 0.25 is for metre-scale
LiDAR scans; here it would leave a unit-sphere object a few dozen points), per-point covariances from the
``num_neighbors`` nearest neighbours, a KD-tree (GICP) or a Gaussian voxel map of ``voxel_resolution``
(VGICP), then Gauss-Newton up to ``max_iterations`` with correspondences within
``max_correspondence_distance``. ``registration_type`` = ``GICP`` (default) or ``VGICP``. One thread per
pair (``num_threads = 1``, the library's default; the grid's runner registers pairs in parallel). Defaults:
``downsampling_resolution = 0.01`` (below these clouds' point spacing: no down-sampling), ``num_neighbors = 20``
(10, the library's, was worse), ``max_correspondence_distance = 1.0`` and GICP (VGICP at voxel 0.05-0.2 stayed
near the initial pose), from sweeps on 30 training pairs: ``docs/methods/small_gicp.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from baselines.base import Registrator, RegistratorConfig, _positive, require_found
from baselines.classical._optional import NeedsPackage
from src.utils.errors import ConfigError

REGISTRATION_TYPES = ("GICP", "VGICP")


@dataclass
class SmallGICPConfig(RegistratorConfig):
    """Settings of :class:`SmallGICP` (see the module docstring and ``docs/methods/small_gicp.md``)."""

    registration_type: str = "GICP"
    max_correspondence_distance: float = 1.0
    downsampling_resolution: float = 0.01
    num_neighbors: int = 20
    voxel_resolution: float = 0.1
    max_iterations: int = 30
    num_threads: int = 1

    def __post_init__(self) -> None:
        _positive(self, "max_correspondence_distance", "downsampling_resolution", "num_neighbors",
                  "voxel_resolution", "max_iterations", "num_threads")
        if self.registration_type not in REGISTRATION_TYPES:
            raise ConfigError(f"SmallGICPConfig.registration_type must be one of {', '.join(REGISTRATION_TYPES)}, "
                              f"got {self.registration_type!r}")


class SmallGICP(NeedsPackage, Registrator):
    """small_gicp's GICP or VGICP from the identity (optional package ``small-gicp``)."""

    name = "small_gicp"
    module, package = "small_gicp", "small-gicp"
    config_cls = SmallGICPConfig

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        import small_gicp

        cfg: SmallGICPConfig = self.config
        common = {"num_threads": int(cfg.num_threads)}
        (ref_pc, ref_tree), (src_pc, _) = (
            small_gicp.preprocess_points(cloud, float(cfg.downsampling_resolution), int(cfg.num_neighbors), **common)
            for cloud in (ref, src)
        )
        options = {"max_correspondence_distance": float(cfg.max_correspondence_distance),
                   "max_iterations": int(cfg.max_iterations), **common}
        if cfg.registration_type == "VGICP":
            voxels = small_gicp.GaussianVoxelMap(float(cfg.voxel_resolution))
            voxels.insert(ref_pc)
            result = small_gicp.align(voxels, src_pc, **options)
        else:
            result = small_gicp.align(ref_pc, src_pc, ref_tree, registration_type="GICP", **options)
        transform = np.asarray(result.T_target_source, dtype=np.float64)
        require_found(self.name, cfg.registration_type, int(result.num_inliers), np.array_equal(transform, np.eye(4)))
        return transform
