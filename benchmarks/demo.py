"""The end of the first run: a small comparison on the test pairs of a ``src.train`` run.

    python -m src.train +exp=unseen_shapes data=synthetic trainer=smoke && python -m benchmarks.demo
    python -m benchmarks.demo --run outputs/unseen_shapes/<time>        # a given run
    python -m benchmarks.demo demo.pairs=all workers=2                  # every test pair; any grid setting
    python -m benchmarks.demo --threads 2                                # torch threads (default 1)

Takes the last started ``src.train`` run under ``outputs/`` with a best checkpoint (or ``--run``) and
recomposes its own test set: its experiment, dataset, sampling and partial manner, plus every other
data setting of its ``config_resolved.yaml`` that differs from the experiment's defaults (data
overrides, cache folder). By default it takes the pairs the run's own test evaluated (the first
``trainer.limit_test_batches`` batches: 32 after ``trainer=smoke``, so the run's row repeats its test
metrics); ``demo.pairs=all`` takes them all. On those pairs it evaluates, through the comparison grid
(:mod:`benchmarks.grid`: the same test set, registrators, metrics and timing, so the numbers are the
grid's), the methods of ``conf/benchmark/demo.yaml`` (identity, ICP, FGR), the shipped checkpoint
(``checkpoints/*.json``: :func:`~src.models.pretrained.find_shipped`'s for the run's experiment, else
the card closest to it, evaluated here whatever it was trained for and labelled so) and the run's own
best checkpoint; the identity is always its first row. Every row is evaluated in float32, as the run's own test
is (:mod:`src.run.precision`): where a learned row was trained in another precision (the run's config, the shipped
card's ``training.precision``), a note says what each trained in. A run whose model does not beat the identity's
Error(R) (a few CPU minutes of training do not) is labelled a pipeline check, with what a useful run
needs: the shipped model's steps, batch, CPU-hours and validation curve, from its card. It prints a
compact table (Error(R), Error(t), RMSE(R), ms/pair; units and "lower is better" in the header) and writes
``demo.md`` and ``demo.tex`` into the run dir; the grid's files go to ``<run>/demo/<group>/``, and a
re-run reuses their finished cells.

A missing or unusable run stops with one ``error: ...`` line (exit status 2).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import re
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from baselines.methods import Method, display_name, get_method, method_of_network
from benchmarks.grid.plan import GRID_CONFIG
from benchmarks.tables import render as tables
from benchmarks.tables.paper import EXPERIMENT_LABELS, canonical_experiment
from src.compose import compose_experiment
from src.metrics import ERROR_R, ERROR_T, RMSE_R
from src.pair_sets import LOADER_KEYS
from src.run.precision import FP32
from src.run.resume import best_checkpoint
from src.utils.errors import CheckpointError, ConfigError, exit_code_of
from src.utils.paths import CONF_DIR, SHIPPED_DIR

METRICS = (ERROR_R, ERROR_T, RMSE_R)
#: Data keys that change how the test set is loaded, not which pairs it holds (the cache folder does count).
LOADER_ONLY = tuple(k for k in LOADER_KEYS if k != "cache_root")
TABLE_NAME = "demo"
#: What the closest shipped checkpoint shares with the run when none was trained for its experiment.
SHARED_KEYS = ("dataset", "sampling", "partial")
#: ``demo.pairs`` of ``conf/benchmark/demo.yaml``: the pairs the run's own test evaluated, or all.
PAIRS = ("tested", "all")
#: The reference row, always first.
IDENTITY = "identity"
IDENTITY_LABEL = display_name(IDENTITY)
#: The CSV logger records a validation at global step - 1 (best-8.ckpt's validation is logged at step 7).
LOGGED_STEP_OFFSET = 1
#: How a card's note states the training's cost, e.g. "1.21 CPU hours".
CPU_HOURS = re.compile(r"([\d.]+) CPU hours")
UNITS = ("Lower is better in every column (↓): Error(R) and RMSE(R) in degrees, Error(t) in the shapes' units (each "
         "shape lies in the unit sphere), times in ms per pair.")


@dataclass(frozen=True)
class Run:
    """A ``src.train`` run: its folder, resolved config, experiment and best checkpoint."""

    path: Path
    cfg: DictConfig
    experiment: str
    checkpoint: Path

    @property
    def identity(self) -> dict[str, str]:
        """What a shipped checkpoint is matched on (:data:`src.models.pretrained.IDENTITY_KEYS`)."""
        return {"task": self.experiment, "dataset": str(self.cfg.data.dataset), "sampling": str(self.cfg.sampling),
                "partial": str(self.cfg.partial)}


@dataclass(frozen=True)
class Entry:
    """One row of the demo: a registry method, its label, and a checkpoint for a learned one."""

    method: str
    label: str
    checkpoint: Path | None = None


# --- the run ---------------------------------------------------------------------------------------


def find_run(outputs: Path) -> Path:
    """The newest ``src.train`` run under ``outputs`` with a best checkpoint (the last started: its
    ``config_resolved.yaml`` is written when a run starts or resumes)."""
    runs = [config for config in outputs.rglob("config_resolved.yaml") if best_checkpoint(config.parent)]
    if not runs:
        raise ConfigError(
            f"no src.train run with a best checkpoint under {outputs}/: train one first, e.g. `python -m src.train "
            "+exp=unseen_shapes data=synthetic trainer=smoke`, or pass --run <run dir>"
        )
    return max(runs, key=lambda config: config.stat().st_mtime).parent


def load_run(run_dir: Path) -> Run:
    """The run in ``run_dir`` (ConfigError if it is not a ``src.train`` run with a best checkpoint)."""
    from src.models.pretrained import run_experiment

    if not run_dir.is_dir():
        raise ConfigError(f"run directory {run_dir} does not exist: pass the folder of a src.train run")
    config = run_dir / "config_resolved.yaml"
    if not config.is_file():
        raise ConfigError(f"{run_dir} is not a src.train run (no config_resolved.yaml)")
    checkpoint = best_checkpoint(run_dir)
    if checkpoint is None:
        raise ConfigError(f"{run_dir} has no best checkpoint (checkpoints/best-*.ckpt): it stopped before its first "
                          "validation; train longer or pick another run")
    cfg = OmegaConf.load(config)
    return Run(run_dir, cfg, run_experiment(run_dir, {"task": cfg.task_name}), checkpoint)


# --- its test set ----------------------------------------------------------------------------------


def _override_value(value: Any) -> str:
    """``value`` in Hydra's override grammar."""
    if isinstance(value, str):
        return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"
    if isinstance(value, bool) or value is None:
        return "null" if value is None else str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_override_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{_override_value(v)}" for k, v in value.items()) + "}"
    return repr(value)


