"""DDP jobs under Hydra: this process's rank, jobs run one after the other in one process, and the
command that starts a job's DDP ranks inside a multirun."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Callable, Iterator, Sequence

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from lightning.pytorch.utilities.rank_zero import rank_zero_only

from src.utils.errors import ConfigError

#: A launcher's ``(command, working directory)`` of DDP rank ``local_rank``.
SubprocessCommand = Callable[[int], tuple[Sequence[str], str]]

_DDP_ENV = ("MASTER_ADDR", "MASTER_PORT", "NODE_RANK", "LOCAL_RANK", "WORLD_SIZE", "OMP_NUM_THREADS")
_CONFIG_FLAGS = ("--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd")
_child_overrides: tuple[str, ...] = ()  # the running job's overrides for the DDP ranks it starts


def global_rank() -> int:
    """This process's global rank: Lightning's (set once a DDP strategy is set up; before that
    read from RANK/LOCAL_RANK/SLURM_PROCID), 0 without distribution."""
    return int(getattr(rank_zero_only, "rank", 0) or 0)


@contextlib.contextmanager
def distributed_job_scope(*child_overrides: str) -> Iterator[None]:
    """Run one job so that several DDP jobs can run one after the other in one process (Hydra's
    basic launcher); ``child_overrides`` join the command of the DDP ranks it starts in a multirun.

    Lightning's subprocess launcher leaves the process group initialised and writes MASTER_PORT,
    LOCAL_RANK, WORLD_SIZE, ... into ``os.environ``; the next job would then take LOCAL_RANK as a
    sign that its processes were started externally and wait for ranks that never come. After
    each job of a launching process, destroy the process group and restore those variables.
    """
    global _child_overrides
    before = {k: os.environ.get(k) for k in _DDP_ENV}
    _child_overrides = child_overrides
    try:
        yield
    finally:
        _child_overrides = ()
        if before["LOCAL_RANK"] is None:  # this process launched the ranks itself
            import torch.distributed as dist

            if dist.is_available() and dist.is_initialized():
                dist.destroy_process_group()
            for key, value in before.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


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


def ddp_job_command(local_rank: int, original: SubprocessCommand) -> tuple[Sequence[str], str]:
    """Command that starts DDP rank ``local_rank`` of the current Hydra job (``original``: Lightning's,
    used outside a multirun).

    Lightning re-runs ``sys.argv`` plus ``hydra.run.dir=<run dir>``; inside a multirun that would
    start a whole new sweep (``-m``, every swept value) in every child. Here a child instead runs
    this job alone: the config flags of the command line, the job's own overrides (its swept values
    included), the overrides of :func:`distributed_job_scope` and ``hydra.run.dir=<the job's output dir>``.
    """
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
    command += _child_overrides
    return command, get_original_cwd()
