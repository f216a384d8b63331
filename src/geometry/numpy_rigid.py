"""Rigid transforms in NumPy, one (4, 4) float64 homogeneous matrix at a time; rotations from SciPy's
``Rotation``. The counterparts of the batched torch :mod:`src.geometry.se3` for the NumPy code (pair
transforms, scans, the classical baselines and their tests); imports no torch.

Convention as everywhere: ``T`` maps the source to the reference, ``ref ≈ R @ src + t``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation


def rigid_transform(rotation: ArrayLike, translation: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) float64 from ``R`` (3, 3) and ``t`` (3,)."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return out


def euler_transform(angles: ArrayLike, translation: ArrayLike = (0.0, 0.0, 0.0), seq: str = "xyz",
                    degrees: bool = True) -> np.ndarray:
    """(4, 4): the rotation of extrinsic Euler angles as SciPy's ``from_euler(seq)`` (``angles[k]`` about axis
    ``seq[k]``, applied in that order: ``"xyz"`` gives Rz·Ry·Rx, ``"zyx"`` Rx·Ry·Rz, as
    :func:`src.geometry.se3.euler_to_matrix`), then ``translation``."""
    return rigid_transform(Rotation.from_euler(seq, angles, degrees=degrees).as_matrix(), translation)


def twist_matrix(twist: ArrayLike) -> np.ndarray:
    """exp of a twist (ω1, ω2, ω3, v1, v2, v3) → (4, 4): R = exp([ω]×), t = V·v with
    V = I + (1 − cos θ)/θ²·[ω]× + (θ − sin θ)/θ³·[ω]×² (PointNetLK's ``se3.exp``)."""
    w, v = np.asarray(twist[:3], dtype=np.float64), np.asarray(twist[3:], dtype=np.float64)
    theta = float(np.linalg.norm(w))
    wx = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-8:
        left = np.eye(3) + wx / 2
    else:
        left = np.eye(3) + (1 - np.cos(theta)) / theta**2 * wx + (theta - np.sin(theta)) / theta**3 * (wx @ wx)
    return rigid_transform(Rotation.from_rotvec(w).as_matrix(), left @ v)


def apply_transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) moved by ``transform`` (4, 4): ``points @ Rᵀ + t``."""
    return points @ transform[:3, :3].T + transform[:3, 3]


def inverse_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4): (Rᵀ, −Rᵀt)."""
    rot_t = transform[:3, :3].T
    return rigid_transform(rot_t, -rot_t @ transform[:3, 3])


def project_to_rotation(matrix: ArrayLike) -> np.ndarray:
    """Nearest rotation matrix (Frobenius norm) to a 3x3 matrix, via SVD with det = +1."""
    u, _, vt = np.linalg.svd(np.asarray(matrix, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle(rotation: np.ndarray, degrees: bool = True) -> float:
    """Angle of a rotation (3, 3): arccos((trace − 1) / 2)."""
    angle = np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))
    return float(np.degrees(angle) if degrees else angle)
