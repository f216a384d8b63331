"""Config values as plain Python data."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from omegaconf import OmegaConf


def plain(value: Any) -> Any:
    """``value`` with every OmegaConf node (at any depth, interpolations resolved) turned into dicts and lists:
    what a checkpoint, a JSON record or a comparison needs (a checkpoint holding OmegaConf objects cannot be
    read back with ``torch.load(weights_only=True)``)."""
    if OmegaConf.is_config(value):
        return OmegaConf.to_container(value, resolve=True)
    if isinstance(value, Mapping):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    return value
