"""The optional PyPI packages of some classical baselines: one check, one error line naming the install."""

from __future__ import annotations

import importlib.util
from typing import Any, ClassVar

from src.utils.errors import ConfigError

#: The extra of ``pyproject.toml`` that installs the optional packages with wheels (FilterReg's probreg has its own).
EXTRA = "classical"


def install_hint(package: str, extra: str = EXTRA) -> str:
    """How to install ``package``: ``pip install <package> (or pip install -e ".[<extra>]")``."""
    return f'pip install {package} (or pip install -e ".[{extra}]")'


def require(module: str, package: str, method: str, extra: str = EXTRA) -> None:
    """ConfigError naming the install command unless ``module`` (of PyPI's ``package``, in the extra ``extra``)
    can be imported."""
    if importlib.util.find_spec(module) is None:
        raise ConfigError(f"method '{method}' needs the optional package {package}, which is not installed: "
                          f"{install_hint(package, extra)}")


class NeedsPackage:
    """Mixin of a Registrator whose backend is an optional package (of ``pyproject.toml``'s extra ``extra``):
    constructing it checks the package is there."""

    module: ClassVar[str]
    package: ClassVar[str]
    extra: ClassVar[str] = EXTRA

    def __init__(self, config: Any = None, **overrides: Any) -> None:
        super().__init__(config, **overrides)
        require(self.module, self.package, self.name, self.extra)
