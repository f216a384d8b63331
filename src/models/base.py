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
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class RegistrationNetwork(Protocol):
    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict: ...

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]: ...