def _differences(run: dict[str, Any], composed: dict[str, Any], prefix: str) -> list[str]:
    """Overrides that turn ``composed`` into ``run`` on every key of ``run`` (loader settings aside)."""
    out = []
    for key, value in run.items():
        if key in LOADER_ONLY and prefix == "data":
            continue
        if isinstance(value, dict) and isinstance(composed.get(key), dict):
            out += _differences(value, composed[key], f"{prefix}.{key}")
        elif key not in composed:
            out.append(f"+{prefix}.{key}={_override_value(value)}")
        elif composed[key] != value:
            out.append(f"{prefix}.{key}={_override_value(value)}")
    return out


def data_overrides(run: Run) -> list[str]:
    """The ``data.*`` overrides that make the run's experiment compose the run's own test set."""
    base = [f"+exp={run.experiment}", f"sampling={run.cfg.sampling}", f"partial={run.cfg.partial}",
            f"data={run.cfg.data.dataset}"]
    wanted = OmegaConf.to_container(run.cfg.data, resolve=True)
    overrides = _differences(wanted, OmegaConf.to_container(compose_experiment(base).data, resolve=True), "data")
    left = _differences(wanted, OmegaConf.to_container(compose_experiment(base + overrides).data, resolve=True), "data")
    if left:
        raise ConfigError(f"cannot recompose the test set of {run.path}: {', '.join(left)} still differ")
    return overrides


