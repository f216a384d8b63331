"""Per-element layers on channel-last features, shared by every learned baseline (one copy each).

Features are (..., C): points and per-point features (B, N, C), per-edge (neighbourhood) features
(B, N, k, C). 1×1 convolutions of the official codes are written as ``nn.Linear`` on the last dimension
(the same function, faster on a CPU).

* :func:`~src.models.base.scaled` — a layer's channel count under the width multiplier (``model_scale``).
* :class:`BatchNormLast`, :class:`GroupNormLast` — BatchNorm / GroupNorm of (..., C) features.
* :class:`MLP` — per-element Linear (+ BatchNorm / GroupNorm) + (Leaky)ReLU layers on (..., C): PointNet's
  shared MLP, DGCNN's edge MLPs (any number of leading dimensions), GroupNorm (RPMNet), LeakyReLU (PRNet)
  and a biased plain last layer (IDAM's score heads), which the networks need to keep their papers'
  layer definitions.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch.nn.functional as F
from torch import Tensor, nn

NORMS = ("batch", "group", "none")


class BatchNormLast(nn.BatchNorm1d):
    """BatchNorm over every leading dimension of (..., C) features (BatchNorm1d/2d of the official
    code on (B, C, N) / (B, C, N, k): statistics per channel over batch, points and neighbours)."""

    def forward(self, x: Tensor) -> Tensor:
        shape = x.shape
        return super().forward(x.reshape(-1, shape[-1])).reshape(shape)


class GroupNormLast(nn.GroupNorm):
    """GroupNorm of (B, ..., C) features: per sample, over each channel group and all positions."""

    def forward(self, x: Tensor) -> Tensor:
        shape = x.shape
        y = F.group_norm(x.reshape(shape[0], -1, shape[-1]).transpose(1, 2), self.num_groups, self.weight, self.bias, self.eps)
        return y.transpose(1, 2).reshape(shape)


class MLP(nn.Module):
    """Per-element Linear (+ norm) + activation layers on (..., C).

    ``norm`` is ``"batch"``, ``"group"`` (``groups`` channels groups, one int or one per layer) or
    ``"none"``; ``negative_slope`` > 0 gives LeakyReLU. With ``last_activation=False`` the last layer is
    a plain biased Linear (no norm, no activation). ``bias`` None: biases only on un-normalised layers.
    ``layers`` holds the modules in order (Linear, norm, activation per layer).
    """

    def __init__(
        self,
        channels: Sequence[int],
        norm: str = "batch",
        groups: int | Sequence[int] = 8,
        negative_slope: float = 0.0,
        last_activation: bool = True,
        bias: bool | None = None,
    ) -> None:
        super().__init__()
        if norm not in NORMS:
            raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
        pairs = list(zip(channels[:-1], channels[1:]))
        group_list = [groups] * len(pairs) if isinstance(groups, int) else list(groups)
        layers: list[nn.Module] = []
        for k, (c_in, c_out) in enumerate(pairs):
            plain = k == len(pairs) - 1 and not last_activation
            normed = norm != "none" and not plain
            layers.append(nn.Linear(c_in, c_out, bias=(not normed) if (bias is None or plain) else bias))
            if normed:
                layers.append(BatchNormLast(c_out) if norm == "batch" else GroupNormLast(group_list[k], c_out))
            if not plain:
                # in place: Linear / BatchNorm / GroupNorm backward do not need their outputs
                layers.append(nn.LeakyReLU(negative_slope, inplace=True) if negative_slope > 0 else nn.ReLU(inplace=True))
        self.layers = nn.Sequential(*layers)
        self.channels_first = norm == "group"

    def forward(self, x: Tensor) -> Tensor:
        if not self.channels_first:
            return self.layers(x)
        # GroupNorm stacks run as 1×1 convolutions on (B, C, L): PyTorch's CPU GroupNorm is several
        # times faster on contiguous channel-first tensors (same parameters, same function).
        shape = x.shape
        y = self.forward_channels_first(x.reshape(shape[0], -1, shape[-1]).transpose(1, 2))
        return y.transpose(1, 2).reshape(*shape[:-1], y.shape[1])

    def forward_channels_first(self, y: Tensor) -> Tensor:
        """The same layers on channel-first (B, C, L) features, as 1×1 convolutions."""
        for layer in self.layers:
            if isinstance(layer, nn.Linear):
                y = F.conv1d(y, layer.weight.unsqueeze(-1), layer.bias)
            elif isinstance(layer, nn.GroupNorm):
                y = F.group_norm(y, layer.num_groups, layer.weight, layer.bias, layer.eps)
            elif isinstance(layer, nn.BatchNorm1d):
                y = nn.BatchNorm1d.forward(layer, y)
            else:
                y = layer(y)
        return y
