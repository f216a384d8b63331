"""One CPU budget, every learned method: each trained through ``src.train`` on the real airplanes.

Protocol: ``+exp=real_airplane`` (train on the airplanes outside validation and test, select on the 200
validation pairs, test on the carve-out), TS, PRNet manner, clean pairs, one torch thread, pairs made in
the training process. Each method keeps its authors' recipe (``conf/recipe/<model>.yaml``; OMNet: the
official code's, ``recipe=omnet_official``) with the schedule mapped onto the steps the budget buys
(:func:`budget_schedule`), its authors' batch, and the widest width that still buys ``MIN_STEPS`` steps
(:func:`plan_method`, from a probe of the step's CPU time). PointNetLK's classifier stage trains first,
inside PointNetLK's budget. Resumable: ``run`` again resumes every run from its ``last.ckpt``.

    python -m benchmarks.studies.cpu_budget.budget run --root RUNS [--methods omnet,dcp] [--budget-h 1] [--parallel 2] [--archive DIR]
    python -m benchmarks.studies.cpu_budget.budget beyond --root RUNS --method omnet --recipe omnet_cpu --budget-h 1.5 [--init-weights CKPT]
    python -m benchmarks.studies.cpu_budget.budget archive --root RUNS --out benchmarks/studies/cpu_budget/results/runs
    python -m benchmarks.studies.cpu_budget.budget extend --root RUNS --folder omnet_beyond   # then run it again
    python -m benchmarks.studies.cpu_budget.budget ship --root RUNS --folder fmr --name <checkpoint name> --compute TEXT
    python -m benchmarks.studies.cpu_budget.report --root benchmarks/studies/cpu_budget/results/runs --out benchmarks/studies/cpu_budget/results

``extend`` re-plans a stopped run whose probe over-estimated the step cost (its planned steps leave CPU time of
its budget unused) to the steps the unused time buys at the cost the run measured.

``archive`` copies each run's record (plan, commands, CSV logs, test metrics: kilobytes, no checkpoint)
into the repository, so that the report is made from committed files: run folders need not outlive
the machine they ran on.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from benchmarks.studies.cpu_budget.recipes import (
    CPU_TRAINING_ENV,
    add_run_parser,
    code_version,
    run_each,
    train_logged,
)
from src.run.reporting import read_csv_logs
from src.run.resume import best_checkpoint, own_last_checkpoint, resumed_overrides
from src.utils.errors import ConfigError, exit_code_of
from src.utils.files import write_atomic
from src.utils.paths import with_folder, without_folder


def logged_cpu_hours(logs: pd.DataFrame) -> float:
    """The CPU hours a run's logs say it used (training and validation: the largest ``time/cpu_hours``)."""
    return float(logs["time/cpu_hours"].max()) if "time/cpu_hours" in logs else 0.0


def steps_trained(run_dir: Path, logs: pd.DataFrame) -> int:
    """Optimiser steps of a stage: the trainer's count in its test ``metrics.json`` or, where its logs go further (a
    run extended and still training), the step after their last training-time row."""
    path = run_dir / "metrics.json"
    tested = int(json.loads(path.read_text()).get("global_step", 0)) if path.is_file() else 0
    if logs.empty or "time/cpu_hours" not in logs:
        return tested
    return max(tested, int(logs.dropna(subset=["time/cpu_hours"])["step"].max()) + 1)


