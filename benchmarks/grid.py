"""The comparison grid: methods × experiments × sampling (OS/TS) × partial manner (PRNet/RPMNet).

    python -m benchmarks.grid                                    # classical methods on the synthetic default
    python -m benchmarks.grid +benchmark=real_airplane           # real airplanes (PRNet manner, OS and TS)
    python -m benchmarks.grid data=modelnet40                    # the paper's experiments on ModelNet40
    python -m benchmarks.grid 'benchmark.methods=[icp,omnet]' method_options.omnet.checkpoint=PATH
    python -m benchmarks.grid benchmark.max_pairs=20 workers=2 timeout_s=30

Configuration: ``conf/benchmark/default.yaml`` (the default grid and every option); ``+benchmark=<name>``
merges ``conf/benchmark/<name>.yaml`` into ``benchmark`` (a grid file may also switch the data).

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
  ``seconds``, ``failed``, ``reason`` and per-pair errors (``Error(R)``, ``Error(t)``, ``MAE(R)``,
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

Bad input (unknown method or experiment, an invalid data or model value, missing checkpoint, a test
set that was never prepared, a degenerate pair) stops with one ``error: ...`` line and exit status 2.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf

from baselines import PairResult, check_cloud, resolve_registrator, run_pairs
from baselines.base import Registrator
from src.config import euler_seq_for, register_resolvers
from src.errors import CheckpointError, ConfigError, PointCloudError
from src.files import write_atomic

# torch, pandas, torchmetrics and lightning are imported where they are used: the worker processes
# of run_pairs (spawned) re-import this module, and a light module keeps their start-up short.

register_resolvers()

GRID_FORMAT = 1
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
SAMPLINGS = ("os", "ts")
PARTIALS = ("prnet", "rpmnet", "none")
CLASSICAL_NAMES = {"icp": "ICP", "fgr": "FGR", "goicp": "Go-ICP", "symmetric_icp": "Symmetric ICP",
                   "identity": "Identity (no registration)"}
TIDY_COLUMNS = ("method", "method_id", "experiment", "sampling", "partial", "dataset", "noise_sigma", "metric",
                "value", "n_pairs", "n_failed", "seconds", "seconds_per_pair", "cell")
PAIR_ERROR_COLUMNS = ("Error(R)", "Error(t)", "MAE(R)", "MAE(t)", "chamfer")
_LOADER_KEYS = ("batch_size", "eval_batch_size", "num_workers", "pin_memory", "persistent_workers", "cache_root", "_target_")

# The app's primary config only pulls in conf/benchmark/default.yaml, so that `+benchmark=<name>`
# (conf/benchmark/<name>.yaml, package `benchmark`) can be appended on the command line.
ConfigStore.instance().store(name="benchmark_grid", node={"defaults": ["_self_", "benchmark/default"]})



def display_name(method: str) -> str:
    from baselines.base import LEARNED_DISPLAY_NAMES

    return CLASSICAL_NAMES.get(method) or LEARNED_DISPLAY_NAMES.get(method) or method


# --- composing the experiments --------------------------------------------------------------------


def compose_experiment(overrides: Sequence[str]) -> DictConfig:
    """``conf/config.yaml`` composed with ``overrides`` (inside a Hydra app: its own search path),
    checked by :func:`src.validation.validate_config`."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    from src.validation import validate_config

    try:
        if GlobalHydra.instance().is_initialized():
            cfg = compose("config", overrides=list(overrides))
        else:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                cfg = compose("config", overrides=list(overrides))
    except HydraException as err:
        experiment = next((o.split("=", 1)[1] for o in overrides if o.startswith("+exp=")), None)
        available = sorted(p.stem for p in (CONF_DIR / "exp").glob("*.yaml"))
        if experiment and "exp/" in str(err) and experiment not in available:
            raise ConfigError(f"unknown experiment '{experiment}'; available: {', '.join(available)}") from None
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot compose the test set with overrides {list(overrides)}: {first}") from None
    validate_config(cfg)
    return cfg


