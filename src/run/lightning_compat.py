"""The one patch of a private Lightning function, applied only to the function it was written for.

Lightning's DDP subprocess launcher builds its ranks' command in ``_hydra_subprocess_cmd`` (fabric's,
imported by pytorch's launcher); under a Hydra multirun that command restarts the whole sweep in
every rank, so :func:`patch_ddp_subprocess_launcher` replaces it with
:func:`src.run.distributed.ddp_job_command`. The replacement is installed only while the function's
source is the one it was checked against (:data:`SOURCE_SHA256`, for the Lightning versions that
pyproject.toml requires: :func:`supported_lightning`); otherwise it warns and leaves Lightning alone.
``tests/unit/src/test_lightning_compat.py`` fails when the installed Lightning is outside that range
or its function differs: review the replacement against the new source, then update both.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import warnings
from importlib import metadata
from types import ModuleType

import lightning
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet

from src.run.distributed import SubprocessCommand, ddp_job_command
from src.utils.paths import REPO_ROOT

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the installed package's metadata only
    tomllib = None

PATCHED = "lightning.fabric.strategies.launchers.subprocess_script._hydra_subprocess_cmd"
PYPROJECT = REPO_ROOT / "pyproject.toml"
DISTRIBUTION = "omnet-registration"
SOURCE_SHA256 = "57adc882a2aaa952160fa642a37b09741ebde3b37c2b7fabf2028a6138abe1bd"

_original: SubprocessCommand | None = None  # Lightning's function, once the patch is installed


def supported_lightning() -> SpecifierSet:
    """The Lightning versions this repository supports: the ``lightning`` requirement of
    pyproject.toml's ``[project] dependencies`` (the installed package's metadata without it)."""
    if tomllib is not None and PYPROJECT.is_file():
        with PYPROJECT.open("rb") as f:
            requirements = tomllib.load(f)["project"]["dependencies"]
    else:
        requirements = metadata.requires(DISTRIBUTION) or []
    for line in requirements:
        requirement = Requirement(line)
        if requirement.name == "lightning" and requirement.marker is None:
            return requirement.specifier
    raise LookupError(f"no lightning requirement in {PYPROJECT.name} (or {DISTRIBUTION}'s metadata)")


def _launchers() -> tuple[ModuleType, ModuleType]:
    from lightning.fabric.strategies.launchers import subprocess_script as fabric_launcher
    from lightning.pytorch.strategies.launchers import subprocess_script as pytorch_launcher

    return fabric_launcher, pytorch_launcher


def source_sha256(function: object) -> str | None:
    """sha256 of a function's source text; None when its source cannot be read."""
    try:
        return hashlib.sha256(inspect.getsource(function).encode()).hexdigest()
    except (OSError, TypeError):
        return None


def upstream_change() -> str | None:
    """Why the installed Lightning's function is not the one the patch was written for, or None."""
    fabric_launcher, pytorch_launcher = _launchers()
    function = _original or getattr(fabric_launcher, "_hydra_subprocess_cmd", None)
    if function is None:
        return f"Lightning {lightning.__version__} has no {PATCHED}"
    if _original is None and getattr(pytorch_launcher, "_hydra_subprocess_cmd", None) is not function:
        return f"Lightning {lightning.__version__}'s pytorch launcher no longer uses {PATCHED}"
    if source_sha256(function) != SOURCE_SHA256:
        return f"Lightning {lightning.__version__} changed {PATCHED} (the patch was written for lightning{supported_lightning()})"
    return None


def patch_ddp_subprocess_launcher() -> bool:
    """Make Lightning's DDP subprocess launchers use :func:`~src.run.distributed.ddp_job_command`
    (idempotent); returns whether the patch is in place."""
    global _original
    change = upstream_change()
    if change is not None:
        warnings.warn(f"{change}: DDP inside a multirun is left to Lightning, which restarts the sweep in each rank; "
                      "review src.run.distributed.ddp_job_command and src.run.lightning_compat", stacklevel=2)
        return False
    fabric_launcher, pytorch_launcher = _launchers()
    _original = _original or fabric_launcher._hydra_subprocess_cmd
    replacement = functools.partial(ddp_job_command, original=_original)
    fabric_launcher._hydra_subprocess_cmd = pytorch_launcher._hydra_subprocess_cmd = replacement
    return True