def own_test_pairs(run: Run, overrides: Sequence[str]) -> int | None:
    """How many pairs the run's own test evaluated (None: all): the first ``trainer.limit_test_batches``
    batches of ``data.eval_batch_size`` (an int: that many; a float: that fraction of them)."""
    limit, size = run.cfg.trainer.get("limit_test_batches"), int(run.cfg.data.eval_batch_size)
    if isinstance(limit, int):
        return limit * size  # the grid takes at most the whole test set
    if limit is None or float(limit) >= 1.0:
        return None
    from src.pair_sets import build_test_set

    total = build_test_set(run.experiment, str(run.cfg.sampling), str(run.cfg.partial), str(run.cfg.data.dataset),
                           overrides).definition["num_test_pairs"]
    return max(int(math.ceil(total / size) * float(limit)), 1) * size


# --- the rows --------------------------------------------------------------------------------------


def _learned(target: str, where: str) -> Method:
    method = method_of_network(target)
    if method is None:
        raise ConfigError(f"{where} holds a {target} network, which is no method of baselines/methods.yaml")
    return method


def checkpoint_label(method: Method, who: str, network: dict[str, Any], best: int | None, steps: int | None) -> str:
    """``OMNet (this run: best at step 8 of 16, width 0.25)``: the method, whose weights, how trained
    (the step of the kept checkpoint, of how many steps run)."""
    trained = None if best is None else f"best at step {best:,}" + (f" of {steps:,}" if steps else "")
    details = [trained, f"width {network['width']:g}" if network.get("width") is not None else None]
    return f"{method.display} ({who}: {', '.join(d for d in details if d)})"


def steps_run(run: Run) -> int | None:
    """How many optimisation steps the run made (its ``metrics.json``; None before its test)."""
    metrics = run.path / "metrics.json"
    return json.loads(metrics.read_text()).get("global_step") if metrics.is_file() else None


def run_entry(run: Run) -> Entry:
    """The row of the run's own best checkpoint."""
    from src.run.checkpoint_io import read_checkpoint

    checkpoint = read_checkpoint(run.checkpoint)
    network = checkpoint["hyper_parameters"]["network"]
    method = _learned(network["_target_"], str(run.checkpoint))
    label = checkpoint_label(method, "this run", network, checkpoint.get("global_step"), steps_run(run))
    return Entry(method.key, label, run.checkpoint)


def shipped_card(run: Run, directory: Path) -> tuple[Path, dict[str, Any]] | None:
    """The shipped checkpoint for the run's experiment and network (:func:`find_shipped`), else the card (of
    the run's network, if one is shipped) with the most of (dataset, sampling, partial) in common; None when
    no card has its ``.ckpt``."""
    from src.models.pretrained import find_shipped

    cards = {p.with_suffix(".ckpt"): json.loads(p.read_text()) for p in sorted(directory.glob("*.json"))}
    cards = {path: card for path, card in cards.items() if path.is_file()}
    network = run.cfg.model.network._target_
    cards = {path: card for path, card in cards.items() if card["network"]["_target_"] == network} or cards
    try:
        path = find_shipped(run.identity, directory, network=network)
    except CheckpointError:
        path = None
    if path not in cards and cards:
        path = max(cards, key=lambda p: sum(cards[p]["experiment"][k] == run.identity[k] for k in SHARED_KEYS))
    return (path, cards[path]) if path in cards else None


