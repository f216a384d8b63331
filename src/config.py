"""OmegaConf resolvers used by ``conf/`` (registered on import of the entry points)."""

from __future__ import annotations

import warnings

from omegaconf import OmegaConf

from src.errors import ConfigError

EULER_SEQ_BY_PARTIAL = {"prnet": "zyx", "rpmnet": "xyz", "none": "zyx"}


def euler_seq_for(partial: str) -> str:
    """Metric Euler convention of a partial manner: PRNet's code uses zyx, RPMNet's xyz."""
    if partial not in EULER_SEQ_BY_PARTIAL:
        raise ConfigError(f"partial must be one of {sorted(EULER_SEQ_BY_PARTIAL)}, got {partial!r}")
    return EULER_SEQ_BY_PARTIAL[partial]


def add_ints(*values: int | str) -> int:
    """``${add:a,b}``: the sum of integers (e.g. a carve-out's start from two sizes)."""
    return sum(int(v) for v in values)


def register_resolvers() -> None:
    if not OmegaConf.has_resolver("euler_seq"):
        OmegaConf.register_new_resolver("euler_seq", euler_seq_for)
    if not OmegaConf.has_resolver("add"):
        OmegaConf.register_new_resolver("add", add_ints)
    if not OmegaConf.has_resolver("wandb_group"):
        from src.wandb_logging import run_group

        OmegaConf.register_new_resolver("wandb_group", run_group)


# conf/hydra/launcher/{joblib,submitit_slurm}.yaml deliberately share their names with the launcher
# plugins' configs (so `hydra/launcher=joblib|submitit_slurm` picks ours); they are complete on
# their own, so Hydra's deprecated same-name schema matching is harmless: silence its warning.
warnings.filterwarnings("ignore", message=r"(?s).*is validated against ConfigStore schema with the same name")