def _command_line_data_overrides() -> list[str]:
    """``data.*`` overrides given to this Hydra app (applied to every experiment too)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    out = []
    for override in HydraConfig.get().overrides.task:
        key = override.lstrip("+~").split("=", 1)[0]
        if key.startswith("data."):
            out.append(override)
    return out


def _data_choice(cfg: DictConfig) -> str | None:
    """The data config the grid was composed with (``data=<name>``), or None to keep each experiment's."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        choice = HydraConfig.get().runtime.choices.get("data")
        if choice:
            return str(choice)
    data = cfg.get("data")
    return str(data.dataset) if data is not None and data.get("dataset") else None


@dataclass
class TestSet:
    """One (experiment, sampling, partial): its composed config, datamodule and definition."""

    experiment: str
    sampling: str
    partial: str
    cfg: DictConfig
    dataset: Any  # src.data.dataset.PairDataset
    definition: dict[str, Any]
    _pairs: list | None = None

    @property
    def key(self) -> str:
        return f"{self.experiment}/{self.sampling}/{self.partial}"

    @property
    def dataset_name(self) -> str:
        return str(self.definition["dataset"])

    @property
    def noise_sigma(self) -> float:
        return float(self.definition["pair"].get("noise_sigma") or 0.0)

    def pairs(self, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The first ``n`` pairs ``(src, ref, transform_gt)``; each cloud is checked (≥ 3 points, finite)."""
        if self._pairs is None:
            self._pairs = []
        for index in range(len(self._pairs), n):
            sample = self.dataset[index]
            src, ref = sample["points_src"].numpy(), sample["points_ref"].numpy()
            try:
                check_cloud(src, "points_src")
                check_cloud(ref, "points_ref")
            except PointCloudError as err:
                raise PointCloudError(f"test set {self.key}, pair {index}: {err}") from None
            self._pairs.append((src, ref, sample["transform_gt"].numpy().astype(np.float64)))
        return self._pairs[:n]


def build_test_set(experiment: str, sampling: str, partial: str, data: str | None, extra: Sequence[str]) -> TestSet:
    overrides = [f"+exp={experiment}", f"sampling={sampling}", f"partial={partial}"]
    if data:
        overrides.append(f"data={data}")
    overrides += list(extra)
    cfg = compose_experiment(overrides)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("test")  # DatasetError if the test set was never prepared
    if "test" not in datamodule.datasets:
        raise ConfigError(f"experiment {experiment} has no test split (data.splits.test)")
    data_cfg = OmegaConf.to_container(cfg.data, resolve=True)
    definition = {k: v for k, v in data_cfg.items() if k not in _LOADER_KEYS}
    if "splits" in data_cfg:  # a cache datamodule: of its splits only the test split defines the test set
        definition["splits"] = {"test": data_cfg["splits"]["test"]}
    definition["content_hash"] = datamodule.cache.manifest.get("content_hash")
    definition["num_test_pairs"] = len(datamodule.datasets["test"])
    return TestSet(experiment, sampling, partial, cfg, datamodule.datasets["test"], definition)


# --- methods -----------------------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value


def method_options(cfg: DictConfig, method: str) -> dict[str, Any]:
    options = cfg.get("method_options") or {}
    return dict(_plain(options.get(method)) or {})


def checkpoint_for(checkpoint: Any, cell_key: str) -> str | None:
    """The checkpoint of a cell: one path, or the first ``{pattern: path}`` whose pattern matches."""
    if checkpoint is None or isinstance(checkpoint, (str, os.PathLike)):
        return None if checkpoint in (None, "") else str(checkpoint)
    if isinstance(checkpoint, Mapping):
        for pattern, path in checkpoint.items():
            if fnmatch.fnmatchcase(cell_key, str(pattern)):
                return str(path)
        return None
    raise ConfigError(f"checkpoint must be a path or a mapping {{experiment/sampling/partial: path}}, got {checkpoint!r}")


class MethodFactory:
    """Builds (and caches) one registrator per method and checkpoint; validates everything upfront."""

    def __init__(self, cfg: DictConfig) -> None:
        self.cfg = cfg
        self._cache: dict[tuple[str, str | None], Registrator] = {}
        self._digests: dict[str, str] = {}

    def is_learned(self, method: str) -> bool:
        return bool(getattr(resolve_registrator(method), "needs_training", False))

    def validate(self, method: str) -> None:
        """Build the method once per checkpoint it names (ConfigError / CheckpointError early)."""
        options = method_options(self.cfg, method)
        raw = options.get("checkpoint")
        if not self.is_learned(method) or options.get("fresh_weights") or options.get("weights") or not isinstance(raw, Mapping):
            self.build(method, "*")
            return
        if not raw:
            raise CheckpointError(f"method_options.{method}.checkpoint is an empty mapping")
        for path in raw.values():
            self._get(method, options, str(path))

    def build(self, method: str, cell_key: str) -> Registrator | None:
        """The registrator for ``method`` in cell ``cell_key`` (None: a learned method without a
        checkpoint for this cell)."""
        options = method_options(self.cfg, method)
        checkpoint = None
        if self.is_learned(method) and not options.get("fresh_weights") and not options.get("weights"):
            raw = options.get("checkpoint")
            if raw is None or raw == "":
                raise CheckpointError(
                    f"method '{method}' needs a checkpoint: set method_options.{method}.checkpoint=PATH "
                    f"(a .ckpt written by `python -m src.train model={method}`) or .weights=official:<name>"
                )
            checkpoint = checkpoint_for(raw, cell_key)
            if checkpoint is None:
                return None
        return self._get(method, options, checkpoint)

    def _get(self, method: str, options: dict[str, Any], checkpoint: str | None) -> Registrator:
        key = (method, checkpoint)
        if key not in self._cache:
            if checkpoint is not None:
                options = {**options, "checkpoint": checkpoint}
            self._cache[key] = resolve_registrator(method)(None, **options)
        return self._cache[key]

    def identity(self, registrator: Registrator) -> dict[str, Any]:
        """What defines the method's results: its name and options (+ the checkpoint's or weights' sha256)."""
        config = registrator.config.to_dict()
        for key in ("device", "batch_size"):  # same results, different speed
            config.pop(key, None)
        if config.get("weights"):
            from baselines.learned.published import weights_sha256

            config["weights_sha256"] = weights_sha256(config["weights"])
        checkpoint = config.get("checkpoint")
        if checkpoint:
            if checkpoint not in self._digests:
                from baselines.learned.adapter import checkpoint_digest

                self._digests[checkpoint] = checkpoint_digest(checkpoint)
            config["checkpoint_sha256"] = self._digests[checkpoint]
        return {"name": registrator.name, "config": config}


# --- one cell ---------------------------------------------------------------------------------------


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


@dataclass
class Cell:
    method: str
    test_set: TestSet
    registrator: Registrator
    n_pairs: int
    definition: dict[str, Any]
    digest: str
    folder: Path

    @property
    def stem(self) -> str:
        t = self.test_set
        return f"{self.method}__{t.experiment}__{t.sampling}__{t.partial}__{self.digest[:12]}"

    @property
    def pairs_path(self) -> Path:
        return self.folder / f"{self.stem}.parquet"

    @property
    def summary_path(self) -> Path:
        return self.folder / f"{self.stem}.json"

    @property
    def key(self) -> str:
        return f"{self.method}/{self.test_set.key}"

    def load(self) -> dict[str, Any] | None:
        """The finished cell's summary, or None if it must be computed: never run, interrupted (no
        JSON yet), or a file that does not read back (with a warning)."""
        import pandas as pd
        import pyarrow as pa

        if not (self.pairs_path.is_file() and self.summary_path.is_file()):
            return None
        try:
            summary = json.loads(self.summary_path.read_text())
        except (OSError, ValueError) as err:
            return self._damaged(self.summary_path, f"{type(err).__name__}: {err}")
        if summary.get("digest") != self.digest or summary.get("complete") is not True:
            return None
        try:
            frame = pd.read_parquet(self.pairs_path)
        except (OSError, ValueError, pa.ArrowException) as err:
            return self._damaged(self.pairs_path, type(err).__name__)
        if len(frame) != summary.get("n_pairs"):
            return self._damaged(self.pairs_path, f"{len(frame)} rows for {summary.get('n_pairs')} pairs")
        return summary

    def _damaged(self, path: Path, problem: str) -> None:
        print(f"warning: cell {self.key}: {path.name} is damaged ({problem}); recomputing it", file=sys.stderr)


def cell_metrics(
    results: Sequence[PairResult], pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], euler_seq: str
) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """RegistrationMetrics over the cell (failed pairs count with their identity estimate) and the
    per-pair errors."""
    import torch

    from src.geometry import se3_apply
    from src.metrics import RegistrationMetrics, chamfer_distance, pair_errors

    metric = RegistrationMetrics(euler_seq)
    per_pair: dict[str, list[float]] = {name: [] for name in PAIR_ERROR_COLUMNS}
    for result, (src, ref, gt) in zip(results, pairs):
        pred_t = torch.tensor(np.asarray(result.transform), dtype=torch.float64)[None]
        gt_t = torch.as_tensor(gt, dtype=torch.float32)[None]
        src_t = torch.as_tensor(src, dtype=torch.float32)[None]
        ref_t = torch.as_tensor(ref, dtype=torch.float32)[None]
        metric.update(pred_t, gt_t, src_t, ref_t)
        err = pair_errors(pred_t, gt_t, euler_seq)
        per_pair["Error(R)"].append(float(err["rot_deg"][0]))
        per_pair["Error(t)"].append(float(err["trans_norm"][0]))
        per_pair["MAE(R)"].append(float(err["euler_err"][0].abs().mean()))
        per_pair["MAE(t)"].append(float(err["trans_err"][0].abs().mean()))
        moved = se3_apply(pred_t.float(), src_t)
        per_pair["chamfer"].append(float(chamfer_distance(moved, ref_t)[0]))
    return metric.compute(), {k: np.asarray(v) for k, v in per_pair.items()}