def shipped_entry(run: Run, directory: Path) -> tuple[Entry | None, str]:
    """The row of the shipped checkpoint (None if there is none) and a note on what it was trained for."""
    found = shipped_card(run, directory)
    if found is None:
        return None, f"no shipped checkpoint in {directory} (a .json card with its .ckpt): its row is left out"
    path, card = found
    method = _learned(card["network"]["_target_"], str(path))
    training = card.get("training", {})
    entry = Entry(method.key, checkpoint_label(method, "shipped", card["network"], training.get("step_of_checkpoint"),
                                               training.get("steps_run")), path)
    trained = card["experiment"]
    what = ", ".join(f"{k}={trained[k]}" for k in run.identity)
    differ = ", ".join(f"{k}={v}" for k, v in run.identity.items() if trained[k] != v)
    if not differ:
        return entry, f"{entry.label}: {path.name}, trained for this run's experiment ({what})"
    return entry, f"{entry.label}: {path.name}, trained for {what}; evaluated here on this run's pairs ({differ})"


def _cpu_hours(card: dict[str, Any]) -> str:
    """`` (1.21 CPU-h)`` as the card's note records the training's cost, else empty."""
    found = CPU_HOURS.search(card.get("note", ""))
    return f" ({found.group(1)} CPU-h)" if found else ""


def pipeline_check_note(tidy: Any, mine: Entry, run: Run, card: dict[str, Any] | None) -> str | None:
    """When the run's own model does not beat the identity's Error(R): what the run is (a pipeline check) and
    what a useful one needs, from the shipped model's card: its budget and its validation curve, with the
    step at which it first beat the identity's Error(R) on these pairs. None when the run beats the identity."""
    errors = tidy[tidy["metric"] == ERROR_R].set_index("method")["value"]
    identity, own = float(errors[IDENTITY_LABEL]), float(errors[mine.label])
    if own < identity:
        return None
    steps, batch = steps_run(run), run.cfg.data.batch_size
    note = (f"{mine.label} is a pipeline check, not a result: {steps or '?'} steps of batch {batch} do not learn "
            f"registration (Error(R) {own:.1f}° against the identity's {identity:.1f}°)")
    if card is None:
        return note
    training = card["training"]
    curve = [(point["step"] + LOGGED_STEP_OFFSET, point[ERROR_R]) for point in training.get("validation", [])]
    first = next((step for step, error in curve if error < identity), None)
    beat = (f"; its validation Error(R) first fell below {identity:.1f}° after {first:,} steps" if first else "")
    shown = ", ".join(f"{error:.1f}° at {step:,}" for step, error in curve)
    return (f"{note}. A useful model needs a longer run: the shipped one trained {training['steps_run']:,} steps of "
            f"batch {training['batch_size']}{_cpu_hours(card)}{beat} (validation curve: {shown}); its command is in "
            f"its card, {card['name']}.json (docs/results.md: Shipped checkpoints)")


# --- the comparison --------------------------------------------------------------------------------


def grid_config(run: Run, overrides: Sequence[str]) -> DictConfig:
    """``benchmark_grid`` with ``+benchmark=demo``, the run's data and ``overrides``, on the run's test set."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(GRID_CONFIG, overrides=["+benchmark=demo", *overrides, f"data={run.cfg.data.dataset}"])
    except HydraException as err:
        raise ConfigError(f"bad grid override in {list(overrides)}: {str(err).strip().splitlines()[0]}") from None
    cfg.benchmark.experiments = [run.experiment]
    cfg.benchmark.samplings = [str(run.cfg.sampling)]
    cfg.benchmark.partials = [str(run.cfg.partial)]
    cfg.benchmark.overrides = data_overrides(run)
    cfg.benchmark.exclude = []
    return cfg


def _group_config(cfg: DictConfig, entries: Sequence[Entry], output_dir: Path) -> DictConfig:
    """``cfg`` for the grid run of ``entries`` (one checkpoint at most)."""
    group = copy.deepcopy(cfg)
    group.benchmark.methods = [entry.method for entry in entries]
    group.benchmark.reference = None  # the demo's own first row is the identity
    for entry in entries:
        if entry.checkpoint is not None:
            group.method_options[entry.method].checkpoint = str(entry.checkpoint)
    group.output_dir = str(output_dir)
    return group


def compare(run: Run, entries: Sequence[Entry], cfg: DictConfig) -> tuple[Any, list[dict[str, Any]]]:
    """Every entry on the run's test set through :func:`benchmarks.grid.run.run_grid`, one grid run per
    checkpoint (the grid takes one per method); the tidy table (``method`` = the entry's label, rows in
    entry order) and the cells' summaries."""
    import pandas as pd

    from benchmarks.grid.run import run_grid

    groups: dict[Path | None, list[Entry]] = {}
    for entry in entries:
        groups.setdefault(entry.checkpoint, []).append(entry)
    tidy, cells = [], []
    for checkpoint, members in groups.items():
        name = "methods" if checkpoint is None else checkpoint.stem
        print(f"evaluating {', '.join(e.label for e in members)} ...", flush=True)
        start = time.perf_counter()
        result = run_grid(_group_config(cfg, members, run.path / "demo" / name))
        print(f"  {time.perf_counter() - start:.0f} s, {result.computed} cell(s) computed, {result.reused} reused")
        labels = {entry.method: entry.label for entry in members}
        tidy.append(result.tidy.assign(method=result.tidy["method_id"].map(labels)))
        cells += [{**cell, "label": labels[cell["method"]]} for cell in result.cells]
    frame = pd.concat(tidy, ignore_index=True)
    order = {entry.label: i for i, entry in enumerate(entries)}
    return frame.sort_values("method", key=lambda s: s.map(order), kind="stable", ignore_index=True), cells


