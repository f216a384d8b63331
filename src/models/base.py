"""The contract between a registration network and :class:`~src.models.module.RegistrationModule`.

Any network (OMNet, and later the learned baselines) plugs in by implementing two methods:

* ``forward(points_src (B,N,3), points_ref (B,M,3), transform_gt=None) -> dict`` whose
  ``"transforms"`` entry is the list of source→reference (B,4,4) estimates after each iteration
  (the last one is the prediction); ``transform_gt`` is given during training and validation for
  networks whose forward needs supervision signals (OMNet's mask labels).
* a network that uses normals has a true ``uses_normals``; its forward then also gets the keywords
  ``normals_src`` (B,N,3) and ``normals_ref`` (B,M,3) from the batch (``data.normals=cache``), or None.
* ``loss(outputs, transform_gt) -> dict[str, Tensor]`` with the total under ``"loss"`` and its
  terms under other keys (logged as ``train/<key>``).

:func:`check_network` refuses, in one line, a network built without them.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor

from src.utils.errors import ConfigError


@runtime_checkable
class RegistrationNetwork(Protocol):
    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict: ...

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]: ...


#: Fewest channels of a width-scaled layer of OMNet and the global-feature networks (PointNetLK, FMR,
#: DeepGMR, PointNet).
MIN_CHANNELS = 8


def scaled(channels: int, width: float, multiple: int = 1, minimum: int = 1) -> int:
    """``channels × width`` rounded to a multiple of ``multiple``, at least ``multiple`` and ``minimum``
    (channel-width scaling, ``model_scale``; ``width`` = 1 keeps the paper's network)."""
    return max(minimum, multiple, int(round(channels * width / multiple)) * multiple)


def check_network(network: object, target: str) -> RegistrationNetwork:
    """``network`` (built from ``model.network._target_`` = ``target``) if it has both methods,
    else a ConfigError naming the missing ones."""
    if isinstance(network, RegistrationNetwork):
        return network
    missing = [name for name in ("forward", "loss") if not callable(getattr(network, name, None))]
    raise ConfigError(f"model.network: {target} is not a registration network: it has no {' or '.join(missing)} "
                      "method (the two methods every network needs: src/models/base.py)")
