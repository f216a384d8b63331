"""The grid's plan: its configuration, test sets, methods and cells (see :mod:`benchmarks.grid`).

:func:`plan` turns the grid's config into :class:`Cell` objects: every method × experiment × sampling
× partial manner not excluded, each with its fixed test set (:func:`src.pair_sets.build_test_set`, the pairs of
``src.eval +exp=<experiment>``), its registrator (:class:`MethodFactory`) and a digest of everything
that defines its results (method and options, checkpoint or weights contents, test set and data
content hash, number of pairs, timeout), which names its files and makes finished cells reusable.

The grid's primary config ``benchmark_grid`` is stored here: ``conf/benchmark/default.yaml`` plus, from
the method registry (:mod:`baselines.methods`), the default ``benchmark.methods`` and a
``method_options.<key>`` entry per method (so ``method_options.<key>.checkpoint=PATH`` is a plain override).
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf

from baselines import resolve_registrator
from baselines.base import Registrator
from baselines.methods import METHODS, default_grid_methods
from src.config import register_resolvers
from src.data.cache import file_sha256
from src.utils.errors import CheckpointError, ConfigError, UserError
from src.utils.files import read_parquet
from src.pair_sets import TestSet, build_test_set

# torch, pandas, torchmetrics and lightning are imported where they are used: the worker processes
# of run_pairs (spawned) re-import the grid's modules, and light modules keep their start-up short.

register_resolvers()

GRID_FORMAT = 1
SAMPLINGS = ("os", "ts")
PARTIALS = ("prnet", "rpmnet", "none")

# The app's primary config only pulls in conf/benchmark/default.yaml, so that `+benchmark=<name>`
# (conf/benchmark/<name>.yaml, package `benchmark`) can be appended on the command line.
#: The grid's primary config, registered here (compose it by this name, imported from here).
GRID_CONFIG = "benchmark_grid"
ConfigStore.instance().store(name=GRID_CONFIG, node={
    "defaults": ["_self_", "benchmark/default"],
    "benchmark": {"methods": default_grid_methods()},
    "method_options": {method.key: method.grid_options for method in METHODS},
})


# --- composing the experiments --------------------------------------------------------------------


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
        if getattr(registrator, "samples_at_test", None) is False:  # a deterministic network: its seed draws nothing
            config.pop("seed", None)
        if config.get("weights"):
            from baselines.learned.published import weights_sha256  # torch: not in the grid's worker start-up

            config["weights_sha256"] = weights_sha256(config["weights"])
        checkpoint = config.get("checkpoint")
        if checkpoint:
            if checkpoint not in self._digests:
                self._digests[checkpoint] = file_sha256(checkpoint)
            config["checkpoint_sha256"] = self._digests[checkpoint]
        return {"name": registrator.name, "config": config}


# --- one cell ---------------------------------------------------------------------------------------


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def numbers_digest(summary: Mapping[str, Any]) -> str:
    """The checksum of a cell's summary (as read back from its JSON): every field but ``checksum`` itself, the
    per-pair file's ``pairs_sha256`` included."""
    return _digest({key: value for key, value in summary.items() if key != "checksum"})


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
    def progress_path(self) -> Path:
        """The results of the cell's first pairs, kept while an unfinished call goes on (removed once it is written)."""
        return self.folder / f"{self.stem}.partial.parquet"

    @property
    def key(self) -> str:
        return f"{self.method}/{self.test_set.key}"

    def load(self) -> dict[str, Any] | None:
        """The finished cell's summary when its files prove intact, else None (it must be computed): never run,
        interrupted (no JSON yet), or (with one warning line) a file that does not read back, a summary whose
        numbers do not match the checksum written with them (:func:`numbers_digest`), a per-pair file changed since
        (its sha256), or a cell written without these checksums."""
        if not (self.pairs_path.is_file() and self.summary_path.is_file()):
            return None
        try:
            summary = json.loads(self.summary_path.read_text())
        except (OSError, ValueError) as err:
            return self._damaged(self.summary_path, f"is damaged ({type(err).__name__}: {err})")
        if not isinstance(summary, dict):
            return self._damaged(self.summary_path, "is damaged (not a JSON object)")
        if summary.get("digest") != self.digest or summary.get("complete") is not True:
            return None
        if "checksum" not in summary:
            return self._damaged(self.summary_path, "cannot be verified (written without a checksum, by an earlier "
                                                    "version)")
        if summary["checksum"] != numbers_digest(summary):
            return self._damaged(self.summary_path, "was changed after it was written (its numbers do not match "
                                                    "the checksum written with them)")
        if file_sha256(self.pairs_path) != summary.get("pairs_sha256"):
            return self._damaged(self.pairs_path, "was changed after it was written (its sha256 is not the one "
                                                  f"{self.summary_path.name} records)")
        try:
            frame = read_parquet(self.pairs_path)
        except UserError as err:
            return self._damaged(self.pairs_path, f"is damaged ({err})")
        if len(frame) != summary.get("n_pairs"):
            return self._damaged(self.pairs_path, f"is damaged ({len(frame)} rows for {summary.get('n_pairs')} pairs)")
        return summary

    def _damaged(self, path: Path, problem: str) -> None:
        print(f"warning: cell {self.key}: {path.name} {problem}; recomputing it", file=sys.stderr)


# --- the grid ---------------------------------------------------------------------------------------


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
    reference = bench.get("reference")
    if reference and resolve_registrator(reference).name not in methods:  # the reference row, whatever the list
        methods.append(resolve_registrator(reference).name)
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