def demo_table(tidy: Any, run: Run, notes: Sequence[str]) -> tables.Table:
    """The demo's table for :func:`benchmarks.tables.render.to_markdown` / ``to_latex``: one row per method,
    :data:`METRICS` and ms/pair (no ranking: the identity is the reference, not a competitor)."""
    metrics = [*METRICS, "ms/pair"]
    rows = []
    for label, part in tidy.groupby("method", sort=False):
        values = part.set_index("metric")["value"]
        ms_per_pair = 1000 * float(part["seconds_per_pair"].iloc[0])
        rows.append(tables.Row(label, [float(values[m]) for m in METRICS] + [ms_per_pair]))
    first = tidy.iloc[0]
    experiment = EXPERIMENT_LABELS.get(canonical_experiment(run.experiment), run.experiment)
    manner = {"prnet": "PRNet manner", "rpmnet": "RPMNet manner"}.get(first["partial"], f"partial={first['partial']}")
    caption = (f"Demo comparison on the {int(first['n_pairs'])} test pairs of the run "
               f"{'/'.join(run.path.parts[-2:])}: {experiment}, {first['dataset']} data, {first['sampling']}, {manner}. "
               f"{UNITS}")
    return tables.Table(TABLE_NAME, metrics, [str(first["sampling"])], [tables.Block(None, rows)], caption,
                        f"tab:{TABLE_NAME}", list(notes), header_units=True)


def precision_note(trained: dict[str, str]) -> str | None:
    """The note of a table whose learned rows (label -> the precision it trained in) were not all trained in
    float32; None when they were."""
    if set(trained.values()) <= {FP32}:
        return None
    return ("precision: every row is evaluated in float32 (32-true); the learned rows were trained in "
            + ", ".join(f"{precision} ({label})" for label, precision in trained.items()))


def _notes(run: Run, shipped_note: str, cells: Sequence[dict[str, Any]], tested: bool,
           check: str | None, precision: str | None) -> list[str]:
    """What the table's reader must know: what the run's row is, the shipped row, the precisions, the pairs, the
    data, failures, the times."""
    import torch

    notes = [*([check] if check else []), shipped_note, *([precision] if precision else [])]
    used, total = cells[0]["n_pairs"], cells[0]["definition"]["test_set"]["num_test_pairs"]
    if used < total:
        which = ", those the run was tested on" if tested else ""
        notes.append(f"the first {used} of the test set's {total} pairs{which}; demo.pairs=all evaluates all {total}")
    if run.cfg.data.dataset == "synthetic":
        notes.append("synthetic data (procedural CAD-like shapes): not ModelNet40 results")
    notes += [f"{c['label']}: {c['n_failed']} of {c['n_pairs']} pairs failed and count with the identity"
              for c in cells if c["n_failed"]]
    notes.append(f"times (ms/pair): one pass on this machine ({torch.get_num_threads()} torch thread(s)), first-call "
                 "overheads included (learned methods: batch time / batch size); python -m benchmarks.speed measures "
                 "steady-state speed")
    return notes


