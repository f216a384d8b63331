"""OmegaConf resolvers used by ``conf/`` (registered on import of the entry points)."""

from __future__ import annotations

import os
import warnings

from omegaconf import OmegaConf

from src.utils.errors import ConfigError
from src.utils.paths import shipped_checkpoint_path

EULER_SEQ_BY_PARTIAL = {"prnet": "zyx", "rpmnet": "xyz", "none": "zyx"}


def euler_seq_for(partial: str) -> str:
    """Metric Euler convention of a partial manner: PRNet's code uses zyx, RPMNet's xyz."""
    if partial not in EULER_SEQ_BY_PARTIAL:
        raise ConfigError(f"partial must be one of {sorted(EULER_SEQ_BY_PARTIAL)}, got {partial!r}")
    return EULER_SEQ_BY_PARTIAL[partial]


def add_ints(*values: int | str) -> int:
    """``${add:a,b}``: the sum of integers (e.g. a carve-out's start from two sizes)."""
    return sum(int(v) for v in values)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask, e.g. a container's share)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def loader_workers(most: int | str) -> int:
    """``${loader_workers:N}``: data-loader worker processes for this machine: one core is left to the
    training process, and at most ``N`` (2 cores: 1 worker; 16 cores: N)."""
    return max(0, min(int(most), usable_cores() - 1))


def register_resolvers() -> None:
    if not OmegaConf.has_resolver("euler_seq"):
        OmegaConf.register_new_resolver("euler_seq", euler_seq_for)
    if not OmegaConf.has_resolver("add"):
        OmegaConf.register_new_resolver("add", add_ints)
    if not OmegaConf.has_resolver("shipped"):
        OmegaConf.register_new_resolver("shipped", shipped_checkpoint_path)
    if not OmegaConf.has_resolver("loader_workers"):
        OmegaConf.register_new_resolver("loader_workers", loader_workers)
    if not OmegaConf.has_resolver("wandb_group"):
        OmegaConf.register_new_resolver("wandb_group", sweep_group)


# conf/hydra/launcher/{joblib,submitit_slurm}.yaml deliberately share their names with the launcher
# plugins' configs (so `hydra/launcher=joblib|submitit_slurm` picks ours); they are complete on
# their own, so Hydra's deprecated same-name schema matching is harmless: silence its warning.
warnings.filterwarnings("ignore", message=r"(?s).*is validated against ConfigStore schema with the same name")


def sweep_group() -> str | None:
    """``logger.wandb.group``: a Hydra multirun's sweep folder (its jobs group together), else None."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    return str(HydraConfig.get().sweep.dir)
