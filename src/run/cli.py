"""The one command-line path of every Hydra entry point (``src.train``, ``src.eval``, ``benchmarks.grid``).

:func:`hydra_command` is Hydra's ``main`` around a task function run through
:func:`~src.utils.errors.exit_on_user_error`, plus Hydra's own errors in the command line rendered as the
project's one line and exit status 2 (instead of Hydra's multi-line report and status 1): an override
that does not parse (an unquoted list), a config of a group that does not exist (``data=modelnet41``)
with the group's choices, a key or group name that is not in the config (a typo) with the close matches.
"""

from __future__ import annotations

import difflib
import functools
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from hydra.errors import (
    ConfigCompositionException,
    MissingConfigException,
    OverrideParseException,
)
from omegaconf import DictConfig

from src.utils.errors import exit_on_user_error
from src.utils.files import disk_error

_MISSING = re.compile(r"Could not find '([^']+)/([^']+)'")
_NOT_OVERRIDABLE = re.compile(r"Could not override '([^']+)'")


def _groups(config_dir: Path) -> list[str]:
    return sorted(p.name for p in config_dir.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))


def _choices(config_dir: Path, group: str) -> list[str]:
    return sorted(p.stem for p in (config_dir / group).glob("*.yaml"))


def _keys_near(cfg: DictConfig | None, dotted: str) -> tuple[str, list[str]]:
    """The parent of ``dotted`` and the keys of that node in ``cfg`` (none when it has no such node)."""
    parent, _, _ = dotted.rpartition(".")
    node: Any = cfg
    for part in filter(None, parent.split(".")):
        node = node.get(part) if isinstance(node, DictConfig) else None
    return parent, sorted(node.keys()) if isinstance(node, DictConfig) else []


def describe_hydra_error(err: Exception, config_dir: Path, cfg: DictConfig | None = None) -> str:
    """One line for a Hydra composition error: what is wrong and the valid choices (``cfg``: the
    composed default config, whose keys a misspelt key is compared with)."""
    text = str(err).strip()
    first = text.splitlines()[0] if text else type(err).__name__
    if isinstance(err, OverrideParseException):
        return (f"an override does not parse ({first}); quote values with brackets, commas or spaces, "
                "e.g. 'data.splits.test.slice=[-100, null]'")
    missing = _MISSING.search(text)
    if isinstance(err, MissingConfigException) and missing:
        group, name = missing.groups()
        if (config_dir / group).is_dir():
            return f"{group}={name}: no such config in group {group}; choose one of: {', '.join(_choices(config_dir, group))}"
        return f"{group}={name}: {group} is not a config group; groups: {', '.join(_groups(config_dir))}"
    key = _NOT_OVERRIDABLE.search(first)
    if key:
        dotted = key[1].lstrip("+~")
        parent, keys = _keys_near(cfg, dotted)
        if not parent:
            keys = sorted(set(keys) | set(_groups(config_dir)))
        close = difflib.get_close_matches(dotted.rpartition(".")[2], keys, n=3)
        hint = f"did you mean {', '.join(f'{parent}.{k}' if parent else k for k in close)}? " if close else ""
        where = f"a key of {parent}" if parent else "a config key or group"
        return f"{dotted} is not {where}: {hint}add a new key with +{dotted}=VALUE"
    return first


def _default_config(config_dir: Path, config_name: str) -> DictConfig | None:
    """The config composed without overrides (for the keys a typo is compared with), None if it fails."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            return compose(config_name)
    except Exception:  # noqa: BLE001 - only for suggestions
        return None


def hydra_command(task: Callable[[DictConfig], Any], config_dir: Path, config_name: str) -> Callable[..., None]:
    """Hydra's ``main`` on ``config_dir/config_name`` around ``task`` (run through
    :func:`~src.utils.errors.exit_on_user_error`); composition errors are one ``error:`` line, exit 2."""
    entry = exit_on_user_error(task)
    main = hydra.main(version_base="1.3", config_path=str(config_dir), config_name=config_name)(entry)

    @functools.wraps(entry)
    def command(*args: Any, **kwargs: Any) -> None:
        os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises its errors instead of printing a report
        try:
            main(*args, **kwargs)
        except (ConfigCompositionException, OverrideParseException) as err:
            print(f"error: {describe_hydra_error(err, config_dir, _default_config(config_dir, config_name))}",
                  file=sys.stderr)
            sys.exit(2)
        except OSError as err:  # Hydra creating the run folder (a file there, a read-only mount), before any task
            problem = disk_error(err, "creating the run folder", Path(err.filename or "."))
            if problem is None:
                raise
            print(f"error: {problem}", file=sys.stderr)
            sys.exit(2)

    return command