#: The learned methods of the grid, in the grid's order.
METHODS = ("omnet", "dcp", "prnet", "rpmnet", "idam", "pointnetlk", "pointnetlk_revisited", "fmr", "deepgmr")
#: A recipe other than ``conf/recipe/<model>.yaml``: OMNet's official code, not the paper's text (the guide's rule).
RECIPE_OF = {"omnet": "omnet_official"}
#: PointNetLK's first stage (its authors' ``ex1_train.sh``): a classifier whose features PointNetLK starts from.
CLASSIFIER = "pointnet_classifier"
MIN_STEPS = 500
WIDTHS = (1.0, 0.5, 0.25, 0.125, 0.0625)
VALIDATIONS = 20          # validations per run (200 pairs each), the points of the learning curve
PROBE_POINTS = 768        # the PRNet manner's crop
#: Step-cost allowance for what the probe does not time (pair generation, logging, Lightning's loop).
OVERHEAD = 1.1
#: How every run trains, whatever the protocol.
TRAINING = [
    "trainer.accelerator=cpu", "data.num_workers=0", "data.persistent_workers=false", "data.pin_memory=false",
    "data.eval_batch_size=50", "trainer.check_val_every_n_epoch=null", "trainer.max_epochs=-1",
    "trainer.log_every_n_steps=20", "trainer.enable_progress_bar=false", "test_after_fit=true",
    "callbacks.periodic_checkpoint.train_time_interval.minutes=5",
]


@dataclass(frozen=True)
class Protocol:
    """The data a budget trains on: the experiment's overrides, the classifier stage's (PointNetLK), and what it
    is in words (the note of a shipped checkpoint)."""

    experiment: list[str]
    classifier: list[str]
    description: str


PROTOCOLS = {
    # TS, PRNet manner, clean, real airplanes; the classifier on the synthetic default's categories (the real data
    # has one training category, nothing to classify; bathtubs are the unseen-category test set).
    "real_airplane": Protocol(["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0"],
                              ["+exp=unseen_shapes", "data=synthetic"],
                              "real ModelNet40 airplanes (+exp=real_airplane), TS, PRNet manner, clean"),
    # Table 1 on the 40 real categories, 1,024 points a shape: OS, PRNet manner, the first half's categories
    # (conf/exp/unseen_categories.yaml: validation on its carve-out, test on the second half); the classifier on
    # the same 14 training categories.
    "unseen_categories_npy": Protocol(["+exp=unseen_categories", "data=modelnet40_npy", "partial=prnet"],
                                      ["+exp=unseen_categories", "data=modelnet40_npy"],
                                      "Table 1 on the 40 real ModelNet40 categories (data=modelnet40_npy, 1,024 points a "
                                      "shape): the 3,566 carve-out shapes of the 14 first-half categories, OS, PRNet "
                                      "manner (717 points kept), clean, selected on the 210 validation carve-out pairs; "
                                      "one model for Table 1 (a) and (b)"),
    # Table 1 (c): the same with the paper's noise, tested on the unseen-shapes carve-out.
    "gaussian_noise_npy": Protocol(["+exp=gaussian_noise", "data=modelnet40_npy", "partial=prnet"],
                                   ["+exp=gaussian_noise", "data=modelnet40_npy"],
                                   "Table 1 (c) on the 40 real ModelNet40 categories (data=modelnet40_npy): the same "
                                   "shapes and pairs with the paper's noise (sigma 0.01 clipped at 0.05), selected on "
                                   "the noisy validation pairs"),
}


def compose_recipe(model: str, recipe: str | None = None) -> Any:
    """The model's training recipe as ``src.train`` composes it (``model=<model>`` plus its recipe: ``recipe``, or
    the study's, :data:`RECIPE_OF`)."""
    from src.compose import compose_conf

    recipe = recipe or RECIPE_OF.get(model)
    return compose_conf([f"model={model}"] + ([f"recipe={recipe}"] if recipe else []))


