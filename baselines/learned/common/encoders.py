"""PointNet-style per-point encoders on (B, N, C) features."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from baselines.learned.common.layers import MLP


class PointNetEncoder(nn.Module):
    """PointNet: shared MLP (Linear (+ BatchNorm) + ReLU per layer) then max-pool. ``forward`` returns
    (point features (B,N,C), global (B,C))."""

    def __init__(self, channels: Sequence[int] = (3, 64, 64, 64, 128, 1024), batch_norm: bool = True) -> None:
        super().__init__()
        self.mlp = MLP(channels, norm="batch" if batch_norm else "none")

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        features = self.mlp(points)
        return features, features.amax(dim=1)


def knn_indices(points: Tensor, k: int) -> Tensor:
    """Indices (B, N, k) of each point's k nearest neighbours (itself included) in (B, N, 3)."""
    return torch.cdist(points, points).topk(k, dim=-1, largest=False).indices
