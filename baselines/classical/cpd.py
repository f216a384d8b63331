"""Rigid Coherent Point Drift (Myronenko & Song, TPAMI 2010) with the scale fixed at 1.

The source points are the centroids of a Gaussian mixture fitted by EM to the reference points, with a uniform
component of weight ``w`` for points that no centroid explains, under a rigid motion. The iteration is the
authors' (their CPD package, ``cpd_register.m`` with ``opt.scale=0, opt.normalize=0``, which it otherwise turns
back into ``scale=1``, line 120: ``cpd_rigid.m``'s ``scale=0`` branch, E-step ``cpd_P.c``), in NumPy and float64
(lines of the copy the golden file ran, dpacheco0921/MeshVol_CPD_Registration@5a74b8a ``core/``; the same iteration
as fieldtrip/fieldtrip ``external/cpd/core``):

* σ² starts from the mean squared distance of all pairs of points (``cpd_rigid.m:66``);
* each E-step gives the responsibilities and the negative log-likelihood L (``cpd_P.c:35-73``); EM stops after
  ``max_iterations`` steps, once the relative change of L is at most ``tolerance``, or once σ² ≤ 10 eps
  (``cpd_rigid.m:76, 86``);
* each M-step solves the rotation by SVD (no reflection, ``cpd_rigid.m:98``) and, the scale being 1,
  σ² = (tr(X̂ᵀ d(Pᵀ1) X̂) + tr(Ŷᵀ d(P1) Ŷ) − 2 tr(AᵀR)) / (N_P D) (``cpd_rigid.m:106``; the paper's Fig. 2 gives
  the scaled case only).

Where every kernel of a reference point underflows to 0 (only possible with ``w = 0``, at a small σ², for a point
far from every centroid: a partial cloud's non-overlapping part) the authors' code divides 0 by 0; here that point
gets no responsibility and leaves the M-step; where none is left (N_P = 0: the clouds lie so far apart that the
uniform term explains every point) their code divides 0 by 0, and this one stops with a PointCloudError. The golden
file checks the whole against the authors' code (``benchmarks/studies/golden``). Each EM step holds an N×M matrix, so a cloud is registered with at most
``point_budget = 4,096`` points (voxel down-sampled beyond, :mod:`baselines.conditioning`). Defaults: the authors'
150 iterations and tolerance 1e-5 (``cpd_register.m:90-91``); outlier weight 0.9 (theirs 0.1, line 94), chosen on training pairs
of partial clouds (``docs/methods/cpd.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial.distance import cdist

from baselines.base import Registrator, RegistratorConfig, _positive, _within
from src.geometry.numpy_rigid import rigid_transform
from src.utils.errors import PointCloudError


@dataclass
class CPDConfig(RegistratorConfig):
    """Settings of :class:`CPD` (see the module docstring and ``docs/methods/cpd.md``)."""

    w: float = 0.9
    max_iterations: int = 150
    tolerance: float = 1e-5
    sigma2: float | None = None

    def __post_init__(self) -> None:
        _positive(self, "max_iterations", "tolerance")
        if self.sigma2 is not None:
            _positive(self, "sigma2")
        _within(self, "w", interval="[0, 1)")


class Responsibilities(NamedTuple):
    """One E-step: ``p1`` (M,) = P1, ``pt1`` (N,) = Pᵀ1, ``px`` (M, D) = PX and the negative log-likelihood."""

    p1: np.ndarray
    pt1: np.ndarray
    px: np.ndarray
    nll: float


def expectation(ref: np.ndarray, centroids: np.ndarray, sigma2: float, w: float) -> Responsibilities:
    """The E-step of CPD: posteriors of the M ``centroids`` (plus the uniform term of weight ``w``) for each of the
    N ``ref`` points, with the kernel exp(−|x − y|² / 2σ²)."""
    n, d = ref.shape
    m = centroids.shape[0]
    kernel = cdist(centroids, ref, "sqeuclidean")  # (M, N), from the differences as the authors' cpd_P.c
    np.exp(np.divide(kernel, -2.0 * sigma2, out=kernel), out=kernel)  # in place: at 4,096 points each is 128 MiB
    uniform = w * m * (2.0 * np.pi * sigma2) ** (0.5 * d) / ((1.0 - w) * n)
    total = kernel.sum(axis=0) + uniform  # (N,)
    reached = total > 0
    inverse = np.divide(1.0, total, out=np.zeros_like(total), where=reached)
    posterior = np.multiply(kernel, inverse, out=kernel)
    pt1 = np.where(reached, 1.0 - uniform * inverse, 0.0)
    nll = float(-np.log(total[reached]).sum() + d * n * np.log(sigma2) / 2.0)
    return Responsibilities(posterior.sum(axis=1), pt1, posterior @ ref, nll)


def rigid_cpd(ref: np.ndarray, src: np.ndarray, w: float, max_iterations: int, tolerance: float,
              sigma2: float | None = None) -> tuple[np.ndarray, np.ndarray, int]:
    """Rotation R, translation t (``src @ R.T + t`` fits ``ref``) and the number of EM steps, scale fixed at 1."""
    n, d = ref.shape
    m = src.shape[0]
    if sigma2 is None:
        sigma2 = float((m * np.trace(ref.T @ ref) + n * np.trace(src.T @ src) - 2.0 * ref.sum(0) @ src.sum(0)) / (m * n * d))
    rotation, translation, moved = np.eye(d), np.zeros(d), src
    steps, change, nll = 0, tolerance + 10.0, 0.0
    while steps < max_iterations and change > tolerance and sigma2 > 10.0 * np.finfo(float).eps:
        previous = nll
        p1, pt1, px, nll = expectation(ref, moved, sigma2, w)
        change = abs((nll - previous) / nll)
        mass = pt1.sum()
        if not mass > 0:
            raise PointCloudError(
                f"CPD: every reference point is explained by the outlier term alone (σ² {sigma2:.3g}, w {w}): the clouds "
                "lie too far apart for it; pre-align them (e.g. by their centroids) or lower w")
        mu_ref, mu_src = ref.T @ pt1 / mass, src.T @ p1 / mass
        a = px.T @ src - mass * np.outer(mu_ref, mu_src)
        u, singular, vt = np.linalg.svd(a)
        signs = np.ones(d)
        signs[-1] = np.linalg.det(u @ vt)
        rotation = (u * signs) @ vt
        spread_ref = (ref**2 * pt1[:, None]).sum() - mass * mu_ref @ mu_ref
        spread_src = (src**2 * p1[:, None]).sum() - mass * mu_src @ mu_src
        sigma2 = float(abs(spread_ref + spread_src - 2.0 * (singular * signs).sum()) / (mass * d))
        translation = mu_ref - rotation @ mu_src
        moved = src @ rotation.T + translation
        steps += 1
    return rotation, translation, steps


class CPD(Registrator):
    """Rigid CPD with the scale fixed at 1 (the authors' iteration, NumPy)."""

    name = "cpd"
    config_cls = CPDConfig
    point_budget = 4096

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        cfg: CPDConfig = self.config
        rotation, translation, _ = rigid_cpd(ref.astype(np.float64), src.astype(np.float64), float(cfg.w),
                                             int(cfg.max_iterations), float(cfg.tolerance), cfg.sigma2)
        return rigid_transform(rotation, translation)