def budget_schedule(cfg: Any) -> list[str]:
    """Overrides that put the recipe's schedule on the run's own length: milestones (in epochs or steps)
    become fractions of the steps; a plateau's patience (in epochs) the same share of the validations."""
    from omegaconf import OmegaConf

    spec = OmegaConf.to_container(cfg.model, resolve=True).get("scheduler")
    length = cfg.trainer.max_epochs if cfg.trainer.max_epochs and cfg.trainer.max_epochs > 0 else cfg.trainer.max_steps
    if spec is None:
        return []
    if spec["name"] == "multistep" and "milestones" in spec:
        fractions = ", ".join(f"{m / length:.4g}" for m in spec["milestones"])
        return ["~model.scheduler",
                f"+model.scheduler={{name: multistep, interval: step, fractions: [{fractions}], gamma: {spec['gamma']}}}"]
    if spec["name"] == "plateau":
        patience = max(1, round(spec["patience"] / length * VALIDATIONS))
        return [f"model.scheduler.patience={patience}", "+model.scheduler.interval=validation"]
    if spec["name"] in ("cosine", "onecycle") or "fractions" in spec:
        return []  # already spans the run
    raise ConfigError(f"{cfg.model.network._target_}: no budget mapping for schedule {spec}")


#: Address space a probed step may use: half the machine's 24 GiB, so that two runs and the rest fit beside it.
PROBE_MEMORY_BYTES = 12 * 2**30


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (PROBE_MEMORY_BYTES, PROBE_MEMORY_BYTES))


def probe_step_seconds(model: str, width: float, batch: int) -> float:
    """:func:`time_step` in a child process (one thread, at most :data:`PROBE_MEMORY_BYTES`), so that a step
    too large for the memory is measured as ``inf`` rather than taking the planner (or a run) down with it."""
    code = (f"from benchmarks.studies.cpu_budget.budget import time_step; print(time_step({model!r}, {width!r}, {batch!r}))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            env={**os.environ, **CPU_TRAINING_ENV}, preexec_fn=_limit_memory)
    if result.returncode != 0:
        return math.inf
    return float(result.stdout.strip().splitlines()[-1])


def time_step(model: str, width: float, batch: int, steps: int = 2) -> float:
    """CPU seconds of one training step (forward, loss, backward, Adam) of ``model`` at ``width``, one
    thread, fresh weights, ``batch`` pairs of :data:`PROBE_POINTS` points; the first step is not timed."""
    import torch
    import torch.nn.functional as F

    from benchmarks.speed.train_step import build_network, pair_batch

    torch.set_num_threads(1)
    torch.manual_seed(0)
    network = build_network(model, width, []).train()
    data = pair_batch(batch, PROBE_POINTS, torch.device("cpu"))
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-4)

    def loss() -> torch.Tensor:
        if model == CLASSIFIER:
            return F.cross_entropy(network(data["points_ref"]), torch.arange(batch) % 2)
        return network.loss(network(data["points_src"], data["points_ref"], data["transform_gt"]), data["transform_gt"])["loss"]

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        loss().backward()
        optimizer.step()

    step()
    start = time.process_time()
    for _ in range(steps):
        step()
    return (time.process_time() - start) / steps


