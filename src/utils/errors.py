"""User-facing errors: one clear line naming the cause and the fix.

Every entry point turns a :class:`UserError` into ``error: <message>`` on stderr and exit status 2
instead of a traceback, through :func:`exit_code_of`: argparse commands (``src.data.prepare``,
benchmarks) return its status, Hydra apps (``src.train``, ``src.eval``, ``benchmarks.grid``) wrap
their task function in :func:`exit_on_user_error`.
"""

from __future__ import annotations

import functools
import signal
import sys
from collections.abc import Callable
from typing import Any


class UserError(Exception):
    """Base class for errors caused by input the user can fix (data, config, checkpoint)."""


class DatasetError(UserError):
    """Missing, partial or corrupt dataset or cache."""


class PointCloudError(UserError):
    """Empty, NaN or wrongly shaped point clouds."""


class RegistrationError(UserError):
    """A method's estimate for a pair is no rigid transform (NaN, a reflection): the pair is outside what it handles."""


class ConfigError(UserError):
    """Unknown experiment, model, method or config key."""


class CheckpointError(UserError):
    """Missing checkpoint or one written by another model."""


class DiskError(UserError):
    """A full disk, or a folder without write permission."""


class DivergenceError(UserError):
    """Training produced a non-finite loss (the run diverged): stopped before the step that would spread it."""


class Interrupted(Exception):
    """A run stopped by a signal (``SIGTERM`` from ``timeout``/SLURM/a sweep launcher, ``SIGINT``
    from Ctrl+C): it exits with status ``128 + signal`` (143, 130) after one ``error:`` line, and its
    job records it in ``failure.json`` (:mod:`src.run.signals`)."""

    def __init__(self, signum: int, step: int | None = None, checkpoint: str | None = None) -> None:
        self.signum, self.step, self.checkpoint = signum, step, checkpoint
        self.signal_name = signal.Signals(signum).name
        #: The command that resumes the run in its own folder (:func:`src.run.resume.resume_command`), once known.
        self.resume: str | None = None
        super().__init__(signum, step, checkpoint)

    def __str__(self) -> str:
        where = "" if self.step is None else f" at step {self.step}"
        if self.resume:
            return f"interrupted by {self.signal_name}{where}; resume it in its folder with: {self.resume}"
        resume = f"; resume with ckpt_path={self.checkpoint}" if self.checkpoint else ""
        return f"interrupted by {self.signal_name}{where}{resume}"

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def user_error_behind(err: BaseException) -> UserError | None:
    """``err`` if it is a UserError, else the first UserError it was raised from (Hydra wraps errors
    raised while instantiating, OmegaConf those raised by resolvers), else None."""
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, UserError):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


def exit_code_of(action: Callable[[], Any]) -> int:
    """Run a command-line action: 0 when it succeeds; a UserError (or an error raised from one)
    prints ``error: <message>`` on stderr and gives exit status 2; an :class:`Interrupted` run, or one
    stopped by Ctrl+C (``KeyboardInterrupt``, once the action's own clean-up has run), prints its line and
    gives ``128 + signal``."""
    try:
        action()
    except Interrupted as err:
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code
    except KeyboardInterrupt:
        err = Interrupted(signal.SIGINT)
        print(f"error: {err}", file=sys.stderr)
        return err.exit_code
    except Exception as err:
        user_error = user_error_behind(err)
        if user_error is None:
            raise
        print(f"error: {user_error}", file=sys.stderr)
        return 2
    return 0


def exit_on_user_error(task: Callable[..., Any]) -> Callable[..., None]:
    """A Hydra task function run through :func:`exit_code_of`: it exits with status 2 (after the
    ``error:`` line) for a UserError, ``128 + signal`` for an interrupted run."""

    @functools.wraps(task)
    def wrapper(*args: Any, **kwargs: Any) -> None:
        status = exit_code_of(lambda: task(*args, **kwargs))
        if status:
            sys.exit(status)

    return wrapper
