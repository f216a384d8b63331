"""Batched rigid transforms as homogeneous (..., 4, 4) matrices, and Euler angles, in torch.

Convention everywhere in the framework: ``transform_gt`` maps the source to the reference,
``ref ≈ R @ src + t``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from src.geometry.quaternion import quat_to_matrix

EULER_SEQUENCES = ("xyz", "zyx")


def se3_from_rt(rot: Tensor, trans: Tensor) -> Tensor:
    """Homogeneous (..., 4, 4) from rotations (..., 3, 3) and translations (..., 3)."""
    top = torch.cat((rot, trans.unsqueeze(-1)), dim=-1)
    bottom = torch.zeros(*rot.shape[:-2], 1, 4, dtype=rot.dtype, device=rot.device)
    bottom[..., 0, 3] = 1
    return torch.cat((top, bottom), dim=-2)


def se3_from_quat(quat: Tensor, trans: Tensor) -> Tensor:
    """Homogeneous (..., 4, 4) from quaternions (..., 4) and translations (..., 3)."""
    return se3_from_rt(quat_to_matrix(quat), trans)


def se3_identity(*batch: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """Identity transforms of shape (*batch, 4, 4)."""
    return torch.eye(4, dtype=dtype, device=device).expand(*batch, 4, 4).clone()


def se3_inverse(transform: Tensor) -> Tensor:
    """Inverse of rigid transforms (..., 4, 4)."""
    rot_t = transform[..., :3, :3].transpose(-1, -2)
    trans = -(rot_t @ transform[..., :3, 3:]).squeeze(-1)
    return se3_from_rt(rot_t, trans)


def se3_compose(a: Tensor, b: Tensor) -> Tensor:
    """a ∘ b: apply b first, then a."""
    return a @ b


def se3_apply(transform: Tensor, points: Tensor) -> Tensor:
    """Transform points (..., N, 3) by (..., 4, 4)."""
    return points @ transform[..., :3, :3].transpose(-1, -2) + transform[..., None, :3, 3]


def _axis_rotation(axis: str, angle: Tensor) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    one, zero = torch.ones_like(angle), torch.zeros_like(angle)
    rows = {
        "x": (one, zero, zero, zero, c, -s, zero, s, c),
        "y": (c, zero, s, zero, one, zero, -s, zero, c),
        "z": (c, -s, zero, s, c, zero, zero, zero, one),
    }[axis]
    return torch.stack(rows, dim=-1).reshape(*angle.shape, 3, 3)


def _check_seq(seq: str) -> None:
    if seq not in EULER_SEQUENCES:
        raise ValueError(f"Euler sequence must be one of {EULER_SEQUENCES}, got {seq!r}")


def euler_to_matrix(angles: Tensor, seq: str, degrees: bool = False) -> Tensor:
    """Rotation matrices from extrinsic Euler angles (..., 3), as SciPy's ``from_euler(seq)``.

    ``angles[..., k]`` is the angle about axis ``seq[k]``; extrinsic rotations apply in order,
    so ``"xyz"`` gives ``Rz @ Ry @ Rx`` and ``"zyx"`` gives ``Rx @ Ry @ Rz``.
    """
    _check_seq(seq)
    if degrees:
        angles = angles * (math.pi / 180)
    rot = _axis_rotation(seq[0], angles[..., 0])
    for k in (1, 2):
        rot = _axis_rotation(seq[k], angles[..., k]) @ rot
    return rot


def matrix_to_euler(rot: Tensor, seq: str, degrees: bool = False) -> Tensor:
    """Extrinsic Euler angles (..., 3) of rotation matrices, as SciPy's ``as_euler(seq)``."""
    _check_seq(seq)
    if seq == "xyz":  # R = Rz(c) Ry(b) Rx(a)
        a = torch.atan2(rot[..., 2, 1], rot[..., 2, 2])
        b = torch.asin((-rot[..., 2, 0]).clamp(-1, 1))
        c = torch.atan2(rot[..., 1, 0], rot[..., 0, 0])
    else:  # "zyx": R = Rx(c) Ry(b) Rz(a)
        a = torch.atan2(-rot[..., 0, 1], rot[..., 0, 0])
        b = torch.asin(rot[..., 0, 2].clamp(-1, 1))
        c = torch.atan2(-rot[..., 1, 2], rot[..., 2, 2])
    angles = torch.stack((a, b, c), dim=-1)
    return angles * (180 / math.pi) if degrees else angles


def rotation_angle(rot: Tensor, degrees: bool = True) -> Tensor:
    """Angle of rotations (..., 3, 3): arccos((trace − 1) / 2)."""
    trace = rot[..., 0, 0] + rot[..., 1, 1] + rot[..., 2, 2]
    angle = torch.acos(((trace - 1) / 2).clamp(-1, 1))
    return angle * (180 / math.pi) if degrees else angle
