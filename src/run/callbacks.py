"""Training callbacks beyond Lightning's own."""

from __future__ import annotations

import random
import statistics
import time
from typing import Any

import lightning as L
import numpy as np
import torch

from src.utils.machine_speed import MatmulReference


class RngState(L.Callback):
    """Save the global RNG states (Python, NumPy, torch CPU and CUDA) in each checkpoint and restore
    them on resume, so stochastic training steps (e.g. PRNet's Gumbel noise) continue exactly as in
    the uninterrupted run. Pair generation does not need this: it is seeded per sample index.

    The states are applied at the first training batch after the restore, not when the checkpoint
    is read: Lightning may first finish a validation the checkpoint interrupted (PRNet's evaluation
    draws noise too), which the uninterrupted run had done before the states were saved.
    """

    def __init__(self) -> None:
        self._pending: dict[str, Any] | None = None

    def state_dict(self) -> dict[str, Any]:
        kind, keys, pos, has_gauss, gauss = np.random.get_state()
        # plain types and tensors only, so Lightning's weights-only checkpoint loading accepts them
        state = {"python": random.getstate(), "numpy": (kind, torch.from_numpy(keys.astype(np.int64)), pos,
                                                         has_gauss, gauss), "torch": torch.get_rng_state()}
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            state["cuda"] = torch.cuda.get_rng_state_all()
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._pending = state_dict

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        if self._pending is not None:
            set_rng_states(self._pending)
            self._pending = None


def set_rng_states(state_dict: dict[str, Any]) -> None:
    """Apply states from :meth:`RngState.state_dict`."""
    random.setstate(state_dict["python"])
    kind, keys, pos, has_gauss, gauss = state_dict["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(state_dict["torch"])
    if "cuda" in state_dict and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state_dict["cuda"])


class TrainingClock(L.Callback):
    """Log the training's cumulative cost as ``time/cpu_hours`` (this process's CPU time: every torch
    thread and in-process data loading) and ``time/wall_hours``, carried over resumes in the
    checkpoint, so learning curves can be drawn against compute rather than steps. Validation during
    fit is not training: its CPU time is counted apart, as ``time/eval_cpu_hours``.

    CPU time is the fair axis on a shared machine (wall time stretches with other load); with
    ``data.num_workers=0`` it includes pair generation. ``budget_cpu_hours`` stops training once the
    training CPU time reaches it (a budget, whatever the step count). A CPU hour buys less on a loaded
    machine, so on the CPU each validation also logs ``time/mm_gflops``, the process's ``torch.mm`` rate
    (:class:`~src.utils.machine_speed.MatmulReference`, CPU clock; median of ``mm_probes``, 0: off), counted as
    evaluation time.
    """

    def __init__(self, budget_cpu_hours: float | None = None, mm_probes: int = 3) -> None:
        self.budget_cpu_hours = budget_cpu_hours
        self.mm_probes = mm_probes
        self._mm: MatmulReference | None = None
        self.mm_gflops: float | None = None
        self.cpu_seconds = 0.0
        self.wall_seconds = 0.0
        self.eval_cpu_seconds = 0.0
        self._mark: tuple[float, float] | None = None
        self._evaluating = False

    def state_dict(self) -> dict[str, float]:
        self._tick()
        return {"cpu_seconds": self.cpu_seconds, "wall_seconds": self.wall_seconds,
                "eval_cpu_seconds": self.eval_cpu_seconds}

    def load_state_dict(self, state_dict: dict[str, float]) -> None:
        self.cpu_seconds, self.wall_seconds = state_dict["cpu_seconds"], state_dict["wall_seconds"]
        self.eval_cpu_seconds = state_dict.get("eval_cpu_seconds", 0.0)  # (checkpoints before it was counted apart)

    def _tick(self) -> None:
        now = (time.process_time(), time.perf_counter())
        if self._mark is not None:
            if self._evaluating:
                self.eval_cpu_seconds += now[0] - self._mark[0]
            else:
                self.cpu_seconds += now[0] - self._mark[0]
                self.wall_seconds += now[1] - self._mark[1]
        self._mark = now

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._mark = (time.process_time(), time.perf_counter())

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._tick()
        self._mark = None

    def _fitting(self, trainer: L.Trainer) -> bool:
        return not trainer.sanity_checking and trainer.state.fn == "fit" and self._mark is not None

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._fitting(trainer):
            self._tick()
            self._evaluating = True
            if self.mm_probes > 0 and getattr(getattr(pl_module, "device", None), "type", None) == "cpu":
                self._mm = self._mm or MatmulReference("cpu", clock="cpu")
                self.mm_gflops = statistics.median(self._mm.rate() for _ in range(self.mm_probes))

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._fitting(trainer):
            self._tick()
            self._evaluating = False

    def _log(self, pl_module: L.LightningModule) -> None:
        self._tick()
        pl_module.log_dict({"time/cpu_hours": self.cpu_seconds / 3600, "time/wall_hours": self.wall_seconds / 3600,
                            "time/eval_cpu_hours": self.eval_cpu_seconds / 3600})

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int) -> None:
        if (trainer.global_step % trainer.log_every_n_steps) == 0:
            self._log(pl_module)
        if self.budget_cpu_hours is not None:
            self._tick()
            if self.cpu_seconds >= self.budget_cpu_hours * 3600:
                trainer.should_stop = True

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._fitting(trainer):
            self._log(pl_module)
            if self.mm_gflops is not None:
                pl_module.log("time/mm_gflops", self.mm_gflops)
