"""FilterReg (Gao & Tedrake, CVPR 2019), rigid, point-to-point: the EM of a Gaussian mixture like CPD, its
E-step a Gaussian filter over the reference (a permutohedral lattice), so that each step is linear in the
number of points instead of CPD's N×M.

Backend: PyPI's ``probreg`` 0.3.8 (MIT): an optional dependency. Its wheel is built from the sdist (C++,
pybind11, ~10 min on 2 cores); it installs with the project's Open3D 0.20 and NumPy 2 (the sdist's
``setup.py`` requires an unpinned ``open3d``, though its ``pyproject.toml`` names 0.18.0): ``pip install
probreg`` (or the ``probreg`` extra). Without it, constructing :class:`FilterReg` raises a ConfigError naming
the install. ``sigma2 = None`` starts from probreg's data-driven variance and ``update_sigma2`` re-estimates it
each step (down to ``min_sigma2``); ``w`` is the outlier weight; ``max_iterations`` / ``tolerance`` stop the
EM. Defaults: probreg's, but ``update_sigma2 = True`` (on 30 training pairs: 100 % under 5°, mean 0.59°; probreg's
False: 53 %, 11.1°; ``docs/methods/filterreg.md``). probreg composes its rotation from single-precision Kabsch
steps without renormalising (|RᵀR − I| up to 4e-5 after 50 steps, 1e-4 past ~200, where an estimate counts as
non-rigid): the rotation returned is its nearest rotation. Its Kabsch and kernel sums are OpenMP reductions, whose
result depends on the thread count (0.15° apart between 1 and 2 threads on the golden pairs): it runs on one
OpenMP thread (``threadpoolctl``, in the extra). Its E-step's lattice takes positions in units of σ: a pair
reaching past :data:`LATTICE_REACH` of them (clouds ~1e7 times their size apart) crashes probreg's process, so such a
pair is refused with one line.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from baselines.base import Registrator, RegistratorConfig, _positive, _within
from baselines.classical._optional import NeedsPackage
from src.geometry.numpy_rigid import project_to_rotation, rigid_transform
from src.utils.errors import PointCloudError


#: Farthest coordinate, in units of the smallest σ, handed to probreg: its permutohedral lattice registered a pair
#: reaching 1.1e8 of them (two clouds 9e6 apart in the working frame, σ 0.01) and aborted the process at 1.25e8
#: (``free(): invalid size``); refused with a margin of 4.5.
LATTICE_REACH = 2.5e7


@dataclass
class FilterRegConfig(RegistratorConfig):
    """Settings of :class:`FilterReg` (see the module docstring and ``docs/methods/filterreg.md``)."""

    sigma2: float | None = None
    update_sigma2: bool = True
    w: float = 0.0
    max_iterations: int = 50
    tolerance: float = 1e-3
    min_sigma2: float = 1e-4

    def __post_init__(self) -> None:
        _positive(self, "max_iterations", "tolerance", "min_sigma2")
        if self.sigma2 is not None:
            _positive(self, "sigma2")
        _within(self, "w", interval="[0, 1)")


@functools.cache
def registration_filterreg() -> Callable[..., Any]:
    """probreg's ``filterreg.registration_filterreg`` (imported on first use: an optional package)."""
    from probreg import filterreg

    return filterreg.registration_filterreg

class FilterReg(NeedsPackage, Registrator):
    """probreg's rigid point-to-point FilterReg (optional package ``probreg``)."""

    name = "filterreg"
    module, package = "probreg", "probreg"
    extra = "probreg"  # built from its sdist: an extra of its own (pyproject.toml)
    config_cls = FilterRegConfig

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        from threadpoolctl import threadpool_limits

        cfg: FilterRegConfig = self.config
        sigma = math.sqrt(min(cfg.min_sigma2, cfg.sigma2 if cfg.sigma2 is not None else math.inf))
        reach = max(float(np.abs(src).max()), float(np.abs(ref).max())) / sigma
        if reach > LATTICE_REACH:
            raise PointCloudError(
                f"FilterReg: the pair reaches {reach:.3g} σ from its centre (σ {sigma:.3g}), beyond the {LATTICE_REACH:.3g} "
                "that probreg's lattice holds (its process crashes there): pre-align the clouds, or raise min_sigma2")
        with threadpool_limits(1, user_api="openmp"):  # its reductions' sums depend on the thread count
            result = registration_filterreg()(
                src, ref, sigma2=cfg.sigma2, update_sigma2=bool(cfg.update_sigma2), w=float(cfg.w),
                maxiter=int(cfg.max_iterations), tol=float(cfg.tolerance), min_sigma2=float(cfg.min_sigma2),
            )
        rotation = project_to_rotation(result.transformation.rot)  # its float32 steps' drift off SO(3)
        return rigid_transform(rotation, np.asarray(result.transformation.t))
