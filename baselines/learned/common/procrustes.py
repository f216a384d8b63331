"""Weighted Procrustes (Kabsch/SVD) solve for a rigid transform, batched and differentiable."""

from __future__ import annotations

import torch
from torch import Tensor

from src.geometry import se3_from_rt


def weighted_procrustes(src: Tensor, tgt: Tensor, weights: Tensor | None = None, eps: float = 1e-6) -> Tensor:
    """Rigid (B,4,4) T minimising Σ w_i ‖R src_i + t − tgt_i‖² for corresponding (B,N,3) points.

    ``weights`` (B,N) ≥ 0 (uniform if None). The reflection case is fixed with the sign of
    det(V Uᵀ), so the result is always a proper rotation.
    """
    if weights is None:
        weights = src.new_ones(src.shape[:2])
    w = weights.unsqueeze(-1) / (weights.sum(dim=1, keepdim=True).unsqueeze(-1) + eps)
    src_mean, tgt_mean = (w * src).sum(dim=1), (w * tgt).sum(dim=1)
    cov = (src - src_mean.unsqueeze(1)).transpose(1, 2) @ (w * (tgt - tgt_mean.unsqueeze(1)))
    rot = kabsch_rotation(cov).to(src.dtype)
    trans = tgt_mean - (rot @ src_mean.unsqueeze(-1)).squeeze(-1)
    return se3_from_rt(rot, trans)


def kabsch_rotation(cov: Tensor) -> Tensor:
    """The rotation (B,3,3), float64, best aligning centred source to target points given their
    cross-covariance ``cov`` (B,3,3) = Σ w·s·tᵀ: V·diag(1, 1, ±1)·Uᵀ from the SVD U·S·Vᵀ of cov, the sign
    that of det(V·Uᵀ), so that it is never a reflection."""
    u, _, vh = torch.linalg.svd(cov.double())
    v = vh.transpose(1, 2)
    sign = torch.sign(torch.linalg.det(v @ u.transpose(1, 2)))
    fix = torch.diag_embed(torch.stack((torch.ones_like(sign), torch.ones_like(sign), sign), dim=-1))
    return v @ fix @ u.transpose(1, 2)
