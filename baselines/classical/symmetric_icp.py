r"""Symmetric ICP (Rusinkiewicz, "A Symmetric Objective Function for ICP", SIGGRAPH 2019).

Our own vectorised numpy implementation on Open3D normals and scipy KD-trees. The OMNet paper ran
PCL's ``IterativeClosestPointWithNormals`` with ``setUseSymmetricObjective(true)``; line numbers
below are of PCL commit 1fdb038 and of Rusinkiewicz's own ICP in trimesh2 (mirror
``Forceflow/trimesh2``, commit 76bc893).

**Objective and step** (as PCL). The motion ``M`` taking ``p`` (source) onto ``q`` (reference) is
split into two half-rotations ``R`` (angle θ about the unit axis ``a``) around a translation,
``M = R · T(t) · R``, and the residual is measured along the sum of both normals:

.. math::

   \varepsilon = \sum_i \big[(R p_i - R^{-1} q_i + t)\cdot(R n_{p,i} + R^{-1} n_{q,i})\big]^2 .

Linearising (paper, Sec. 3.2) with :math:`n_i = n_{p,i} + n_{q,i}`, :math:`\tilde a = a\tan\theta`
and :math:`\tilde t = t/\cos\theta` gives a linear least-squares problem in six unknowns,

.. math::

   \varepsilon \approx \sum_i \big[(p_i - q_i)\cdot n_i + ((p_i + q_i)\times n_i)\cdot\tilde a
                                   + n_i\cdot\tilde t\big]^2 ,

solved through its 6x6 normal equations: PCL's ``transformation_estimation_symmetric_point_to_plane_lls.hpp``
lines 168-197 build the same rows ``[(p+q)×n, n]`` and right-hand side ``(q-p)·n``. Each source
normal is first flipped to agree with its partner (PCL's ``enforce_same_direction_normals``, on by
default: same file lines 174-179, ``icp.h`` line 368), as estimated normals have arbitrary signs.
The step is recovered as :math:`\theta = \arctan\lVert\tilde a\rVert`, :math:`t = \tilde t\cos\theta`
(the paper's and trimesh2's ``libsrc/ICP.cc`` lines 244-252), in coordinates centred on the
correspondences and scaled to unit RMS radius (trimesh2 lines 438-453 centre each side on its own
centroid instead). PCL instead reads ã as small Euler angles and t̃ as the translation
(``constructTransformationMatrix``, lines 128-147) and does not centre: with PCL's step, or without
centring, the flip rate below stayed the same.

**Loop and correspondences** (the fix). PCL's loop (``icp.hpp`` lines 164-241) matches one way:
each source point to its nearest reference point (line 183), with no distance limit by default
(``registration.h`` line 117), for at most 10 iterations (same file, line 566). Started from the
identity, the protocols' motions (Euler angles up to 45° per axis about the origin, translations up
to 0.5 per axis) put the source far from the reference: one-way matching then sends the
whole source onto a small part of the reference (at the identity, 5-7% of the reference points of
the real-airplane PRNet-manner pairs receive a partner), and the linearised step turns the wrong
way (in 9 of the 17 OS pairs that end over 30°, a first step of 40-90° that increases the error)
or slides along weakly constrained directions.
That flipped 10% of those pairs by more than 90° and 17-20% by more than 30° (mean Error(R)
19.7° / 20.6°, OS / TS). Normal signs (``"centroid"`` / ``"none"``), PCL's step, the centring, 10
iterations, no distance limit, and trimesh2's Huber weights, regularisation, adaptive distance
rejection and normal-angle rejection each left that tail in place.

We therefore match **both ways**, as Rusinkiewicz's own implementation does (trimesh2
``select_and_match`` called for mesh1→mesh2 and mesh2→mesh1, ``libsrc/ICP.cc`` lines 380-383):
each moved source point with its nearest reference point and each reference point with its nearest
moved source point, all pairs together (a mutual pair counts twice), with PCL's default of no
distance limit. On the same pairs this brings the share over 30° to 2% / 1%. ``two_way=False``
restores PCL's one-way matching. Past the basin it does not help: on synthetic airplanes with every
Euler angle in [30°, 45°], 15% (two-way) and 19% (one-way) of the pairs still end over 30°.

Remaining deviations from PCL: two-way matching; the step's recovery and centring (above);
``max_iterations = 30`` (PCL 10; 10 gave 4.6° / 3.2° instead of 4.4° / 3.0° on those pairs); stopping
when a step rotates by less than ``rotation_tolerance`` (rad) and translates by less than
``translation_tolerance`` (PCL: ``DefaultConvergenceCriteria``); the normals (Open3D PCA, hybrid
radius 0.1 / at most 30 neighbours, signed away from each cloud's centroid, as for FGR; their sign
does not matter once each pair is made to agree). trimesh2's covariance-weighted sampling, adaptive
distance and normal-angle rejection and Huber weights are not used.

``max_correspondence_distance = inf`` (PCL's default). ``python -m baselines.classical.sweep
symmetric_icp --pairs 200 --set max_correspondence_distance=D`` (noisy TS RPMNet-manner airplane
pairs, 717 points), mean / median rotation error: two-way 0.3 → 21.76° / 6.57°, 0.5 → 16.24° /
7.76°, 1.0 → 15.62° / 7.57°, 2.0 and no limit → 16.06° / 7.58°; one-way (before the fix) 0.3 →
25.39° / 10.69°, 0.5 → 21.73° / 7.85°, 1.0 → 17.68° / 8.55° (paper, RPMNet manner, TS unseen
categories with noise: 21.8°). On the PRNet-manner airplane pairs (mean Error(R), OS / TS) a limit
of 1.0 gave 4.4° / 4.7°, no limit 4.4° / 3.0°. One-way (PCL's loop) is ``--set two_way=False``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from baselines.base import Registrator, RegistratorConfig, _positive
from baselines.classical._open3d import NORMAL_ORIENTATIONS, estimate_normals, open3d, to_pcd
from src.errors import ConfigError
from src.geometry.numpy_rigid import apply_transform, project_to_rotation, rigid_transform, rotation_angle


@dataclass
class SymmetricICPConfig(RegistratorConfig):
    """Settings of :class:`SymmetricICP` (see the module docstring for why these defaults)."""

    max_correspondence_distance: float = math.inf
    two_way: bool = True
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


def nearest_pairs(
    src_tree: cKDTree, ref_tree: cKDTree, transform: np.ndarray, max_distance: float, two_way: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays ``(source, reference)`` of nearest-neighbour pairs closer than ``max_distance``,
    the source moved by ``transform`` (4x4).

    Each moved source point with its nearest reference point (PCL's one-way matching) and, if
    ``two_way``, also each reference point with its nearest moved source point (trimesh2), found by
    moving the reference back into the source's frame (same distances, the source's tree).
    """
    rot, trans = transform[:3, :3], transform[:3, 3]
    dist, idx = ref_tree.query(apply_transform(transform, src_tree.data), distance_upper_bound=max_distance)
    found = np.isfinite(dist)
    src_idx, ref_idx = np.flatnonzero(found), idx[found]
    if two_way:
        dist, idx = src_tree.query((ref_tree.data - trans) @ rot, distance_upper_bound=max_distance)
        found = np.isfinite(dist)
        src_idx = np.concatenate([src_idx, idx[found]])
        ref_idx = np.concatenate([ref_idx, np.flatnonzero(found)])
    return src_idx, ref_idx


