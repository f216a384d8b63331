"""Batched unit quaternions (w, x, y, z) in torch."""

from __future__ import annotations

import torch
from torch import Tensor


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Scale quaternions (..., 4) to unit norm."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a ⊗ b of (..., 4) quaternions: rotating by b, then by a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """Inverse of unit quaternions (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_canonical(q: Tensor) -> Tensor:
    """Representative with w >= 0 (q and -q are the same rotation)."""
    return torch.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices (..., 3, 3) from quaternions (..., 4); normalises first."""
    w, x, y, z = quat_normalize(q).unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(rot: Tensor) -> Tensor:
    """Unit quaternions (..., 4) with w >= 0 from rotation matrices (..., 3, 3).

    Uses the numerically stable branch per element (largest of w, x, y, z).
    """
    m = rot
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = torch.stack(
        (
            1 + m00 + m11 + m22,
            1 + m00 - m11 - m22,
            1 - m00 + m11 - m22,
            1 - m00 - m11 + m22,
        ),
        dim=-1,
    )
    best = candidates.argmax(dim=-1, keepdim=True)
    s = 2 * candidates.gather(-1, best).clamp_min(1e-12).sqrt()  # 4 * |component|
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    s = s.squeeze(-1)
    options = torch.stack(
        (
            torch.stack((s / 4, d21 / s, d02 / s, d10 / s), -1),
            torch.stack((d21 / s, s / 4, s01 / s, s02 / s), -1),
            torch.stack((d02 / s, s01 / s, s / 4, s12 / s), -1),
            torch.stack((d10 / s, s02 / s, s12 / s, s / 4), -1),
        ),
        dim=-2,
    )
    q = options.gather(-2, best.unsqueeze(-1).expand(*best.shape[:-1], 1, 4)).squeeze(-2)
    return quat_canonical(quat_normalize(q))


def quat_rotate(q: Tensor, points: Tensor) -> Tensor:
    """Rotate points (..., N, 3) by quaternions (..., 4)."""
    return points @ quat_to_matrix(q).transpose(-1, -2)