@dataclass
class Stage:
    """One ``src.train`` run of a method's budget: its model, width, batch, steps and overrides."""

    name: str
    model: str
    width: float
    batch: int
    step_cpu_s: float
    budget_cpu_h: float
    max_steps: int
    overrides: list[str] = field(default_factory=list)
    planned_steps: int | None = None   # the probe's plan, where :func:`extend_plan` re-planned ``max_steps``

    @property
    def val_every(self) -> int:
        return max(1, self.max_steps // VALIDATIONS)


def _steps_for(seconds: float, step_s: float) -> int:
    return int(seconds / (step_s * OVERHEAD))


def plan_method(method: str, budget_h: float, protocol: str = "real_airplane", probe=probe_step_seconds) -> dict[str, Any]:
    """Width, batch, steps and schedule of ``method`` under ``budget_h`` CPU hours (see the module docstring)."""
    cfg = compose_recipe(method)
    batch = int(cfg.data.batch_size)
    probes: dict[str, float] = {}
    for width in WIDTHS:
        probes[str(width)] = probe(method, width, batch)
        if _steps_for(budget_h * 3600, probes[str(width)]) >= MIN_STEPS:
            break
    step_s = probes[str(width)]
    if not math.isfinite(step_s):
        raise ConfigError(f"{method}: no training step ran at width {width}, batch {batch} in "
                          f"{PROBE_MEMORY_BYTES / 2**30:.0f} GiB (out of memory?)")
    stages = []
    budget_s = budget_h * 3600
    if method == "pointnetlk":  # the classifier stage's share: the authors' epochs times the probed step costs
        cls = compose_recipe(CLASSIFIER)
        cls_batch = int(cls.data.batch_size)
        cls_step = probe(CLASSIFIER, width, cls_batch)
        cls_cost, lk_cost = cls.trainer.max_epochs * cls_step, cfg.trainer.max_epochs * step_s
        cls_s = budget_s * cls_cost / (cls_cost + lk_cost)
        stages.append(Stage("classifier", CLASSIFIER, width, cls_batch, cls_step, cls_s / 3600,
                            _steps_for(cls_s, cls_step), budget_schedule(cls)))
        budget_s -= cls_s
    stages.append(Stage(method, method, width, batch, step_s, budget_s / 3600, _steps_for(budget_s, step_s),
                        ([f"recipe={RECIPE_OF[method]}"] if method in RECIPE_OF else []) + budget_schedule(cfg)))
    return {"method": method, "protocol": protocol, "budget_cpu_h": budget_h, "width": width, "probe_step_cpu_s": probes,
            "stages": [vars(s) for s in stages], "code": code_version()}


#: The folder of a method's run beyond the equal budget, beside the method's own.
BEYOND = "_beyond"


def plan_beyond(method: str, recipe: str, budget_h: float, init_weights: str | None = None,
                protocol: str = "real_airplane", probe=probe_step_seconds) -> dict[str, Any]:
    """A run of ``method`` beyond the equal budget: ``recipe`` as it is (its width, batch and a schedule that spans
    the run), the steps ``budget_h`` buys at the probed step cost, optionally starting from ``init_weights`` (then at
    that checkpoint's width: a fine-tune goes on with the network it starts from)."""
    cfg = compose_recipe(method, recipe)
    width, batch = float(cfg.model_scale), int(cfg.data.batch_size)
    if init_weights:
        from src.run.checkpoint_io import read_checkpoint

        width = float(read_checkpoint(init_weights)["hyper_parameters"]["network"].get("width", width))
    step_s = probe(method, width, batch)
    if not math.isfinite(step_s):
        raise ConfigError(f"{method}: no training step ran at width {width}, batch {batch} (out of memory?)")
    overrides = [f"recipe={recipe}"] + ([f"init_weights={init_weights}"] if init_weights else [])
    stage = Stage(method, method, width, batch, step_s, budget_h, _steps_for(budget_h * 3600, step_s), overrides)
    return {"method": method, "protocol": protocol, "beyond": recipe, "budget_cpu_h": budget_h, "width": width,
            "probe_step_cpu_s": {str(width): step_s}, "stages": [vars(stage)], "code": code_version()}


def extend_plan(method_dir: Path) -> Stage:
    """Re-plan the last stage of the stopped run in ``method_dir`` to the steps its CPU-hour budget buys at the step
    cost the run measured (where the probe over-estimated it and the planned steps left budget unused): the steps
    trained plus the unused CPU time over the measured CPU seconds a step. The run goes on from its ``last.ckpt``
    when its command runs again, its schedule as it was (a milestone already passed stays passed)."""
    plan_file = method_dir / "plan.json"
    if not plan_file.is_file():
        raise ConfigError(f"{method_dir} has no plan.json: give the folder of a budget run")
    plan = json.loads(plan_file.read_text())
    stage = Stage(**plan["stages"][-1])
    run_dir = method_dir / stage.name
    logs = read_csv_logs(run_dir)
    done, used_s = steps_trained(run_dir, logs), logged_cpu_hours(logs) * 3600
    if done == 0 or used_s == 0:
        raise ConfigError(f"{run_dir} has logged no training yet: nothing to measure a step's cost on")
    step_s = used_s / done
    steps = done + int(max(0.0, stage.budget_cpu_h * 3600 - used_s) / step_s)
    if steps <= stage.max_steps:
        raise ConfigError(f"{run_dir}: its {stage.max_steps:,} planned steps already use its {stage.budget_cpu_h:g} "
                          f"CPU hours at the measured {step_s:.2f} CPU s a step: nothing to extend")
    extended = Stage(**{**vars(stage), "max_steps": steps, "step_cpu_s": step_s,
                        "planned_steps": stage.planned_steps or stage.max_steps})
    plan["stages"][-1] = vars(extended)
    plan_file.write_text(json.dumps(plan, indent=2))
    (run_dir / "done.json").unlink(missing_ok=True)
    return extended


def stage_command(stage: Stage, run_dir: Path, extra: list[str], protocol: str = "real_airplane") -> list[str]:
    """The ``src.train`` command line of one stage of ``protocol`` (resuming from its ``last.ckpt`` when there is one,
    then without the overrides that only start a run, such as ``init_weights``)."""
    data = PROTOCOLS[protocol].classifier if stage.model == CLASSIFIER else PROTOCOLS[protocol].experiment
    last = own_last_checkpoint(run_dir)
    resuming = last.is_file()
    overrides = [*stage.overrides, *extra]
    command = [sys.executable, "-m", "src.train", *data, *TRAINING, f"model={stage.model}", f"model_scale={stage.width}",
               f"data.batch_size={stage.batch}", f"trainer.max_steps={stage.max_steps}",
               f"trainer.val_check_interval={stage.val_every}", *(resumed_overrides(overrides) if resuming else overrides),
               f"callbacks.clock.budget_cpu_hours={stage.budget_cpu_h:.4f}",
               f"task_name=cpu_budget_{stage.name}", f"hydra.run.dir={run_dir}"]
    return command + ([f"ckpt_path={last}"] if resuming else [])


#: Planning composes configs (Hydra's global state) and times steps in this process: one method at a time.
_PLANNING = threading.Lock()


def run_method(method: str, root: Path, budget_h: float, folder: str | None = None,
               planner: Callable[[], dict[str, Any]] | None = None) -> str:
    """Plan (once: ``planner``, by default :func:`plan_method`), then train each stage of ``method`` to its steps
    (resuming) in ``root/<folder>`` (by default the method's name); a one-line status."""
    method_dir = root / (folder or method)
    method_dir.mkdir(parents=True, exist_ok=True)
    plan_file = method_dir / "plan.json"
    with _PLANNING:
        if not plan_file.is_file():
            plan = planner() if planner else plan_method(method, budget_h)
            plan_file.write_text(json.dumps(plan, indent=2))
    plan = json.loads(plan_file.read_text())
    extra: list[str] = []
    for stage in (Stage(**s) for s in plan["stages"]):
        run_dir = method_dir / stage.name
        run_dir.mkdir(exist_ok=True)
        done = run_dir / "done.json"
        if not done.is_file():
            command = stage_command(stage, run_dir, extra, plan.get("protocol", "real_airplane"))
            (run_dir / "command.txt").write_text(" ".join(command[1:]) + "\n")
            code = train_logged(run_dir, command)
            if code != 0:
                return f"{method_dir.name}/{stage.name}: exit {code} (see {run_dir / 'train.log'}; run again to resume)"
            done.write_text(json.dumps({"stage": vars(stage), "command": " ".join(command[1:])}, indent=2))
        extra = [f"model.network.feature_init={best_checkpoint(run_dir) or own_last_checkpoint(run_dir)}"]  # the next stage starts from these features
    return f"{method_dir.name}: done"


#: A stage's record: what ran (command, plan), its logs and its test metrics; checkpoints stay in the run folder,
#: but for an unfinished stage's (:func:`archive_runs`).
RECORD_FILES = ("command.txt", "done.json", "metrics.json")
#: What a checkpoint holds as numbers; the rest (its callbacks' state: the best checkpoint's path, the folder) may
#: name the run folder.
CHECKPOINT_TENSORS = ("state_dict", "optimizer_states")


def run_folders(root: Path) -> list[str]:
    """The run folders under ``root`` in the grid's order: each method's, then its run beyond the budget."""
    return [name for m in METHODS for name in (m, m + BEYOND) if (root / name / "plan.json").is_file()]


def _copy_record(source: Path, target: Path, root: Path) -> None:
    """A text record copied with ``root`` written as ``RUNS``: the repository names no path of this machine."""
    target.write_text(without_folder(source.read_text(), root, "RUNS"))


def _map_strings(obj: Any, change: Callable[[str], str]) -> Any:
    """``obj`` with ``change`` applied to every string in it, the keys of its mappings included."""
    if isinstance(obj, str):
        return change(obj)
    if isinstance(obj, dict):
        return {_map_strings(key, change): _map_strings(value, change) for key, value in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_map_strings(value, change) for value in obj)
    return obj


def _copy_checkpoint(source: Path, target: Path, change: Callable[[str], str], drop: Sequence[str] = ()) -> None:
    """A Lightning checkpoint copied with ``change`` applied to the strings of all but its tensors, less ``drop``."""
    import torch

    checkpoint = torch.load(source, map_location="cpu", weights_only=False)
    tensors = {key: checkpoint[key] for key in CHECKPOINT_TENSORS if key in checkpoint and key not in drop}
    rest = {key: value for key, value in checkpoint.items() if key not in CHECKPOINT_TENSORS and key not in drop}
    target.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(target, lambda tmp: torch.save({**_map_strings(rest, change), **tensors}, tmp))


def archive_runs(root: Path, out: Path, methods: Sequence[str] | None = None) -> list[str]:
    """Copy the record of each run folder (``methods``, by default all: :func:`run_folders`) under ``root`` into
    ``out`` (replacing its older copy)."""
    methods = run_folders(root) if methods is None else methods
    archived = []
    for method in methods:
        plan = root / method / "plan.json"
        if not plan.is_file():
            continue
        target = out / method
        if target.exists():
            shutil.rmtree(target)
        target.mkdir(parents=True)
        _copy_record(plan, target / "plan.json", root)
        for stage in json.loads(plan.read_text())["stages"]:
            run_dir, copy_dir = root / method / stage["name"], target / stage["name"]
            for log in run_dir.glob("csv/version_*/metrics.csv"):
                (copy_dir / log.parent.relative_to(run_dir)).mkdir(parents=True, exist_ok=True)
                shutil.copy2(log, copy_dir / log.relative_to(run_dir))
            for name in RECORD_FILES:
                if (run_dir / name).is_file():
                    copy_dir.mkdir(parents=True, exist_ok=True)
                    _copy_record(run_dir / name, copy_dir / name, root)
            if not (run_dir / "done.json").is_file():
                _archive_checkpoints(run_dir, copy_dir, root)
        archived.append(method)
    if not archived:
        raise ConfigError(f"no method run under {root}: nothing to archive")
    return archived


def _archive_checkpoints(run_dir: Path, copy_dir: Path, root: Path) -> None:
    """What an unfinished stage goes on from on another machine: its ``last.ckpt`` and its best checkpoints so far
    (without the optimiser's state), ``root`` written as ``RUNS`` (:func:`restore_runs` writes it back)."""
    last = own_last_checkpoint(run_dir)
    if not last.is_file():
        return
    change = lambda text: without_folder(text, root, "RUNS")
    _copy_checkpoint(last, copy_dir / last.relative_to(run_dir), change)
    for best in last.parent.glob("best-*.ckpt"):
        _copy_checkpoint(best, copy_dir / "checkpoints" / best.name, change, drop=("optimizer_states",))


def restore_runs(archive: Path, root: Path) -> tuple[list[str], list[str]]:
    """Copy the archived runs (:func:`archive_runs`) into ``root``, ``RUNS`` written as ``root``, so that each
    unfinished one goes on from its checkpoints as it would have where it ran. A run folder ``root`` already has is
    left as it is. Returns the folders restored and those kept."""
    restored, kept = [], []
    change = lambda text: with_folder(text, root, "RUNS")
    for method in run_folders(archive):
        target = root / method
        if (target / "plan.json").is_file():
            kept.append(method)
            continue
        for source in sorted(p for p in (archive / method).rglob("*") if p.is_file()):
            copy = target / source.relative_to(archive / method)
            copy.parent.mkdir(parents=True, exist_ok=True)
            if source.suffix == ".ckpt":
                _copy_checkpoint(source, copy, change)
            elif source.suffix == ".csv":
                shutil.copy2(source, copy)
            else:
                copy.write_text(change(source.read_text()))
        restored.append(method)
    if not restored and not kept:
        raise ConfigError(f"no archived run under {archive}: give the folder `archive` wrote")
    return restored, kept


def ship_note(method_dir: Path, compute: str) -> str:
    """The note of a shipped checkpoint of the run in ``method_dir``: its protocol, each stage's steps, batch, width
    and the CPU hours it was planned and used, where it started from, how its weights were chosen, on ``compute``."""
    plan = json.loads((method_dir / "plan.json").read_text())
    stages = [Stage(**s) for s in plan["stages"]]

    def planned(stage: Stage) -> str:
        if stage.planned_steps is None:
            return "from a probe of its step cost"
        return (f"from a probe of its step cost ({stage.planned_steps:,} steps), then from the step cost the run "
                f"measured ({stage.step_cpu_s:.2f} CPU s a step)")

    parts = [f"{stage.model}: {stage.max_steps:,} steps x batch {stage.batch} at width {stage.width:g}, planned for a "
             f"{stage.budget_cpu_h:.3g}-CPU-hour budget {planned(stage)}, "
             f"{logged_cpu_hours(read_csv_logs(method_dir / stage.name)):.2f} CPU hours used with validation" for stage in stages]
    start = next((o.split("=", 1)[1] for o in stages[0].overrides if o.startswith("init_weights=")), None)
    recipe = f"recipe {plan['beyond']}" if "beyond" in plan else "its authors' recipe on the steps the budget buys"
    results = json.loads((method_dir / stages[-1].name / "metrics.json").read_text())
    return (f"{PROTOCOLS[plan['protocol']].description}. Trained by benchmarks/studies/cpu_budget ({recipe}; "
            f"{'; '.join(parts)}), {'starting from ' + Path(start).name if start else 'from scratch'}, one torch "
            f"thread, {results['trained_precision']}, on {compute}. Weights: "
            f"{results['tested_weights'].replace(results['checkpoint'], Path(results['checkpoint']).name)}.")


def ship(method_dir: Path, name: str, compute: str) -> Path:
    """Export the last stage of the finished run in ``method_dir`` as ``checkpoints/<name>`` (float16 weights) with
    its card and :func:`ship_note`."""
    from src.models.pretrained import export

    plan = json.loads((method_dir / "plan.json").read_text())
    run_dir = method_dir / plan["stages"][-1]["name"]
    if not (run_dir / "done.json").is_file():
        raise ConfigError(f"{run_dir} has not finished (no done.json): run it to the end first")
    return export(run_dir, name, note=ship_note(method_dir, compute), half=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.cpu_budget.budget", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = add_run_parser(sub, "methods", METHODS, ("--budget-h", 1.0, "CPU hours"), parallel=2)
    run.add_argument("--protocol", choices=sorted(PROTOCOLS), default="real_airplane", help="the data it trains on")
    run.add_argument("--archive", type=Path, default=None,
                     help="archive each method's record here when its run returns (e.g. benchmarks/studies/cpu_budget/results/runs)")
    beyond = sub.add_parser("beyond", help="train one method beyond the budget with a recipe (resumable)")
    beyond.add_argument("--root", type=Path, required=True, help="folder of the runs (outside the repository)")
    beyond.add_argument("--method", required=True, choices=METHODS)
    beyond.add_argument("--recipe", required=True, help="conf/recipe/<name>.yaml, taken as it is (e.g. omnet_cpu)")
    beyond.add_argument("--budget-h", type=float, required=True, help="CPU hours of this run, one thread")
    beyond.add_argument("--init-weights", default=None, help="start from this checkpoint's weights, at its width (src.train init_weights)")
    beyond.add_argument("--archive", type=Path, default=None, help="archive the run's record here when it returns")
    beyond.add_argument("--protocol", choices=sorted(PROTOCOLS), default="real_airplane", help="the data it trains on")
    arc = sub.add_parser("archive", help="copy the runs' records (and what an unfinished run goes on from) into the "
                                         "repository")
    arc.add_argument("--root", type=Path, required=True)
    arc.add_argument("--out", type=Path, default=Path("benchmarks/studies/cpu_budget/results/runs"))
    restoring = sub.add_parser("restore", help="copy archived runs into a folder of runs (on another machine), to go on")
    restoring.add_argument("--archive", type=Path, required=True, help="the folder `archive` wrote")
    restoring.add_argument("--root", type=Path, required=True, help="folder of the runs (outside the repository)")
    extending = sub.add_parser("extend", help="re-plan a stopped run's steps to its budget at its measured step cost")
    extending.add_argument("--root", type=Path, required=True)
    extending.add_argument("--folder", required=True, help="the run's folder under --root (e.g. omnet_beyond)")
    shipping = sub.add_parser("ship", help="export a finished run as a shipped checkpoint with its card")
    shipping.add_argument("--root", type=Path, required=True)
    shipping.add_argument("--folder", required=True, help="the run's folder under --root (e.g. fmr, omnet_beyond)")
    shipping.add_argument("--name", required=True, help="checkpoints/<name>.ckpt, e.g. fmr_unseen_categories_modelnet40_npy_os_prnet")
    shipping.add_argument("--compute", required=True, help="what it trained on, for the card, e.g. '2-core AMD EPYC Zen 3'")
    args = parser.parse_args(argv)

    def action() -> None:
        if args.command == "ship":
            print(f"wrote {ship(args.root / args.folder, args.name, args.compute)} and its card")
            return
        if args.command == "extend":
            stage = extend_plan(args.root / args.folder)
            print(f"{args.folder}/{stage.name}: {stage.max_steps:,} steps (planned {stage.planned_steps:,}) at the "
                  f"measured {stage.step_cpu_s:.2f} CPU s a step; run its command again to go on")
            return
        if args.command == "archive":
            print(f"archived {', '.join(archive_runs(args.root, args.out))} into {args.out}")
            return
        if args.command == "restore":
            restored, kept = restore_runs(args.archive, args.root)
            print(f"restored {', '.join(restored) or 'nothing'} into {args.root}"
                  + (f"; kept the runs already there: {', '.join(kept)}" if kept else ""))
            return
        if args.command == "beyond":
            folder = args.method + BEYOND
            planner = lambda: plan_beyond(args.method, args.recipe, args.budget_h, args.init_weights, args.protocol)
            run_each(args.method, METHODS, "methods", ("--budget-h", args.budget_h), 1,
                     lambda m: run_method(m, args.root, args.budget_h, folder, planner))
            if args.archive is not None:
                archive_runs(args.root, args.archive, [folder])
            return
        def run_one(method: str) -> str:
            status = run_method(method, args.root, args.budget_h,
                                planner=lambda: plan_method(method, args.budget_h, args.protocol))
            if args.archive is not None:
                archive_runs(args.root, args.archive, [method])
            return status

        run_each(args.methods, METHODS, "methods", ("--budget-h", args.budget_h), args.parallel, run_one)

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
