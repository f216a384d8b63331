r"""Symmetric ICP (Rusinkiewicz, "A Symmetric Objective Function for ICP", SIGGRAPH 2019).

Our own vectorised numpy implementation (the OMNet paper used PCL's
``TransformationEstimationSymmetricPointToPlaneLLS``), on Open3D normals and a KD-tree.

The symmetric objective splits the motion ``M`` that takes ``p`` (source) onto ``q``
(reference) into two half-rotations ``R`` (angle θ about the unit axis ``a``) around a
translation: ``M = R · T(t) · R``, and measures the residual along the sum of both normals:

.. math::

   \varepsilon = \sum_i \big[(R p_i - R^{-1} q_i + t)\cdot(R n_{p,i} + R^{-1} n_{q,i})\big]^2 .

Linearising (paper, Sec. 3.2) with :math:`n_i = n_{p,i} + n_{q,i}`,
:math:`\tilde a = a\tan\theta` and :math:`\tilde t = t/\cos\theta` gives a linear least
squares problem in the six unknowns :math:`(\tilde a, \tilde t)`:

.. math::

   \varepsilon \approx \sum_i \big[(p_i - q_i)\cdot n_i + ((p_i + q_i)\times n_i)\cdot\tilde a
                                   + n_i\cdot\tilde t\big]^2 ,

solved through its 6x6 normal equations. The step is then recovered as
:math:`\theta = \arctan\lVert\tilde a\rVert`, :math:`a = \tilde a/\lVert\tilde a\rVert`,
:math:`t = \tilde t\cos\theta`, and composed as ``M = R_{a,θ} · T(t) · R_{a,θ}`` (a total
rotation of 2θ). Following the paper, each step works in coordinates centred on the
correspondences' centroid and scaled to unit RMS radius (for conditioning), and maps back.

Per iteration: transform the source by the current estimate, find each source point's
nearest reference point (scipy ``cKDTree`` built once on the reference), reject pairs
farther apart than ``max_correspondence_distance``, orient each source normal to agree
with its partner's (PCL's ``enforce_same_direction_normals``: estimated normals have an
arbitrary sign, and a flipped pair would cancel in ``n_p + n_q``), drop pairs whose normal
sum vanishes, solve, compose. Stops after ``max_iterations`` or when a step rotates by less
than ``rotation_tolerance`` (rad) and translates by less than ``translation_tolerance``.

Defaults (unit-sphere objects, rotations ≤ 45° per axis, translations ≤ 0.5 per axis,
started from the identity): ``max_correspondence_distance = 0.5`` for the same reason as
point-to-point ICP (``baselines/classical/icp.py``: much smaller thresholds reject nearly
every correspondence at the start). ``python -m baselines.classical.sweep symmetric_icp``
(200 noisy TS RPMNet-manner airplane pairs, 717 points), mean / median rotation error:
0.3 → 26.6° / 7.4°, 0.5 → 21.7° / 7.5°, 1.0 → 21.2° / 9.9° (paper: 19.6°–21.8°).
``max_iterations = 30`` (PCL's default is 10; 30 and 50 gave the same errors), tolerances
1e-6; normals as for FGR (Open3D PCA, hybrid radius 0.1 / at most 30 neighbours, signed
away from each cloud's centroid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from baselines.base import Registrator, RegistratorConfig, _positive, project_to_rotation, rigid_transform
from baselines.classical._open3d import NORMAL_ORIENTATIONS, estimate_normals, open3d, to_pcd
from src.errors import ConfigError


@dataclass
class SymmetricICPConfig(RegistratorConfig):
    """Settings of :class:`SymmetricICP` (see the module docstring for why these defaults)."""

    max_correspondence_distance: float = 0.5
    max_iterations: int = 30
    rotation_tolerance: float = 1e-6
    translation_tolerance: float = 1e-6
    normal_radius: float | None = 0.1
    normal_max_nn: int = 30
    normal_orientation: str = "centroid"
    min_correspondences: int = 6

    def __post_init__(self) -> None:
        _positive(self, "max_correspondence_distance", "max_iterations", "normal_max_nn")
        _positive(self, "rotation_tolerance", "translation_tolerance", allow_zero=True)
        if self.normal_radius is not None:
            _positive(self, "normal_radius")
        if self.min_correspondences < 6:
            raise ConfigError(
                f"SymmetricICPConfig.min_correspondences must be >= 6 (six unknowns), got {self.min_correspondences!r}"
            )
        if self.normal_orientation not in NORMAL_ORIENTATIONS:
            raise ConfigError(
                f"SymmetricICPConfig.normal_orientation must be one of {', '.join(NORMAL_ORIENTATIONS)}, "
                f"got {self.normal_orientation!r}"
            )


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix for a rotation by ``angle`` (rad) about the unit vector ``axis``."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def symmetric_step(p: np.ndarray, q: np.ndarray, n: np.ndarray) -> np.ndarray | None:
    """One linearised symmetric point-to-plane step; 4x4 ``M`` moving ``p`` towards ``q``.

    ``p``, ``q`` (K, 3) are corresponding points, ``n`` (K, 3) the normal sums
    ``n_p + n_q``. Returns None if the 6x6 system is singular.
    """
    centre = 0.5 * (p.mean(axis=0) + q.mean(axis=0))
    pc = p - centre
    qc = q - centre
    scale = float(np.sqrt(0.5 * (np.mean(np.sum(pc * pc, axis=1)) + np.mean(np.sum(qc * qc, axis=1)))))
    if not np.isfinite(scale) or scale <= 0.0:
        return None
    pc /= scale
    qc /= scale

    # residual r_i + J_i · x with x = (ã, t̃):  J_i = [(p+q) x n, n],  r_i = (p - q) · n
    jac = np.concatenate([np.cross(pc + qc, n), n], axis=1)  # (K, 6)
    res = np.einsum("ij,ij->i", pc - qc, n)  # (K,)
    ata = jac.T @ jac
    atb = -jac.T @ res
    try:
        x = np.linalg.solve(ata, atb)
    except np.linalg.LinAlgError:
        return None
    if not np.isfinite(x).all():
        return None

    a_tilde, t_tilde = x[:3], x[3:]
    tan_theta = float(np.linalg.norm(a_tilde))
    theta = float(np.arctan(tan_theta))
    half = np.eye(3) if tan_theta == 0.0 else axis_angle_matrix(a_tilde / tan_theta, theta)
    t = t_tilde * np.cos(theta) * scale  # back to input units

    # M = R · T(t) · R in centred coordinates, then conjugate by the centring shift.
    rot = half @ half
    trans = half @ t + centre - rot @ centre
    return rigid_transform(rot, trans)


class SymmetricICP(Registrator):
    """Symmetric point-to-plane ICP (Rusinkiewicz 2019), linearised, from the identity."""

    name = "symmetric_icp"
    needs_training = False
    needs_normals = True  # estimated here from the points with Open3D
    config_cls = SymmetricICPConfig

    def setup(self) -> None:
        open3d()

    def normals(self, points: np.ndarray) -> np.ndarray:
        cfg: SymmetricICPConfig = self.config
        return estimate_normals(to_pcd(points), cfg.normal_radius, cfg.normal_max_nn, cfg.normal_orientation)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        cfg: SymmetricICPConfig = self.config
        src_normals = self.normals(src)
        ref_normals = self.normals(ref)
        tree = cKDTree(ref)

        transform = np.eye(4)
        for _ in range(int(cfg.max_iterations)):
            rot, trans = transform[:3, :3], transform[:3, 3]
            p = src @ rot.T + trans
            n_p = src_normals @ rot.T
            dist, idx = tree.query(p, k=1, distance_upper_bound=float(cfg.max_correspondence_distance))
            keep = np.isfinite(dist)
            if int(keep.sum()) < cfg.min_correspondences:
                break
            p, n_p = p[keep], n_p[keep]
            q, n_q = ref[idx[keep]], ref_normals[idx[keep]]
            # estimated normals have arbitrary signs: make each pair agree before summing
            sign = np.where(np.einsum("ij,ij->i", n_p, n_q) < 0.0, -1.0, 1.0)
            n = n_p * sign[:, None] + n_q
            good = np.einsum("ij,ij->i", n, n) > 1e-12
            if int(good.sum()) < cfg.min_correspondences:
                break
            step = symmetric_step(p[good], q[good], n[good])
            if step is None:
                break
            transform = step @ transform
            angle = float(np.arccos(np.clip((np.trace(step[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
            if angle < cfg.rotation_tolerance and float(np.linalg.norm(step[:3, 3])) < cfg.translation_tolerance:
                break
        # re-orthonormalise: many composed steps accumulate rounding error
        transform[:3, :3] = project_to_rotation(transform[:3, :3])
        return transform
