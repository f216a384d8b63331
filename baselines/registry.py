"""Methods by name: :func:`get_registrator` builds the method registered under a name (a method's key,
display name or alias), :func:`register_registrator` adds one. Every record of :data:`baselines.methods.METHODS`
is registered lazily (``"module:Class"``), so that ``import baselines`` imports no Open3D, torch or optional
extension.
"""

from __future__ import annotations

import importlib
from typing import Any

from baselines.base import Registrator, RegistratorConfig
from baselines.methods import METHODS, find_method
from src.utils.errors import ConfigError

#: name -> Registrator subclass, or "module:Class" imported on first use: every record of
#: :data:`baselines.methods.METHODS`, and what :func:`register_registrator` adds.
_REGISTRY: dict[str, type[Registrator] | str] = {method.key: method.registrator for method in METHODS}


def _normalise(name: str) -> str:
    return str(name).strip().lower().replace("-", "_").replace(" ", "_")


def register_registrator(name: str, target: type[Registrator] | str | None = None):
    """Add a method outside :data:`baselines.methods.METHODS` (a test's, a plug-in's) to the registry;
    usable as a class decorator.

    ``target`` is a Registrator subclass or a lazy ``"package.module:Class"`` path (imported
    by :func:`get_registrator` on first use), e.g.
    ``register_registrator("toy", "baselines.testing:ToyRegistrator")``.
    """
    key = _normalise(name)

    def _add(obj: type[Registrator] | str) -> type[Registrator] | str:
        _REGISTRY[key] = obj
        return obj

    if target is None:
        return _add
    return _add(target)


def available_registrators() -> list[str]:
    """Registered method names, sorted."""
    return sorted(_REGISTRY)


def resolve_registrator(name: str) -> type[Registrator]:
    """The Registrator class registered under ``name`` (ConfigError if unknown): a method's key,
    display name or alias (:func:`baselines.methods.find_method`), or a name given to
    :func:`register_registrator`."""
    method = find_method(name)
    key = method.key if method is not None else _normalise(name)
    if key not in _REGISTRY:
        raise ConfigError(
            f"unknown registration method '{name}'; available: {', '.join(available_registrators())}"
        )
    target = _REGISTRY[key]
    if isinstance(target, str):
        module_name, _, attr = target.partition(":")
        module = importlib.import_module(module_name)
        target = getattr(module, attr)
        _REGISTRY[key] = target
    return target


def get_registrator(name: str, config: RegistratorConfig | None = None, **cfg: Any) -> Registrator:
    """Build the method registered under ``name`` with its config overridden by ``cfg``.

    Unknown names and unknown config keys raise ConfigError naming the valid choices.
    """
    return resolve_registrator(name)(config, **cfg)
