"""Converters of published state dicts onto this framework's networks, one per source layout.

A converter maps strictly: every source tensor is used (BatchNorm statistics included), none is missing,
and the result must fill the network's state dict exactly (``load_state_dict(strict=True)``). Conv1d/Conv2d
kernels become Linear weights; a convolution bias followed by BatchNorm is folded into the running mean
(μ' = μ − b, the same function: BatchNorm subtracts the mean). The files themselves are recorded in
:mod:`baselines.learned.published`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import torch
from torch import Tensor

from src.utils.errors import CheckpointError

BATCHNORM_TENSORS = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def read_state_dict(path: str | Path) -> dict[str, Tensor]:
    """A plain state dict (name → tensor) from a ``.t7``/``.pth`` file (CheckpointError otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"weights file {path} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any unreadable file is the same user error
        raise CheckpointError(f"{path} is not a readable PyTorch weights file ({type(err).__name__})") from None
    if not isinstance(state, Mapping) or not state or not all(isinstance(v, Tensor) for v in state.values()):
        raise CheckpointError(f"{path} does not hold a state dict (a mapping of names to tensors)")
    return dict(state)


class _Source:
    """The tensors of a source state dict, taken one by one; what is left over is an error."""

    def __init__(self, state: Mapping[str, Tensor], layout: str) -> None:
        self.state, self.layout = dict(state), layout

    def take(self, key: str) -> Tensor:
        if key not in self.state:
            raise CheckpointError(f"not a complete {self.layout} state dict: {key} is missing")
        return self.state.pop(key)

    def conv_bn(self, conv: str, bn: str, bias: bool) -> dict[str, Tensor]:
        """A 1×1 convolution (+ bias) and its BatchNorm as our Linear (no bias) + BatchNorm tensors."""
        weight = self.take(f"{conv}.weight")
        stats = {k: self.take(f"{bn}.{k}") for k in BATCHNORM_TENSORS}
        if bias:
            stats["running_mean"] = stats["running_mean"] - self.take(f"{conv}.bias")
        return {"linear": weight.reshape(weight.shape[0], -1), **stats}

    def done(self) -> None:
        if self.state:
            extra = sorted(self.state)
            raise CheckpointError(
                f"not a {self.layout} state dict: {len(extra)} tensor(s) it does not use, e.g. {', '.join(extra[:3])}"
            )


def _linear_bn(prefix: str, block: Mapping[str, Tensor], linear: int, norm: int) -> dict[str, Tensor]:
    out = {f"{prefix}.{linear}.weight": block["linear"]}
    out.update({f"{prefix}.{norm}.{k}": v for k, v in block.items() if k != "linear"})
    return out


def _pointnet(blocks: Sequence[Mapping[str, Tensor]], prefix: str) -> dict[str, Tensor]:
    """Blocks (conv, BN) as a :class:`~baselines.learned.common.encoders.PointNetEncoder` state dict."""
    out: dict[str, Tensor] = {}
    for i, block in enumerate(blocks):
        out.update(_linear_bn(f"{prefix}mlp.layers", block, 3 * i, 3 * i + 1))
    return out


def convert_dcp(source: _Source) -> dict[str, Tensor]:
    """DCP's ``DCP`` (``model.py``): ``emb_nn.conv1..5`` (no bias) + ``bn1..5`` and the SVD head's constant
    ``head.reflect`` = diag(1, 1, −1) → :class:`~baselines.learned.dcp.DCP` with ``pointer=False``."""
    blocks = [source.conv_bn(f"emb_nn.conv{i}", f"emb_nn.bn{i}", bias=False) for i in range(1, 6)]
    reflect = source.take("head.reflect")
    if not torch.equal(reflect, torch.diag(torch.tensor([1.0, 1.0, -1.0]))):
        raise CheckpointError("not DCP's SVD head: head.reflect is not diag(1, 1, -1)")
    out: dict[str, Tensor] = {}
    for i, block in enumerate(blocks[:4]):
        out.update(_linear_bn(f"embedding.layers.{i}.layers", block, 0, 1))
    out.update(_linear_bn("embedding.fuse.layers", blocks[4], 0, 1))
    return out


def convert_learning3d_pointnet(source: _Source, prefix: str = "") -> dict[str, Tensor]:
    """learning3d's ``PointNet(use_bn=True)``: ``conv1..5`` with biases + ``bn1..5`` → a PointNetEncoder
    (3-64-64-64-128-1024)."""
    return _pointnet([source.conv_bn(f"{prefix}conv{i}", f"{prefix}bn{i}", bias=True) for i in range(1, 6)], "")


def convert_learning3d_pointnetlk(source: _Source) -> dict[str, Tensor]:
    """learning3d's ``PointNetLK``: its ``feature_model`` PointNet and the twist step ``dt`` →
    :class:`~baselines.learned.pointnetlk.PointNetLK` (``encoder`` and ``delta``)."""
    encoder = convert_learning3d_pointnet(source, "feature_model.")
    return {**{f"encoder.{k}": v for k, v in encoder.items()}, "delta": source.take("dt")}


def convert_pointnetlk_revisited(source: _Source) -> dict[str, Tensor]:
    """PointNetLK-Revisited's ``AnalyticalPointNetLK``: ``ptnet.mlp1..3`` = (Conv1d with bias, BatchNorm)
    → :class:`~baselines.learned.pointnetlk_revisited.PointNetLKRevisited`."""
    blocks = [source.conv_bn(f"ptnet.mlp{i}.0", f"ptnet.mlp{i}.1", bias=True) for i in (1, 2, 3)]
    return _pointnet(blocks, "encoder.")


#: layout → (converter, a tensor only that layout has)
LAYOUTS: dict[str, tuple[Callable[[_Source], dict[str, Tensor]], str]] = {
    "dcp": (convert_dcp, "emb_nn.conv1.weight"),
    "learning3d_pointnetlk": (convert_learning3d_pointnetlk, "feature_model.conv1.weight"),
    "learning3d_pointnet": (convert_learning3d_pointnet, "conv1.weight"),
    "pointnetlk_revisited": (convert_pointnetlk_revisited, "ptnet.mlp1.0.weight"),
}


def detect_layout(state: Mapping[str, Tensor], path: str | Path) -> str:
    found = [name for name, (_, key) in LAYOUTS.items() if key in state]
    if len(found) != 1:
        raise CheckpointError(
            f"{path} is not a published state dict of a known layout ({', '.join(LAYOUTS)}); "
            f"its first tensors: {', '.join(list(state)[:3])}"
        )
    return found[0]


def convert(state: Mapping[str, Tensor], layout: str) -> dict[str, Tensor]:
    """Our network's state dict from a published one of ``layout`` (strict, see the module docstring)."""
    source = _Source(state, layout)
    out = LAYOUTS[layout][0](source)
    source.done()
    return out
