"""PointNet-style per-point encoders on (B, N, C) features."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn


class SharedMLP(nn.Module):
    """Per-point Linear (+ optional BatchNorm) + ReLU layers on (B, N, C): PointNet's shared MLP
    (Conv1d k=1), written as matrix products. The last layer's activation is optional."""

    def __init__(self, channels: Sequence[int], batch_norm: bool = True, last_activation: bool = True) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        pairs = list(zip(channels[:-1], channels[1:]))
        for k, (c_in, c_out) in enumerate(pairs):
            last = k == len(pairs) - 1
            layers.append(nn.Linear(c_in, c_out, bias=not batch_norm))
            if batch_norm and (not last or last_activation):
                layers.append(_PointBatchNorm(c_out))
            if not last or last_activation:
                layers.append(nn.ReLU(inplace=True))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x)


class _PointBatchNorm(nn.BatchNorm1d):
    """BatchNorm over batch and points of (B, N, C) features (as BatchNorm1d on (B, C, N))."""

    def forward(self, x: Tensor) -> Tensor:
        b, n, c = x.shape
        return super().forward(x.reshape(b * n, c)).reshape(b, n, c)


class PointNetEncoder(nn.Module):
    """PointNet: shared MLP then max-pool. ``forward`` returns (point features (B,N,C), global (B,C))."""

    def __init__(self, channels: Sequence[int] = (3, 64, 64, 64, 128, 1024), batch_norm: bool = True) -> None:
        super().__init__()
        self.mlp = SharedMLP(channels, batch_norm=batch_norm)

    def forward(self, points: Tensor) -> tuple[Tensor, Tensor]:
        features = self.mlp(points)
        return features, features.amax(dim=1)


def knn_indices(points: Tensor, k: int) -> Tensor:
    """Indices (B, N, k) of each point's k nearest neighbours (itself included) in (B, N, 3)."""
    return torch.cdist(points, points).topk(k, dim=-1, largest=False).indices