def normal_sums(n_p: np.ndarray, n_q: np.ndarray) -> np.ndarray:
    """``±n_p + n_q`` per row, ``n_p`` flipped where it points away from ``n_q`` (PCL's
    ``enforce_same_direction_normals``: a flipped pair would cancel in the sum)."""
    sign = np.where(np.einsum("ij,ij->i", n_p, n_q) < 0.0, -1.0, 1.0)
    return n_p * sign[:, None] + n_q


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
    half = np.eye(3) if tan_theta == 0.0 else Rotation.from_rotvec(a_tilde / tan_theta * theta).as_matrix()
    t = t_tilde * np.cos(theta) * scale  # back to input units

    # M = R · T(t) · R in centred coordinates, then conjugate by the centring shift.
    rot = half @ half
    trans = half @ t + centre - rot @ centre
    return rigid_transform(rot, trans)


class SymmetricICP(Registrator):
    """Symmetric point-to-plane ICP (Rusinkiewicz 2019), linearised, two-way matching, from the identity."""

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
        src_tree, ref_tree = cKDTree(src), cKDTree(ref)

        transform = np.eye(4)
        for _ in range(int(cfg.max_iterations)):
            src_idx, ref_idx = nearest_pairs(
                src_tree, ref_tree, transform, float(cfg.max_correspondence_distance), cfg.two_way
            )
            n = normal_sums(src_normals[src_idx] @ transform[:3, :3].T, ref_normals[ref_idx])
            good = np.einsum("ij,ij->i", n, n) > 1e-12
            if int(good.sum()) < cfg.min_correspondences:
                break
            src_idx, ref_idx = src_idx[good], ref_idx[good]
            step = symmetric_step(apply_transform(transform, src[src_idx]), ref[ref_idx], n[good])
            if step is None:
                break
            transform = step @ transform
            angle = rotation_angle(step[:3, :3], degrees=False)
            if angle < cfg.rotation_tolerance and float(np.linalg.norm(step[:3, 3])) < cfg.translation_tolerance:
                break
        # re-orthonormalise: many composed steps accumulate rounding error
        transform[:3, :3] = project_to_rotation(transform[:3, :3])
        return transform
