"""What ``src.train`` and ``src.eval`` share: building objects from the config and writing results."""

from __future__ import annotations

import contextlib
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

import hydra
import lightning as L
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.rank_zero import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from src.checkpoint_io import AtomicCheckpointIO
from src.errors import ConfigError, user_error_behind
from src.files import remove_stale_temporaries, write_text_atomic
from src.validation import validate_config

log = logging.getLogger(__name__)

FAILURE_FILE = "failure.json"
ON_FAILURE_MODES = ("auto", "record", "raise")


def exit_on_user_error(main: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Turn a UserError (or an error raised from one) into one ``error: ...`` line on stderr and exit
    status 2."""

    @functools.wraps(main)
    def wrapper(cfg: DictConfig) -> Any:
        try:
            return main(cfg)
        except Exception as err:
            user_error = user_error_behind(err)
            if user_error is None:
                raise
            print(f"error: {user_error}", file=sys.stderr)
            sys.exit(2)

    return wrapper


TRAINING_ONLY_CALLBACKS = ("checkpoint", "periodic_checkpoint", "rng_state")


def build_trainer(cfg: DictConfig, with_checkpoints: bool = True) -> L.Trainer:
    """Trainer with the configured loggers and callbacks (checkpointing only when training).

    Checkpoints are written by :class:`~src.checkpoint_io.AtomicCheckpointIO` (a temporary beside
    the target, then a rename); temporaries left in the checkpoint folders by killed runs are
    removed here, before training starts.
    """
    loggers = [hydra.utils.instantiate(c) for c in (cfg.get("logger") or {}).values()]
    callbacks = [
        hydra.utils.instantiate(c)
        for name, c in (cfg.get("callbacks") or {}).items()
        if with_checkpoints or name not in TRAINING_ONLY_CALLBACKS
    ]
    for callback in callbacks:
        if isinstance(callback, ModelCheckpoint) and callback.dirpath:
            for path in remove_stale_temporaries(Path(callback.dirpath)):
                log.info("removed %s, a partial checkpoint left by a killed run", path)
    patch_ddp_subprocess_launcher()
    return hydra.utils.instantiate(cfg.trainer, logger=loggers, callbacks=callbacks, plugins=[AtomicCheckpointIO()])


def global_rank() -> int:
    """This process's global rank: Lightning's (set once a DDP strategy is set up; before that
    read from RANK/LOCAL_RANK/SLURM_PROCID), 0 without distribution."""
    return int(getattr(rank_zero_only, "rank", 0) or 0)


def save_resolved_config(cfg: DictConfig, output_dir: Path) -> None:
    output_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(output_dir / "config_resolved.yaml", OmegaConf.to_yaml(cfg, resolve=True))


def read_csv_logs(run_dir: Path) -> pd.DataFrame:
    """The CSV logger's rows of a run, every version (a resumed run writes a new one) in order."""
    versions = sorted((run_dir / "csv").glob("version_*/metrics.csv"), key=lambda f: int(f.parent.name.split("_")[1]))
    files = [f for f in [run_dir / "csv" / "metrics.csv"] if f.is_file()] + versions  # (logs without versions first)
    if not files:
        return pd.DataFrame()
    return pd.concat([pd.read_csv(f) for f in files], ignore_index=True)


def write_metrics(metrics: dict[str, float], output_dir: Path, context: dict[str, Any]) -> pd.DataFrame:
    """metrics.json (context + metrics) and metrics.csv (one tidy row per metric)."""
    output_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(output_dir / "metrics.json", json.dumps({**context, "metrics": metrics}, indent=2))
    frame = pd.DataFrame([{**context, "metric": k, "value": v} for k, v in metrics.items()])
    frame.to_csv(output_dir / "metrics.csv", index=False)
    return frame


# --- failures: one job of a sweep must not take the others down ------------------------------


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
    """``failure.json`` (``failure.rank<r>.json`` on other DDP ranks): what failed, where and why."""
    rank = global_rank()
    record: dict[str, Any] = {
        "status": "failed",
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
    if HydraConfig.initialized():
        hc = HydraConfig.get()
        record["overrides"] = list(hc.overrides.task)
        record["job"] = {"name": hc.job.name, "num": hc.job.get("num"), "id": hc.job.get("id")}
    output_dir.mkdir(parents=True, exist_ok=True)
    path = output_dir / _failure_name(rank)
    write_text_atomic(path, json.dumps(record, indent=2))
    return path


def record_failures(main: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """Run a job once its config passes :func:`~src.validation.validate_config`; on any exception
    (an invalid config included) write ``failure.json`` into its run dir, then (``on_failure``)
    re-raise it (``raise``) or log it and return None so the sweep goes on (``record``).

    Wrap it inside :func:`exit_on_user_error` so a re-raised UserError stays one line. A job that
    succeeds removes a stale ``failure.json`` left in its dir by an earlier attempt.
    """

    @functools.wraps(main)
    def wrapper(cfg: DictConfig) -> Any:
        global _ACTIVE_ON_FAILURE
        mode = resolve_on_failure(cfg.get("on_failure"))
        _ACTIVE_ON_FAILURE = mode
        output_dir = _job_output_dir(cfg)
        try:
            validate_config(cfg)
            with distributed_job_scope():
                result = main(cfg)
        except Exception as err:
            path = write_failure(output_dir, err)
            if mode == "raise":
                raise
            log.error("job failed, recorded in %s", path, exc_info=err)
            print(f"error: job failed ({failure_reason(err)}); recorded in {path}", file=sys.stderr)
            return None
        stale = output_dir / _failure_name(global_rank())
        if stale.is_file():
            stale.unlink()
        return result

    return wrapper


_ACTIVE_ON_FAILURE: str | None = None  # the current job's resolved mode, passed on to its DDP children
_DDP_ENV = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE", "OMP_NUM_THREADS")


@contextlib.contextmanager
def distributed_job_scope():
    """Let several DDP jobs run one after the other in one process (Hydra's basic launcher).

    Lightning's subprocess launcher leaves the process group initialised and writes MASTER_PORT,
    LOCAL_RANK, WORLD_SIZE, ... into ``os.environ``; the next job would then take LOCAL_RANK as a
    sign that its processes were started externally and wait for ranks that never come. After
    each job of a launching process, destroy the process group and restore those variables.
    """
    before = {k: os.environ.get(k) for k in _DDP_ENV}
    try:
        yield
    finally:
        if before["LOCAL_RANK"] is None:  # this process launched the ranks itself
            import torch.distributed as dist

            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
            for key, value in before.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


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


# --- DDP under a Hydra multirun ------------------------------------------------------------------

_CONFIG_FLAGS = ("--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd")


def _config_flags(argv: list[str]) -> list[str]:
    """The config-selection flags of a command line (``-cn NAME``, ``--config-dir=D``, ...)."""
    kept, i = [], 0
    while i < len(argv):
        arg = argv[i]
        if arg in _CONFIG_FLAGS and i + 1 < len(argv):
            kept += argv[i : i + 2]
            i += 2
            continue
        if arg.split("=", 1)[0] in _CONFIG_FLAGS and "=" in arg:
            kept.append(arg)
        i += 1
    return kept


def ddp_job_subprocess_cmd(local_rank: int, original: Callable[[int], tuple[Any, str]] | None = None):
    """Command that starts DDP rank ``local_rank`` of the current Hydra job.

    Lightning re-runs ``sys.argv`` plus ``hydra.run.dir=<run dir>``; inside a multirun that would
    start a whole new sweep (``-m``, every swept value) in every child. Here a child instead runs
    this job alone: the config flags of the command line, the job's own overrides (its swept values
    included) and ``hydra.run.dir=<the job's output dir>``.
    """
    from lightning.fabric.strategies.launchers import subprocess_script as fabric_launcher

    original = original or _ORIGINAL_SUBPROCESS_CMD or fabric_launcher._hydra_subprocess_cmd
    hc = HydraConfig.get()
    if hc.mode != RunMode.MULTIRUN:
        return original(local_rank)
    import multiprocessing

    import __main__

    if multiprocessing.parent_process() is not None:
        raise ConfigError(
            "DDP cannot start its processes from a launcher worker (hydra/launcher=joblib): run DDP sweeps with "
            "the basic launcher (jobs one after the other) or hydra/launcher=submitit_slurm"
        )

    from hydra.utils import get_original_cwd, to_absolute_path

    if getattr(__main__, "__spec__", None) is None:
        command = [sys.executable, to_absolute_path(sys.argv[0])]
    else:
        command = [sys.executable, "-m", __main__.__spec__.name]
    command += _config_flags(sys.argv[1:])
    command += list(hc.overrides.task)
    skip = ("hydra.run.dir", "hydra.output_subdir", "hydra.job.name", "hydra.mode")
    command += [o for o in hc.overrides.hydra if o.lstrip("+~").split("=", 1)[0] not in skip]
    command += [f'hydra.run.dir="{hc.runtime.output_dir}"', f"hydra.job.name=ddp_rank_{local_rank}", "hydra.output_subdir=null"]
    if _ACTIVE_ON_FAILURE:  # a failing rank records and exits 0: a non-zero exit makes Lightning kill the sweep
        command.append(f"on_failure={_ACTIVE_ON_FAILURE}")
    return command, get_original_cwd()


_ORIGINAL_SUBPROCESS_CMD: Callable[[int], tuple[Any, str]] | None = None


def patch_ddp_subprocess_launcher() -> None:
    """Make Lightning's DDP subprocess launcher use :func:`ddp_job_subprocess_cmd` (idempotent)."""
    global _ORIGINAL_SUBPROCESS_CMD
    from lightning.fabric.strategies.launchers import subprocess_script as fabric_launcher
    from lightning.pytorch.strategies.launchers import subprocess_script as pytorch_launcher

    if _ORIGINAL_SUBPROCESS_CMD is None:
        _ORIGINAL_SUBPROCESS_CMD = fabric_launcher._hydra_subprocess_cmd
    fabric_launcher._hydra_subprocess_cmd = ddp_job_subprocess_cmd
    pytorch_launcher._hydra_subprocess_cmd = ddp_job_subprocess_cmd


def report_test_metrics(
    trainer: L.Trainer, cfg: DictConfig, metrics: dict[str, float], checkpoint: str, **extra: Any
) -> None:
    """On rank 0 (under DDP every rank holds the same synchronised metrics): write metrics.json/.csv
    into the run dir (``extra`` joins the context, e.g. training time) and print the table."""
    if not trainer.is_global_zero:
        return
    context = {"task": cfg.task_name, "checkpoint": checkpoint, "sampling": cfg.sampling, "partial": cfg.partial,
               "dataset": cfg.data.dataset, **extra}
    write_metrics(metrics, Path(cfg.output_dir), context)
    print(f"\nTest metrics ({cfg.task_name}, {cfg.data.dataset}, {cfg.sampling}, {cfg.partial}):\n{format_metrics(metrics)}")


def format_metrics(metrics: dict[str, float]) -> str:
    """The paper's metrics as a two-column text table."""
    width = max(len(k) for k in metrics)
    return "\n".join(f"{k:<{width}}  {v:.4f}" for k, v in metrics.items())
