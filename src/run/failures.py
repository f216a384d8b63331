"""Jobs that fail without taking a sweep down: ``failure.json`` in the job's run dir, the sweep's
summary (:class:`FailureSummary`), and :func:`job_main`, the command-line entry of a job."""

from __future__ import annotations

import datetime
import functools
import json
import logging
import os
import socket
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig

from src.run.cli import hydra_command
from src.run.distributed import distributed_job_scope, global_rank
from src.run.resume import resume_command
from src.utils.errors import ConfigError, DiskError, Interrupted, UserError, user_error_behind
from src.utils.files import disk_errors, write_text_atomic
from src.utils.interrupts import interruptible
from src.utils.paths import REPO_ROOT
from src.validation import validate_config

log = logging.getLogger(__name__)

FAILURE_FILE = "failure.json"
ON_FAILURE_MODES = ("auto", "record", "raise")


def resolve_on_failure(mode: str | None) -> str:
    """``record`` or ``raise``; ``auto`` (default) records inside a multirun and raises otherwise."""
    mode = mode or "auto"
    if mode not in ON_FAILURE_MODES:
        raise ConfigError(f"on_failure must be one of {ON_FAILURE_MODES}, got {mode!r}")
    if mode != "auto":
        return mode
    multirun = HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    return "record" if multirun else "raise"


def _job_output_dir(cfg: DictConfig) -> Path:
    try:
        return Path(cfg.output_dir)
    except Exception:  # noqa: BLE001 - output_dir missing or not resolvable: fall back to Hydra's
        if HydraConfig.initialized():
            return Path(HydraConfig.get().runtime.output_dir)
        return Path.cwd()


def _failure_name(rank: int) -> str:
    return FAILURE_FILE if rank == 0 else f"failure.rank{rank}.json"


def failure_reason(err: BaseException) -> str:
    """One line naming the root cause: the innermost chained exception (Hydra wraps errors raised
    while instantiating in InstantiationException), e.g. ``ValueError: num_iters must be >= 1``."""
    root, seen = err, {id(err)}
    while (root.__cause__ or root.__context__) is not None and id(root.__cause__ or root.__context__) not in seen:
        root = root.__cause__ or root.__context__
        seen.add(id(root))
    lines = str(root).strip().splitlines()
    return f"{type(root).__name__}: {lines[0]}" if lines else type(root).__name__


def write_failure(output_dir: Path, err: BaseException) -> Path:
    """``failure.json`` (``failure.rank<r>.json`` on other DDP ranks): what failed, where and why; an
    interrupted run (status ``interrupted``) also records its signal, step and the checkpoint to resume from."""
    rank = global_rank()
    interrupted = isinstance(err, Interrupted)
    record: dict[str, Any] = {
        "status": "interrupted" if interrupted else "failed",
        "reason": failure_reason(err),
        "error_type": type(err).__name__,
        "message": str(err).strip(),
        "user_error": user_error_behind(err) is not None,
        "traceback": "".join(traceback.format_exception(type(err), err, err.__traceback__)),
        "time": datetime.datetime.now().isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "rank": rank,
    }
    if interrupted:
        record.update(reason=str(err), signal=err.signal_name, step=err.step, resume_from=err.checkpoint,
                      resume_command=err.resume)
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        record["overrides"] = list(hc.overrides.task)
        record["job"] = {"name": hc.job.name, "num": hc.job.get("num"), "id": hc.job.get("id")}
    with disk_errors("writing failure.json", output_dir):
        output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / _failure_name(rank)
    write_text_atomic(path, json.dumps(record, indent=2))
    return path


def record_failures(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Run a job once its config passes :func:`~src.validation.validate_config`; on any exception
    (an invalid config included) write ``failure.json`` into its run dir, then (``on_failure``)
    re-raise it (``raise``) or log it and return None so the sweep goes on (``record``). The DDP
    ranks the job starts get the same resolved ``on_failure``: a failing rank records and exits 0,
    as a non-zero exit makes Lightning kill the sweep.

    Wrap it inside :func:`~src.utils.errors.exit_on_user_error` so a re-raised UserError stays one line. A
    job that succeeds removes a stale ``failure.json`` left in its dir by an earlier attempt. A job
    stopped by SIGTERM/SIGINT (:mod:`src.run.signals`) is recorded and always re-raised: the sweep stops too.
    """

    @functools.wraps(task)
    def wrapper(cfg: DictConfig) -> Any:
        mode = resolve_on_failure(cfg.get("on_failure"))
        output_dir = _job_output_dir(cfg)
        try:
            with interruptible():
                validate_config(cfg)
                with distributed_job_scope(f"on_failure={mode}"):
                    result = task(cfg)
        except Exception as err:
            if isinstance(err, Interrupted) and err.checkpoint:
                err.resume = resume_command(err.checkpoint)
            try:
                path: Path | str = write_failure(output_dir, err)
            except UserError as problem:  # e.g. the disk that stopped the job is full: report the job's error
                if not isinstance(err, DiskError):  # (a job stopped by its folder's disk says so in its own line)
                    log.error("failure.json not written: %s", problem)
                path = f"nowhere ({problem})"
            if mode == "raise" or isinstance(err, Interrupted):
                raise
            log.error("job failed, recorded in %s", path, exc_info=err)
            print(f"error: job failed ({failure_reason(err)}); recorded in {path}", file=sys.stderr)
            return None
        stale = output_dir / _failure_name(global_rank())
        if stale.is_file():
            stale.unlink()
        return result

    return wrapper


def job_main(task: Callable[[DictConfig], Any]) -> Callable[[], None]:
    """The command-line entry of a job on ``conf/config.yaml`` (:func:`~src.run.cli.hydra_command`): Hydra's
    main around ``task``, whose failures are recorded (:func:`record_failures`) and whose UserError, like
    an override Hydra cannot apply, is one ``error:`` line and exit status 2."""
    return hydra_command(record_failures(task), REPO_ROOT / "conf", "config")


def _find_job_dirs(sweep_dir: Path) -> list[Path]:
    return sorted({p.parent.parent for p in sweep_dir.glob("**/.hydra/overrides.yaml")})


class FailureSummary(Callback):
    """Hydra callback (``hydra.callbacks.failure_summary``): after a multirun, list the jobs that
    recorded a ``failure.json`` and exit with ``exit_code`` (default 3) if any did, so a partially
    failed sweep is not silent; the finished jobs' results stay on disk either way."""

    def __init__(self, exit_code: int = 3) -> None:
        self.exit_code = exit_code

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        jobs = _find_job_dirs(sweep_dir)
        failed = [d for d in jobs if (d / FAILURE_FILE).is_file()]
        if not failed:
            return
        print(f"error: {len(failed)} of {len(jobs)} jobs failed (the others' results are kept):", file=sys.stderr)
        for job in failed:
            try:
                reason = json.loads((job / FAILURE_FILE).read_text()).get("reason", "?")
            except (OSError, ValueError):
                reason = "unreadable failure.json"
            print(f"  {job}: {reason}", file=sys.stderr)
        print(f"  collect with: python -m benchmarks.collect {sweep_dir}", file=sys.stderr)
        if self.exit_code:
            sys.stdout.flush()
            sys.stderr.flush()
            sys.exit(self.exit_code)
