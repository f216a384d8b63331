"""Symmetric ICP (Rusinkiewicz, "A Symmetric Objective Function for ICP", SIGGRAPH 2019).

Our own vectorised numpy implementation on Open3D normals and scipy KD-trees of what the OMNet paper ran
(PCL's ``IterativeClosestPointWithNormals`` with ``setUseSymmetricObjective(true)``): the motion is split
into two half-rotations around a translation, and the residual is measured along the sum of both normals.

The objective and its step, the options, the sources followed and the measurements behind the defaults:
``docs/methods/symmetric_icp.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from baselines.base import Registrator, RegistratorConfig, _positive
from baselines.classical._open3d import NORMAL_ORIENTATIONS, estimate_normals, open3d, require_normals, to_pcd
from src.utils.errors import ConfigError, RegistrationError
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
    planar_blind = "the residuals along its normals, all parallel, do not see a motion within the plane"

    def setup(self) -> None:
        open3d()

    def normals(self, points: np.ndarray) -> np.ndarray:
        cfg: SymmetricICPConfig = self.config
        return estimate_normals(to_pcd(points), cfg.normal_radius, cfg.normal_max_nn, cfg.normal_orientation)

    def _refuse_undetermined(self, src: np.ndarray, ref: np.ndarray) -> None:
        """A planar cloud, or one with fewer than six normals."""
        super()._refuse_undetermined(src, ref)
        cfg: SymmetricICPConfig = self.config
        require_normals(self.name, cfg.normal_radius, cfg.normal_max_nn, src=src, ref=ref)

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """The composed steps; RegistrationError when not even the first step could be taken."""
        cfg: SymmetricICPConfig = self.config
        src_normals = self.normals(src)
        ref_normals = self.normals(ref)
        src_tree, ref_tree = cKDTree(src), cKDTree(ref)

        transform = np.eye(4)
        for iteration in range(int(cfg.max_iterations)):
            src_idx, ref_idx = nearest_pairs(
                src_tree, ref_tree, transform, float(cfg.max_correspondence_distance), cfg.two_way
            )
            n = normal_sums(src_normals[src_idx] @ transform[:3, :3].T, ref_normals[ref_idx])
            good = np.einsum("ij,ij->i", n, n) > 1e-12
            step = None
            if int(good.sum()) >= cfg.min_correspondences:
                src_idx, ref_idx = src_idx[good], ref_idx[good]
                step = symmetric_step(apply_transform(transform, src[src_idx]), ref[ref_idx], n[good])
            if step is None:
                if iteration == 0:
                    raise RegistrationError(
                        f"{self.name}: found no transform: its first step had {int(good.sum())} correspondences with "
                        f"normals (min_correspondences={cfg.min_correspondences}) and no solvable system; try another "
                        "method")
                break
            transform = step @ transform
            angle = rotation_angle(step[:3, :3], degrees=False)
            if angle < cfg.rotation_tolerance and float(np.linalg.norm(step[:3, 3])) < cfg.translation_tolerance:
                break
        # re-orthonormalise: many composed steps accumulate rounding error
        transform[:3, :3] = project_to_rotation(transform[:3, :3])
        return transform
