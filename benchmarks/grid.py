"""The comparison grid: methods × experiments × sampling (OS/TS) × partial manner (PRNet/RPMNet).

    python -m benchmarks.grid                                    # classical methods on the synthetic default
    python -m benchmarks.grid +benchmark=real_airplane           # real airplanes (PRNet manner, OS and TS)
    python -m benchmarks.grid data=modelnet40                    # the paper's experiments on ModelNet40
    python -m benchmarks.grid 'benchmark.methods=[icp,omnet]' method_options.omnet.checkpoint=PATH
    python -m benchmarks.grid benchmark.max_pairs=20 workers=2 timeout_s=30

Configuration: ``conf/benchmark/default.yaml`` (the default grid and every option) with, from the method
registry (:mod:`baselines.methods`), the default ``benchmark.methods`` and one ``method_options.<key>``
per method; ``+benchmark=<name>`` merges ``conf/benchmark/<name>.yaml`` into ``benchmark`` (a grid file
may also switch the data).

Modules: :mod:`benchmarks.grid_plan` (configuration, test sets, methods, cells and their hashes),
:mod:`benchmarks.grid_run` (registering, scoring, writing cells; the tidy table) and
:mod:`benchmarks.grid_report` (console summary, LaTeX/Markdown table); this module is the command.

Test sets. Each (experiment, sampling, partial) composes ``conf/config.yaml`` with ``+exp=<experiment>
sampling=<s> partial=<p> data=<the grid's data>`` plus ``benchmark.overrides`` (and any ``data.*``
override of this command line), instantiates the experiment's datamodule and takes its fixed test set
— exactly the pairs ``python -m src.eval +exp=<experiment>`` evaluates. Nothing about the data is
re-implemented here.

Methods. Classical methods run in parallel over pairs with :func:`baselines.run_pairs` (worker
processes, per-pair timeout); learned methods through :mod:`baselines.learned.adapter` (batches, GPU
when available) with the checkpoint named in ``method_options.<name>.checkpoint``. A pair that fails
(error, timeout, crash, non-rigid estimate) counts with the identity transform and is flagged; no
pair is ever dropped.

Outputs (``output_dir``, default ``outputs/grid/<benchmark.name>/``):

* ``cells/<method>__<experiment>__<sampling>__<partial>__<hash>.parquet``: one row per pair —
  cell keys, ``pair`` (index in the test set), ``transform`` / ``transform_gt`` (16 floats, row-major),
  ``seconds``, ``failed``, ``reason`` (the fields of :class:`baselines.RegistrationResult`) and per-pair errors (``Error(R)``, ``Error(t)``, ``MAE(R)``,
  ``MAE(t)``, ``chamfer``); next to it ``<same>.json``: the cell's definition, metrics and timing,
  written last (a cell counts as finished when both exist and read back; a damaged file is reported
  in a ``warning:`` line and its cell recomputed). ``hash`` covers everything that defines
  the cell (method and its options, checkpoint contents, test-set definition and data content hash,
  number of pairs, timeout), so re-running reuses finished cells and recomputes changed ones.
* ``results.parquet`` / ``results.csv``: the tidy table of this run's cells — ``method, method_id,
  experiment, sampling, partial, dataset, noise_sigma, metric, value, n_pairs, n_failed, seconds``
  (total registration time of the cell) and ``seconds_per_pair``; the numbers are
  :class:`src.metrics.RegistrationMetrics` over the cell's pairs (the metrics of ``src.eval``).
* ``pairs.parquet``: the per-pair rows of this run's cells together.
* ``table.md`` / ``table.tex``: the paper's Table-1 layout via :mod:`benchmarks.tables`.

Bad input (an unknown top-level key, unknown method or experiment, an invalid data or model value, missing checkpoint, a test
set that was never prepared, a degenerate pair) stops with one ``error: ...`` line and exit status 2.
"""

from __future__ import annotations

from omegaconf import DictConfig

from baselines.methods import display_name  # re-exported for benchmarks.speed, until it imports baselines.methods
from benchmarks.grid_plan import CONF_DIR, Cell, TestSet, build_test_set, plan
from benchmarks.grid_report import report
from benchmarks.grid_run import GridResult, run_grid
from src.cli import hydra_command
from src.wandb_logging import log_grid

__all__ = ["Cell", "GridResult", "TestSet", "build_test_set", "display_name", "main", "plan", "report", "run_grid"]


def _run(cfg: DictConfig) -> None:
    from src.validation import check_top_level_keys  # (torch: imported where used, see benchmarks.grid_plan)

    check_top_level_keys(cfg, "benchmark_grid")  # a typo'd or unknown top-level key: nothing would read it
    result = run_grid(cfg)
    report(result, cfg)
    log_grid(cfg, result.tidy)  # wandb.enabled=true: the tidy table as a wandb.Table (src/wandb_logging.py)


main = hydra_command(_run, CONF_DIR, "benchmark_grid")  # one `error: ...` line and exit 2 for bad input


if __name__ == "__main__":
    main()

