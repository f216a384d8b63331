"""The optional PyPI packages of some classical baselines: one check, one error line naming the install."""

from __future__ import annotations

import importlib.util

from src.errors import ConfigError

#: The extra of ``pyproject.toml`` that installs every optional package of the classical baselines.
EXTRA = 'pip install -e ".[classical]"'


def require(module: str, package: str, method: str) -> None:
    """ConfigError naming the install command unless ``module`` (of PyPI's ``package``) can be imported."""
    if importlib.util.find_spec(module) is None:
        raise ConfigError(f"method '{method}' needs the optional package {package}, which is not installed: "
                          f"pip install {package} (or {EXTRA})")
