"""The comparison grid: methods × experiments × sampling (OS/TS) × partial manner (PRNet/RPMNet).

    python -m benchmarks.grid                                    # classical methods on the synthetic default
    python -m benchmarks.grid +benchmark=real_airplane           # real airplanes (PRNet manner, OS and TS)
    python -m benchmarks.grid 'benchmark.methods=[icp,omnet]' method_options.omnet.checkpoint=PATH

This module is the command; :mod:`benchmarks.grid_plan` plans the cells, :mod:`benchmarks.grid_run` runs and
scores them, :mod:`benchmarks.grid_report` reports. Configuration, test sets, methods, outputs and bad
input: ``docs/methods/grid.md``.
"""

from __future__ import annotations

from omegaconf import DictConfig

from baselines.methods import display_name  # re-exported for benchmarks.speed, until it imports baselines.methods
from benchmarks.grid_plan import GRID_CONFIG, Cell, plan
from benchmarks.grid_report import report
from benchmarks.grid_run import GridResult, run_grid
from src.cli import hydra_command
from src.paths import CONF_DIR
from src.wandb_logging import log_grid

__all__ = ["Cell", "GridResult", "display_name", "main", "plan", "report", "run_grid"]


def _run(cfg: DictConfig) -> None:
    from src.validation import validate_grid_config  # (torch: imported where used, see benchmarks.grid_plan)

    validate_grid_config(cfg)  # an unknown top-level key (nothing would read it), the grid's own values
    result = run_grid(cfg)
    report(result, cfg)
    log_grid(cfg, result.tidy)  # wandb.enabled=true: the tidy table as a wandb.Table (src/wandb_logging.py)


main = hydra_command(_run, CONF_DIR, GRID_CONFIG)  # one `error: ...` line and exit 2 for bad input


if __name__ == "__main__":
    main()

