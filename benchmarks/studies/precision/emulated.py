"""bf16-mixed numerics at float32 speed on a CPU without bf16 units.

Where a CPU has no bf16 matrix units, PyTorch's bf16 matrix products and convolutions run in slow
fallback kernels (about 1 GFLOP/s against tens of GFLOP/s in float32), which puts a training study out
of reach. :class:`Bf16ProductsInFp32` (a ``TorchDispatchMode``) computes every bf16 matrix product and
convolution (forward and backward) as the float32 product of the same bf16 operands, rounded to bf16:
bf16 values are exact in float32, and bf16 kernels accumulate in float32, so the result is what a bf16
unit returns up to the order of summation. Every other operation, and which operations autocast runs in
bf16, is untouched. ``tests/studies/test_precision_emulated.py`` checks it against the native kernels.
"""

from __future__ import annotations

from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map

aten = torch.ops.aten
#: Matrix products and convolutions: the operations whose bf16 kernels are the slow fallbacks.
PRODUCTS = {aten.mm.default, aten.bmm.default, aten.addmm.default, aten.baddbmm.default, aten.addbmm.default,
            aten.convolution.default, aten.convolution_backward.default}


def _is_bf16(value: Any) -> bool:
    return isinstance(value, torch.Tensor) and value.dtype == torch.bfloat16


class Bf16ProductsInFp32(TorchDispatchMode):
    """Inside this mode, a product with a bf16 operand is computed in float32 and its floating results rounded to bf16."""

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001 (the dispatcher's signature)
        kwargs = kwargs or {}
        if func not in PRODUCTS or not any(_is_bf16(v) for v in (*args, *kwargs.values())):
            return func(*args, **kwargs)
        up = lambda v: v.float() if _is_bf16(v) else v  # noqa: E731
        result = func(*tree_map(up, args), **tree_map(up, kwargs))
        return tree_map(lambda v: v.to(torch.bfloat16) if isinstance(v, torch.Tensor) and v.is_floating_point() else v,
                        result)
