"""What a training run tells its user before and while it trains.

* :func:`require_prepared_paper_data`: the paper's experiments (``+exp=unseen_shapes|unseen_categories|
  gaussian_noise``) run on ModelNet40 (``conf/exp/*.yaml``); with no ModelNet40 cache the run stops
  before anything is built, in one line naming both ways forward: prepare it, or the embedded synthetic
  data with a CPU-sized recipe.
* :class:`TrainingForecast` (``conf/callbacks/default.yaml``): one line when training starts (the data
  and whether it is synthetic, the model's size, steps x batch, the device, the precision and why: the verdict used
  and where it was measured, or that there is none, :mod:`src.run.precision`; the run dir), and after the
  first ``after_steps`` optimiser steps the measured seconds per step and the time of the rest on this
  machine; a schedule of more than ``long_hours`` on a CPU also says how to choose a CPU-sized one.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from src.config import usable_cores
from src.data.cache import default_cache_root
from src.utils.errors import DatasetError

#: The paper's dataset, which its experiments compose by default.
PAPER_DATASET = "modelnet40"
#: A CPU-sized recipe per network class (``conf/recipe/``); other networks get a shorter budget.
CPU_RECIPES = {"OMNet": "recipe=omnet_cpu"}
SHORTER_BUDGET = "trainer.max_steps=N data.batch_size=N"


def _command_overrides() -> list[str] | None:
    """The command line's overrides (None outside a Hydra app)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else None


def cpu_sized(network: str) -> str:
    """Overrides of a CPU-sized run of a network class (its ``conf/recipe/*_cpu.yaml``, else a shorter budget)."""
    return CPU_RECIPES.get(network, SHORTER_BUDGET)


def require_prepared_paper_data(cfg: DictConfig) -> None:
    """DatasetError (one line, both ways forward) if the run's data is ModelNet40 and it was never prepared."""
    if str(cfg.data.get("dataset")) != PAPER_DATASET:
        return
    root = Path(cfg.data.cache_root).expanduser() if cfg.data.get("cache_root") else default_cache_root()
    if (root / PAPER_DATASET / "manifest.json").is_file():
        return  # (a damaged cache is the datamodule's to report or rebuild)
    overrides = _command_overrides()
    kept = [o for o in overrides or [f"+exp={cfg.task_name}"] if not o.lstrip("+~").startswith(("data=", "recipe="))]
    network = str(cfg.model.network._target_).rsplit(".", 1)[-1]
    synthetic = " ".join(["python -m src.train", *kept, "data=synthetic", cpu_sized(network)])
    raise DatasetError(
        f"this run trains on ModelNet40 (the paper's data; the experiment's default), which is not prepared under "
        f"{root}: prepare it with `python -m src.data.prepare modelnet40 --source PATH/ModelNet40.zip` (or --download; "
        f"docs/data.md: Data), or try the pipeline on the embedded synthetic data with a CPU-sized run: `{synthetic}`"
    )


def format_duration(seconds: float) -> str:
    """``42 s``, ``3.5 min``, ``2.1 h``, ``15 days``, ``2.3 years``."""
    for unit, size, limit in (("s", 1, 90), ("min", 60, 90 * 60), ("h", 3600, 48 * 3600), ("days", 86400, 730 * 86400)):
        if seconds < limit:
            value = seconds / size
            return f"{value:.0f} {unit}" if value >= 10 or unit == "s" else f"{value:.1f} {unit}"
    return f"{seconds / (365 * 86400):.1f} years"


def say(text: str) -> None:
    """Print ``text`` above any progress bar (not into its line), flushed (a redirected stdout keeps the order)."""
    tqdm.write(text, file=sys.stdout)
    sys.stdout.flush()


def _device(trainer: L.Trainer) -> str:
    device = trainer.strategy.root_device
    if device.type == "cpu":
        cores, threads = usable_cores(), torch.get_num_threads()
        return f"cpu ({cores} core{'s' * (cores != 1)}, {threads} torch thread{'s' * (threads != 1)})"
    return torch.cuda.get_device_name(device) if device.type == "cuda" else str(device)