def register_cells(cells: Sequence[Cell], cfg: DictConfig) -> list[tuple[list[PairResult], float]]:
    """Register the pairs of ``cells`` (all of one registrator): one PairResult list per cell and the
    wall time of the call. A classical method's cells go through one :func:`run_pairs` call (one set
    of worker processes for all of them); a learned method's through :func:`run_batches`."""
    registrator = cells[0].registrator
    clouds = [[(src, ref) for src, ref, _ in cell.test_set.pairs(cell.n_pairs)] for cell in cells]
    flat = [pair for cell_clouds in clouds for pair in cell_clouds]
    start = time.perf_counter()
    if getattr(registrator, "needs_training", False):
        from baselines.learned.adapter import run_batches

        results = run_batches(registrator, flat, progress=bool(cfg.progress))
    else:
        workers = cfg.get("workers")
        results = run_pairs(registrator, flat, workers=None if workers is None else int(workers),
                            timeout_s=cfg.get("timeout_s"), progress=bool(cfg.progress))
    wall = time.perf_counter() - start
    out, offset = [], 0
    for cell_clouds in clouds:
        part = results[offset : offset + len(cell_clouds)]
        out.append(([PairResult(i, r.transform, r.seconds, r.failed, r.reason) for i, r in enumerate(part)],
                     wall * len(cell_clouds) / max(len(flat), 1)))
        offset += len(cell_clouds)
    return out


