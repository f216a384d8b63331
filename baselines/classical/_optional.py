"""The optional PyPI packages of some classical baselines: one check, one error line naming the install."""

from __future__ import annotations

import importlib.util
from typing import Any, ClassVar

from src.utils.errors import ConfigError

#: The extra of ``pyproject.toml`` that installs every optional package of the classical baselines.
EXTRA = 'pip install -e ".[classical]"'


def require(module: str, package: str, method: str) -> None:
    """ConfigError naming the install command unless ``module`` (of PyPI's ``package``) can be imported."""
    if importlib.util.find_spec(module) is None:
        raise ConfigError(f"method '{method}' needs the optional package {package}, which is not installed: "
                          f"pip install {package} (or {EXTRA})")


class NeedsPackage:
    """Mixin of a Registrator whose backend is an optional package: constructing it checks the package is there."""

    module: ClassVar[str]
    package: ClassVar[str]

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        require(self.module, self.package, self.name)