def _precision(trainer: L.Trainer) -> str:
    choice = getattr(trainer, "precision_choice", None)  # src.run.trainer.build_trainer's
    return f"precision {trainer.precision}" + (f" ({choice.reason})" if choice is not None else "")


def start_line(trainer: L.Trainer, module: L.LightningModule) -> str:
    """``train: <data> | <model> | <steps> x batch <b> on <device> | precision <p> (<why>) | run dir <dir>``."""
    datamodule = trainer.datamodule
    dataset = str(getattr(datamodule, "dataset", "?"))
    data = f"{dataset} data" + (" (SYNTHETIC procedural shapes, not ModelNet40)" if dataset == "synthetic" else "")
    train_set = getattr(datamodule, "datasets", {}).get("train")
    if train_set is not None:
        data += f", {len(train_set):,} training shapes"
    network = getattr(module, "network", module)
    width = dict(module.hparams.get("network") or {}).get("width")
    parameters = sum(p.numel() for p in module.parameters())
    model = f"{type(network).__name__} {parameters / 1e6:.2f} M parameters" + (f" (width {width:g})" if width else "")
    processes = f" x {trainer.world_size} processes" if trainer.world_size > 1 else ""
    steps = trainer.estimated_stepping_batches
    budget = f"{'unlimited' if math.isinf(steps) else f'{int(steps):,}'} steps x batch {getattr(datamodule, 'batch_size', '?')}{processes}"
    resumed = f" (resuming at step {trainer.global_step:,})" if trainer.global_step else ""
    return (f"train: {data} | {model} | {budget}{resumed} on {_device(trainer)} | {_precision(trainer)} | "
            f"run dir {trainer.default_root_dir}")


class TrainingForecast(L.Callback):
    """The start line, then after ``after_steps`` optimiser steps the measured time per step and the
    projected time of the remaining steps (training only: validations come on top); see the module
    docstring. The first step (warm-up) and time spent validating are not measured."""

    def __init__(self, after_steps: int = 10, long_hours: float = 24.0) -> None:
        self.after_steps, self.long_hours = after_steps, long_hours
        self._first: tuple[int, float] | None = None
        self._paused, self._pause_start, self._done = 0.0, 0.0, False

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._first, self._paused, self._done = None, 0.0, False
        if trainer.is_global_zero:
            say(start_line(trainer, pl_module))

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._pause_start = time.perf_counter()

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._paused += time.perf_counter() - self._pause_start

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        if self._done:
            return
        step, now = trainer.global_step, time.perf_counter()
        if self._first is None:
            self._first, self._paused = (step, now), 0.0
            return
        steps = step - self._first[0]
        if steps < self.after_steps:
            return
        self._done = True
        if trainer.is_global_zero:
            seconds = (now - self._first[1] - self._paused) / steps
            say(self.forecast(trainer, pl_module, seconds))

    def forecast(self, trainer: L.Trainer, pl_module: L.LightningModule, seconds_per_step: float) -> str:
        """The estimate line for ``seconds_per_step`` measured now."""
        measured = (f"train: {seconds_per_step:.2f} s/step measured over steps {trainer.global_step - self.after_steps + 1}-"
                    f"{trainer.global_step}")
        if math.isinf(trainer.estimated_stepping_batches):
            return (f"{measured}: no step limit (trainer.max_steps=-1, trainer.max_epochs=-1): training runs until "
                    "trainer.max_time, callbacks.clock.budget_cpu_hours or a signal stops it")
        total = int(trainer.estimated_stepping_batches)
        remaining = max(total - trainer.global_step, 0)
        line = (f"{measured}: the remaining {remaining:,} steps take ~{format_duration(remaining * seconds_per_step)} "
                "on this machine (validation extra)")
        if trainer.strategy.root_device.type == "cpu" and total * seconds_per_step > self.long_hours * 3600:
            advice = cpu_sized(type(getattr(pl_module, "network", pl_module)).__name__)
            advice += "" if "trainer.max_steps" in advice else " trainer.max_steps=N"
            line += (f"\ntrain: {total:,} steps would take ~{format_duration(total * seconds_per_step)} on this CPU: for a "
                     f"CPU-sized run add `{advice}` (docs/results.md: Expected runtimes), or train "
                     "on a GPU (trainer=gpu)")
        return line