def finish_cell(cell: Cell, results: Sequence[PairResult], wall: float) -> dict[str, Any]:
    """Score a registered cell, write its parquet, then its JSON (the commit marker); return the summary."""
    import pandas as pd

    t = cell.test_set
    pairs = t.pairs(cell.n_pairs)
    euler_seq = euler_seq_for(t.partial)
    metrics, errors = cell_metrics(results, pairs, euler_seq)
    frame = pd.DataFrame({
        "method": cell.method,
        "experiment": t.experiment,
        "sampling": t.sampling.upper(),
        "partial": t.partial,
        "dataset": t.dataset_name,
        "cell": cell.digest,
        "pair": [r.index for r in results],
        "transform": [np.asarray(r.transform, dtype=np.float64).reshape(-1).tolist() for r in results],
        "transform_gt": [gt.reshape(-1).tolist() for _, _, gt in pairs],
        "seconds": [float(r.seconds) for r in results],
        "failed": [bool(r.failed) for r in results],
        "reason": [r.reason for r in results],
        **{name: errors[name] for name in PAIR_ERROR_COLUMNS},
    })
    cell.folder.mkdir(parents=True, exist_ok=True)
    write_atomic(cell.pairs_path, lambda p: frame.to_parquet(p, index=False))
    n_failed = int(frame["failed"].sum())
    summary = {
        "digest": cell.digest,
        "method": cell.method,
        "label": getattr(cell.registrator, "label", display_name(cell.method)),
        "experiment": t.experiment,
        "sampling": t.sampling,
        "partial": t.partial,
        "dataset": t.dataset_name,
        "noise_sigma": t.noise_sigma,
        "euler_seq": euler_seq,
        "n_pairs": len(results),
        "n_failed": n_failed,
        "failure_reasons": frame.loc[frame["failed"], "reason"].value_counts().to_dict(),
        "seconds": float(frame["seconds"].sum()),
        "wall_seconds": wall,
        "metrics": metrics,
        "definition": cell.definition,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "complete": True,
    }
    write_atomic(cell.summary_path, lambda p: p.write_text(json.dumps(summary, indent=2, default=str)))
    return summary


