"""The comparison grid: methods × experiments × sampling (OS/TS) × partial manner (PRNet/RPMNet).

    python -m benchmarks.grid                                    # classical methods on the synthetic default
    python -m benchmarks.grid +benchmark=real_airplane           # real airplanes (PRNet manner, OS and TS)
    python -m benchmarks.grid 'benchmark.methods=[icp,omnet]' method_options.omnet.checkpoint=PATH

This module is the command; :mod:`benchmarks.grid.plan` plans the cells, :mod:`benchmarks.grid.run` runs and
scores them, :mod:`benchmarks.grid.report` reports. Configuration, test sets, methods, outputs and bad
input: ``docs/methods/grid.md``.
"""

from __future__ import annotations

from omegaconf import DictConfig

from benchmarks.grid.plan import GRID_CONFIG
from benchmarks.grid.report import report
from benchmarks.grid.run import run_grid
from src.run.cli import hydra_command
from src.run.wandb_logging import log_grid
from src.utils.paths import CONF_DIR


def _run(cfg: DictConfig) -> None:
    from src.validation import validate_grid_config  # (torch: imported where used, see benchmarks.grid.plan)

    validate_grid_config(cfg)  # an unknown top-level key (nothing would read it), the grid's own values
    result = run_grid(cfg)
    report(result, cfg)
    log_grid(cfg, result.tidy)  # wandb.enabled=true: the tidy table as a wandb.Table (src/run/wandb_logging.py)


main = hydra_command(_run, CONF_DIR, GRID_CONFIG)  # one `error: ...` line and exit 2 for bad input
