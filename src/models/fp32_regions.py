"""Parts of a network kept in float32 under bf16 autocast (``model.fp32_modules``).

:func:`keep_fp32` makes every call of the named submodules run with autocast disabled on its inputs'
device and its lower-precision floating inputs cast to float32, so that a precision-sensitive part (a
pose head, a loss) computes as in a float32 run while the rest of the network takes bf16's speed. Names
are ``fnmatch`` patterns over ``network.named_modules()`` (``iterations.*.regressor``). Only calls
through ``module(...)`` are covered (forward hooks), not other methods called directly. The hooks live
in the module (they are copied and pickled with it); without autocast they change nothing.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

LOWER_PRECISIONS = (torch.bfloat16, torch.float16)


def _to_fp32(value: Any) -> Any:
    if isinstance(value, Tensor) and value.dtype in LOWER_PRECISIONS:
        return value.float()
    if isinstance(value, (list, tuple)):
        return type(value)(_to_fp32(v) for v in value)
    return value


def _device_type(args: tuple) -> str:
    for value in args:
        if isinstance(value, Tensor):
            return value.device.type
        if isinstance(value, (list, tuple)) and value:
            found = _device_type(tuple(value))
            if found:
                return found
    return ""


class _Fp32Region:
    """The pre- and post-forward hooks of one module: autocast off for the call, inputs in float32."""

    def __init__(self) -> None:
        self.contexts: list[torch.autocast | None] = []

    def before(self, module: nn.Module, args: tuple, kwargs: dict) -> tuple[tuple, dict]:
        device = _device_type(args) or _device_type(tuple(kwargs.values()))
        context = torch.autocast(device, enabled=False) if device and torch.amp.is_autocast_available(device) else None
        if context is not None:
            context.__enter__()
        self.contexts.append(context)
        return _to_fp32(args), {k: _to_fp32(v) for k, v in kwargs.items()}

    def after(self, module: nn.Module, args: tuple, kwargs: dict, output: Any) -> None:
        context = self.contexts.pop()
        if context is not None:
            context.__exit__(None, None, None)

    def __getstate__(self) -> dict:
        return {"contexts": []}  # no call is in progress in a copy


def fp32_module_names(network: nn.Module, patterns: Sequence[str]) -> list[str]:
    """The qualified names of ``network``'s submodules matched by ``patterns``; ValueError for a pattern
    that matches none (a misspelt name would silently keep nothing in float32)."""
    names = [name for name, _ in network.named_modules() if name]
    matched: list[str] = []
    for pattern in patterns:
        hits = [name for name in names if fnmatch.fnmatchcase(name, pattern)]
        if not hits:
            tops = sorted({name.split(".")[0] for name in names})
            raise ValueError(f"fp32_modules: {pattern!r} matches no submodule of {type(network).__name__} "
                             f"(its top-level modules: {', '.join(tops)})")
        matched += [name for name in hits if name not in matched]
    # a module inside a matched one is covered by it already
    return [name for name in matched if not any(name.startswith(f"{outer}.") for outer in matched)]


def keep_fp32(network: nn.Module, patterns: Sequence[str]) -> list[str]:
    """Keep the submodules matched by ``patterns`` in float32 under autocast; returns their names."""
    names = fp32_module_names(network, patterns)
    modules = dict(network.named_modules())
    for name in names:
        region = _Fp32Region()
        modules[name].register_forward_pre_hook(region.before, with_kwargs=True)
        modules[name].register_forward_hook(region.after, with_kwargs=True, always_call=True)
    return names