def run_cell(cell: Cell, cfg: DictConfig) -> dict[str, Any]:
    """Register one cell's pairs and write its files; return the summary."""
    [(results, wall)] = register_cells([cell], cfg)
    return finish_cell(cell, results, wall)


def _calls(cells: Sequence[Cell], pairs_per_call: int | None) -> list[list[Cell]]:
    """Pending cells grouped by registrator (in grid order), each group cut into calls of at most
    ``pairs_per_call`` pairs (a cell is never split)."""
    groups: dict[int, list[Cell]] = {}
    for cell in cells:
        groups.setdefault(id(cell.registrator), []).append(cell)
    calls = []
    for group in groups.values():
        current: list[Cell] = []
        for cell in group:
            if current and pairs_per_call and sum(c.n_pairs for c in current) + cell.n_pairs > pairs_per_call:
                calls.append(current)
                current = []
            current.append(cell)
        calls.append(current)
    return calls


def tidy_rows(summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    from src.metrics import METRIC_NAMES

    n = int(summary["n_pairs"])
    common = {
        "method": summary.get("label") or display_name(summary["method"]),
        "method_id": summary["method"],
        "experiment": summary["experiment"],
        "sampling": str(summary["sampling"]).upper(),
        "partial": summary["partial"],
        "dataset": summary["dataset"],
        "noise_sigma": float(summary["noise_sigma"]),
    }
    tail = {"n_pairs": n, "n_failed": int(summary["n_failed"]), "seconds": float(summary["seconds"]),
            "seconds_per_pair": float(summary["seconds"]) / max(n, 1), "cell": summary["digest"]}
    return [{**common, "metric": name, "value": float(summary["metrics"][name]), **tail}
            for name in METRIC_NAMES if name in summary["metrics"]]


# --- the grid ---------------------------------------------------------------------------------------


@dataclass
class GridResult:
    tidy: Any  # pandas.DataFrame, see TIDY_COLUMNS
    pairs: Any  # pandas.DataFrame, one row per pair
    cells: list[dict[str, Any]]
    reused: int = 0
    computed: int = 0
    skipped: list[str] = field(default_factory=list)
    output_dir: Path | None = None


def _names(values: Any, what: str, allowed: Sequence[str] | None = None) -> list[str]:
    values = _plain(values)
    if isinstance(values, str):
        values = [values]
    if not values:
        raise ConfigError(f"benchmark.{what} is empty")
    names = [str(v).strip().lower() for v in values]
    if allowed is not None:
        bad = [v for v in names if v not in allowed]
        if bad:
            raise ConfigError(f"benchmark.{what}: unknown value(s) {bad}; choose from {list(allowed)}")
    return list(dict.fromkeys(names))


def plan(cfg: DictConfig) -> tuple[list[Cell], list[str]]:
    """Every cell of the grid (validated: methods, checkpoints, experiments, data), and notes on the
    cells that are skipped."""
    bench = cfg.benchmark
    methods = _names(bench.methods, "methods")
    for method in methods:
        resolve_registrator(method)  # ConfigError naming the available methods
    methods = [resolve_registrator(m).name for m in methods]
    experiments = _names(bench.experiments, "experiments")
    samplings = _names(bench.samplings, "samplings", SAMPLINGS)
    partials = _names(bench.partials, "partials", PARTIALS)
    exclude = [str(p) for p in (_plain(bench.get("exclude")) or [])]
    max_pairs = bench.get("max_pairs")
    by_method = _plain(bench.get("max_pairs_by_method")) or {}
    timeout = cfg.get("timeout_s")
    extra = [str(o) for o in (_plain(bench.get("overrides")) or [])] + _command_line_data_overrides()
    data = _data_choice(cfg)
    folder = Path(str(cfg.output_dir)) / "cells"
    factory = MethodFactory(cfg)

    cells, notes = [], []
    for method in methods:  # bad options, missing or foreign checkpoints fail before any data is touched
        factory.validate(method)
    for experiment in experiments:
        for sampling in samplings:
            for partial in partials:
                keys = [f"{m}/{experiment}/{sampling}/{partial}" for m in methods]
                if all(any(fnmatch.fnmatchcase(k, p) for p in exclude) for k in keys):
                    continue
                test_set = build_test_set(experiment, sampling, partial, data, extra)
                for method in methods:
                    key = f"{method}/{test_set.key}"
                    if any(fnmatch.fnmatchcase(key, p) for p in exclude):
                        continue
                    registrator = factory.build(method, test_set.key)
                    if registrator is None:
                        notes.append(f"{key}: skipped (no checkpoint of {method} matches {test_set.key})")
                        continue
                    limit = by_method.get(method, max_pairs)
                    total = test_set.definition["num_test_pairs"]
                    n_pairs = total if limit is None else min(int(limit), total)
                    if n_pairs < 1:
                        raise ConfigError(f"{key}: no pairs to evaluate (max_pairs={limit})")
                    definition = {
                        "format": GRID_FORMAT,
                        "method": factory.identity(registrator),
                        "experiment": experiment,
                        "sampling": sampling,
                        "partial": partial,
                        "test_set": test_set.definition,
                        "n_pairs": n_pairs,
                        "timeout_s": None if factory.is_learned(method) else timeout,
                    }
                    cells.append(Cell(method, test_set, registrator, n_pairs, definition, _digest(definition), folder))
    if not cells:
        raise ConfigError("the grid has no cells (check benchmark.methods/experiments/exclude and the checkpoints)")
    return cells, notes


def run_grid(cfg: DictConfig) -> GridResult:
    """Plan, run (or reuse) every cell, write the tidy table and the per-pair rows."""
    import pandas as pd
    from tqdm.auto import tqdm

    output_dir = Path(str(cfg.output_dir))
    cells, notes = plan(cfg)
    output_dir.mkdir(parents=True, exist_ok=True)
    done = {cell.digest: loaded for cell in cells if (loaded := cell.load()) is not None}
    pending = [cell for cell in cells if cell.digest not in done]
    with tqdm(total=len(cells), initial=len(done), disable=not cfg.progress, desc="grid", unit="cell", dynamic_ncols=True) as bar:
        for call in _calls(pending, cfg.get("pairs_per_call")):
            bar.set_postfix_str(f"{call[0].method}: {len(call)} cell(s)", refresh=True)
            for cell, (results, wall) in zip(call, register_cells(call, cfg)):
                done[cell.digest] = finish_cell(cell, results, wall)
                bar.update(1)
    summaries = [done[cell.digest] for cell in cells]
    tidy = pd.DataFrame([row for s in summaries for row in tidy_rows(s)], columns=list(TIDY_COLUMNS))
    pairs = pd.concat([pd.read_parquet(cell.pairs_path) for cell in cells], ignore_index=True)
    write_atomic(output_dir / "results.parquet", lambda p: tidy.to_parquet(p, index=False))
    tidy.to_csv(output_dir / "results.csv", index=False)
    write_atomic(output_dir / "pairs.parquet", lambda p: pairs.to_parquet(p, index=False))
    return GridResult(tidy, pairs, summaries, len(cells) - len(pending), len(pending), notes, output_dir)


# --- reporting --------------------------------------------------------------------------------------


def summary_table(tidy, metrics: Sequence[str] = ("Error(R)", "Error(t)", "RMSE(R)", "RMSE(t)")) -> str:
    """A compact plain-text view: one row per cell, a few metrics, failures and time per pair."""
    import pandas as pd

    wide = tidy.pivot_table(index=["partial", "experiment", "sampling", "method"], columns="metric", values="value",
                            aggfunc="first", sort=False)
    extra = tidy.groupby(["partial", "experiment", "sampling", "method"], sort=False)[["n_pairs", "n_failed", "seconds_per_pair"]].first()
    table = wide[[m for m in metrics if m in wide.columns]].join(extra)
    table["ms/pair"] = (table.pop("seconds_per_pair") * 1000).round(1)
    with pd.option_context("display.width", 200, "display.max_rows", 500, "display.float_format", "{:.4f}".format):
        return table.reset_index().to_string(index=False)


def write_tables(tidy, output_dir: Path, paper: bool = True) -> list[Path]:
    """table.md / table.tex in the paper's Table-1 layout via benchmarks.tables (if available)."""
    try:
        from benchmarks import tables
    except ImportError:  # pragma: no cover - tables module absent
        return []
    paper_frame = None
    if paper:
        try:
            from benchmarks.paper import load_paper_tables

            paper_frame = load_paper_tables()
        except (ImportError, FileNotFoundError):
            paper_frame = None
    try:
        table = tables.build_table(tidy, "table1", paper=paper_frame)
    except ValueError as err:
        print(f"note: no LaTeX/Markdown table ({err})", file=sys.stderr)
        return []
    written = [output_dir / "table.md", output_dir / "table.tex"]
    written[0].write_text(tables.to_markdown(table))
    written[1].write_text(tables.to_latex(table))
    return written


def report(result: GridResult, cfg: DictConfig) -> None:
    print(f"\nComparison grid '{cfg.benchmark.name}': {len(result.cells)} cells "
          f"({result.computed} computed, {result.reused} reused) in {result.output_dir}")
    datasets = sorted(result.tidy["dataset"].unique())
    if "synthetic" in datasets:
        print("dataset: synthetic (procedural CAD-like shapes) - these are NOT ModelNet40 results")
    print(summary_table(result.tidy))
    failed = [c for c in result.cells if c["n_failed"]]
    for c in failed:
        reasons = "; ".join(f"{k} (x{v})" for k, v in list(c.get("failure_reasons", {}).items())[:3])
        print(f"failed pairs: {c['method']}/{c['experiment']}/{c['sampling']}/{c['partial']}: "
              f"{c['n_failed']} of {c['n_pairs']} (counted with the identity): {reasons}")
    for note in result.skipped:
        print(f"note: {note}")
    written = write_tables(result.tidy, result.output_dir, paper=bool(cfg.get("paper", True)))
    if written:
        print("\n" + written[0].read_text())
    print("wrote " + ", ".join(str(p) for p in [result.output_dir / "results.parquet", result.output_dir / "results.csv",
                                                result.output_dir / "pairs.parquet", *written]))


def _run(cfg: DictConfig) -> None:
    result = run_grid(cfg)
    report(result, cfg)


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="benchmark_grid")
def main(cfg: DictConfig) -> None:
    from src.runtime import exit_on_user_error  # one `error: ...` line and exit 2 for a UserError

    exit_on_user_error(_run)(cfg)


if __name__ == "__main__":
    main()