def write_tables(table: tables.Table, run_dir: Path) -> list[Path]:
    """``demo.md`` and ``demo.tex`` in ``run_dir``."""
    markdown, latex = run_dir / f"{TABLE_NAME}.md", run_dir / f"{TABLE_NAME}.tex"
    markdown.write_text(tables.to_markdown(table))
    tex = tables.to_latex(table).split("\n", 1)[1]  # its first line names benchmarks.tables
    latex.write_text("% generated by python -m benchmarks.demo\n" + tex)
    return [markdown, latex]


def run_demo(run_dir: Path, overrides: Sequence[str] = (), shipped_dir: Path | None = None) -> list[Path]:
    """The demo for the run in ``run_dir``: evaluate, print, write; returns the files written."""
    from src.models.pretrained import trained_precision

    run = load_run(run_dir)
    cfg = grid_config(run, overrides)
    if cfg.demo.pairs not in PAIRS:
        raise ConfigError(f"demo.pairs must be one of {', '.join(PAIRS)}, got {cfg.demo.pairs!r}")
    tested = cfg.demo.pairs == "tested" and cfg.benchmark.max_pairs is None
    if tested:
        cfg.benchmark.max_pairs = own_test_pairs(run, cfg.benchmark.overrides)
    methods = [IDENTITY, *(m for m in cfg.benchmark.methods if get_method(m).key != IDENTITY)]
    classical = [Entry(get_method(m).key, display_name(m)) for m in methods]
    directory = SHIPPED_DIR if shipped_dir is None else shipped_dir
    shipped, shipped_note = shipped_entry(run, directory)
    mine = run_entry(run)
    tidy, cells = compare(run, [*classical, *([shipped] if shipped else []), mine], cfg)
    card = shipped_card(run, directory) if shipped else None
    check = pipeline_check_note(tidy, mine, run, None if card is None else card[1])
    trained = {mine.label: str(run.cfg.trainer.precision)}
    if shipped is not None and card is not None:
        trained[shipped.label] = trained_precision(card[1])
    table = demo_table(tidy, run, _notes(run, shipped_note, cells, tested, check, precision_note(trained)))
    written = write_tables(table, run.path)
    print("\n" + written[0].read_text())
    print(f"wrote {written[0]} and {written[1]} (the grid's files: {run.path / 'demo'}/)\n"
          "next: the full comparison grid, python -m benchmarks.grid (docs/benchmarks.md: The grid)")
    return written


def _demo(args: argparse.Namespace) -> None:
    """The command: threads, then the demo of the given or the last started run."""
    import torch

    if args.threads < 1:
        raise ConfigError(f"--threads must be >= 1, got {args.threads}")
    torch.set_num_threads(args.threads)
    run_demo(args.run or find_run(args.outputs), args.overrides)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.demo", description=__doc__.split("\n\n")[0],
                                     epilog="Overrides: settings of the comparison grid (conf/benchmark/default.yaml).")
    parser.add_argument("--run", type=Path, default=None,
                        help="a src.train run dir (default: the last started under --outputs)")
    parser.add_argument("--outputs", type=Path, default=Path("outputs"),
                        help="where to look for runs (default: outputs)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads (default 1: the demo's batches are small, and threads contending for busy "
                             "cores made OMNet's inference up to 40 times slower on a shared 2-core machine)")
    parser.add_argument("overrides", nargs="*", help="grid overrides, e.g. benchmark.max_pairs=20 workers=0")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    status = exit_code_of(lambda: _demo(args))
    if not status:
        print(f"demo: {time.perf_counter() - start:.0f} s")
    return status


if __name__ == "__main__":
    sys.exit(main())
