"""User-facing errors: one clear line naming the cause and the fix.

Entry points (``src.train``, ``src.eval``, ``src.data.prepare``, benchmarks) catch
:class:`UserError` and print ``error: <message>`` instead of a traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any


class UserError(Exception):
    """Base class for errors caused by input the user can fix (data, config, checkpoint)."""


class DatasetError(UserError):
    """Missing, partial or corrupt dataset or cache."""


class PointCloudError(UserError):
    """Empty, NaN or wrongly shaped point clouds."""


class ConfigError(UserError):
    """Unknown experiment, model, method or config key."""


class CheckpointError(UserError):
    """Missing checkpoint or one written by another model."""


def exit_code_of(action: Callable[[], Any]) -> int:
    """Run a command-line action: 0 when it succeeds; a UserError prints ``error: <message>`` on
    stderr and gives exit status 2."""
    try:
        action()
    except UserError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0
