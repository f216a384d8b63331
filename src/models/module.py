"""One LightningModule that trains and evaluates any registration network."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import hydra
import lightning as L
import torch
from torch import Tensor, nn
from torch.optim import Optimizer
from torch.optim.lr_scheduler import (
    LambdaLR,
    MultiStepLR,
    OneCycleLR,
    ReduceLROnPlateau,
)
from torchmetrics import MeanMetric

from src.metrics import METRIC_NAMES, SCORE, RegistrationMetrics
from src.models.base import check_network
from src.models.fp32_regions import keep_fp32
from src.utils.config_values import plain
from src.utils.errors import ConfigError, DivergenceError

#: Lightning's learning-rate scheduler config (``scheduler``, ``interval``, ``monitor``).
SchedulerConfig = dict[str, Any]
#: The number of optimiser steps of the whole run (asked only by schedules that need it).
TotalSteps = Callable[[], int]


def _evaluate_calls(network: dict[str, Any]) -> dict[str, Any]:
    """Arguments given as calls (``{_target_: fn, ...}``, e.g. FMR's decoder size from ``data.pair``)
    replaced by their values, so that the checkpoint's network config holds plain numbers."""
    return {key: hydra.utils.instantiate(value) if isinstance(value, dict) and "_target_" in value else value
            for key, value in network.items()}


def multistep(optimizer: Optimizer, total_steps: TotalSteps, milestones: Sequence[int] = (), gamma: float = 0.1,
              interval: str = "step", fractions: Sequence[float] = ()) -> SchedulerConfig:
    """×``gamma`` at each milestone, counted in optimiser steps or in epochs (``interval``): epochs
    follow the dataset actually used, as the authors' epoch schedules do. ``fractions`` instead puts the
    milestones at those fractions of the run's optimiser steps, so the decay follows any budget."""
    if interval not in ("step", "epoch"):
        raise ConfigError(f"model.scheduler.interval must be step or epoch, got {interval!r}")
    if fractions:
        if milestones or interval != "step":
            raise ConfigError("model.scheduler: give milestones or fractions (of the run's steps, interval step), not both")
        if not all(0 < f < 1 for f in fractions):
            raise ConfigError(f"model.scheduler.fractions must lie in (0, 1), got {list(fractions)}")
        milestones = [max(1, round(f * total_steps())) for f in fractions]
    return {"scheduler": MultiStepLR(optimizer, list(milestones), gamma), "interval": interval}


#: Lightning frequency of a schedule that the module steps itself (never reached by Lightning's own stepping).
NEVER = 2**62


def plateau(optimizer: Optimizer, total_steps: TotalSteps, monitor: str = "val/loss", factor: float = 0.1,
            patience: int = 10, min_lr: float = 0.0, interval: str = "epoch") -> SchedulerConfig:
    """×``factor`` when ``monitor`` (lower is better) has not improved for more than ``patience``
    epochs, stepped once per epoch after its validation; ``interval: validation`` counts ``patience``
    in validations instead and steps after each one (runs validated every N steps, whose epochs are
    not the authors')."""
    if interval not in ("epoch", "validation"):
        raise ConfigError(f"model.scheduler plateau interval must be epoch or validation, got {interval!r}")
    scheduler = ReduceLROnPlateau(optimizer, mode="min", factor=factor, patience=patience, min_lr=min_lr)
    if interval == "validation":  # stepped by RegistrationModule.on_validation_epoch_end; Lightning saves its state
        return {"scheduler": scheduler, "interval": "epoch", "frequency": NEVER, "monitor": monitor, "strict": False}
    return {"scheduler": scheduler, "interval": "epoch", "monitor": monitor}


@dataclass
class WarmupCosine:
    """Learning-rate factor of step ``k``: linear warm-up to 1 over ``warmup_steps``, then a cosine
    down to ``final_factor`` at ``total_steps``."""

    warmup_steps: int
    total_steps: int
    final_factor: float

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            return (step + 1) / self.warmup_steps
        progress = min(1.0, (step - self.warmup_steps) / max(1, self.total_steps - self.warmup_steps))
        return self.final_factor + (1.0 - self.final_factor) * 0.5 * (1.0 + math.cos(math.pi * progress))


def cosine(optimizer: Optimizer, total_steps: TotalSteps, warmup_steps: int = 0,
           min_lr: float = 0.0) -> SchedulerConfig:
    """Linear warm-up over ``warmup_steps``, then cosine annealing to ``min_lr`` at the end of the run."""
    factor = WarmupCosine(warmup_steps, total_steps(), min_lr / optimizer.defaults["lr"])
    return {"scheduler": LambdaLR(optimizer, factor), "interval": "step"}


def onecycle(optimizer: Optimizer, total_steps: TotalSteps, pct_start: float = 0.3, div_factor: float = 25.0,
             final_div_factor: float = 1e4) -> SchedulerConfig:
    """PyTorch's one-cycle over the run: lr/``div_factor`` up to lr during ``pct_start`` of it, then
    down to lr/(``div_factor``·``final_div_factor``) (Adam's β₁ cycles too, PyTorch's default)."""
    scheduler = OneCycleLR(optimizer, max_lr=optimizer.defaults["lr"], total_steps=total_steps(), pct_start=pct_start,
                           div_factor=div_factor, final_div_factor=final_div_factor)
    return {"scheduler": scheduler, "interval": "step"}


#: ``model.scheduler.name`` -> builder; the other keys of ``model.scheduler`` are its keyword arguments.
SCHEDULERS: dict[str, Callable[..., SchedulerConfig]] = {
    "multistep": multistep, "plateau": plateau, "cosine": cosine, "onecycle": onecycle}


def check_scheduler(spec: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """``model.scheduler`` as a plain dict, checked (ConfigError naming the choices); None = constant lr."""
    if spec is None:
        return None
    spec = dict(spec)
    builder = SCHEDULERS.get(spec.get("name"))
    if builder is None:
        raise ConfigError(f"model.scheduler.name must be one of {sorted(SCHEDULERS)}, got {spec.get('name')!r}")
    options = {k: v for k, v in spec.items() if k != "name"}
    signature = inspect.signature(builder)
    try:
        signature.bind(None, None, **options)
    except TypeError as err:
        allowed = list(signature.parameters)[2:]
        raise ConfigError(
            f"model.scheduler {spec['name']} takes {allowed}, got {sorted(options)} ({err}); to switch schedulers, "
            "replace the whole block: ~model.scheduler '+model.scheduler={name: cosine, warmup_steps: 500}'"
        ) from None
    return spec


def refuse_non_finite(losses: dict[str, Tensor], step: int, lr: float) -> None:
    """Stop a run whose loss is not finite, before its optimiser step writes NaN into the weights (one line:
    the step, the terms, what to do; the checkpoints written before stay)."""
    if bool(torch.isfinite(losses["loss"])):
        return
    ordered = sorted(losses.items(), key=lambda item: item[0] != "loss")  # the total first
    terms = ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in ordered)
    raise DivergenceError(f"training diverged at step {step}: the loss is not finite ({terms}); resume from the run's "
                          f"last checkpoint with a lower model.lr (now {lr:g}) or trainer.gradient_clip_val=1.0")


class RegistrationModule(L.LightningModule):
    """Wraps a network (see :mod:`src.models.base`) with its loss, the paper's metrics, Adam and a
    learning-rate schedule.

    ``network`` is the Hydra config of the network (``_target_`` + arguments), stored in the
    checkpoint so :meth:`load_from_checkpoint` rebuilds it without the original config.
    ``scheduler`` is ``{name: <one of SCHEDULERS>, **its arguments}`` or None (constant lr). Each
    method's optimiser, schedule, batch, budget and checkpoint selection come from its recipe,
    ``conf/recipe/<model>.yaml`` (docs/recipes.md). ``lr_milestones``/``lr_gamma`` (step milestones)
    are what checkpoints and model configs written before the recipes hold. ``fp32_modules``: the network's
    submodules (``fnmatch`` patterns of their names) that run in float32 under bf16 autocast
    (:func:`src.models.fp32_regions.keep_fp32`).
    """

    #: What each validation logs, that a checkpoint can be selected on (``callbacks.checkpoint.monitor``).
    VALIDATION_METRICS: tuple[str, ...] = ("val/loss", *(f"val/{name}" for name in METRIC_NAMES), "val_score")

    def __init__(
        self,
        network: Mapping[str, Any],
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        scheduler: Mapping[str, Any] | None = None,
        euler_seq: str = "zyx",
        compile: bool = False,
        lr_milestones: Sequence[int] | None = None,
        lr_gamma: float = 0.1,
        fp32_modules: Sequence[str] = (),
    ) -> None:
        super().__init__()
        network = _evaluate_calls(plain(network))
        scheduler = check_scheduler(plain(scheduler))
        if lr_milestones is not None:
            if scheduler is not None:
                raise ConfigError("give model.scheduler or the older model.lr_milestones/lr_gamma, not both")
            scheduler = {"name": "multistep", "milestones": list(lr_milestones), "gamma": lr_gamma, "interval": "step"}
        self.save_hyperparameters({"network": network, "lr": lr, "weight_decay": weight_decay, "scheduler": scheduler,
                                   "euler_seq": euler_seq, "compile": compile})
        self.network: nn.Module = check_network(hydra.utils.instantiate(network), network["_target_"])
        if fp32_modules:
            try:
                keep_fp32(self.network, list(fp32_modules))
            except ValueError as err:
                raise ConfigError(f"model.{err}") from None
            self.hparams["fp32_modules"] = list(fp32_modules)
        self.val_metrics = RegistrationMetrics(euler_seq)
        self.test_metrics = RegistrationMetrics(euler_seq)
        # Eval losses as sum-reduced metrics: Lightning's own sync_dist mean truncates the (integer)
        # pair count when it averages it across gloo ranks, skewing the loss for odd totals.
        self.eval_losses = nn.ModuleDict({"val": MeanMetric(), "test": MeanMetric()})
        self.test_results: dict[str, float] = {}

    @property
    def network_target(self) -> str:
        return self.hparams["network"]["_target_"]

    def configure_model(self) -> None:
        if self.hparams["compile"] and not isinstance(self.network, torch._dynamo.eval_frame.OptimizedModule):
            self.network = torch.compile(self.network)

    def _normals(self, normals_src: Tensor | None, normals_ref: Tensor | None) -> dict[str, Tensor | None]:
        """The normals keywords for a network that uses them (``uses_normals``), else none."""
        if getattr(self.network, "uses_normals", False):
            return {"normals_src": normals_src, "normals_ref": normals_ref}
        return {}

    def _run(self, batch: dict[str, Tensor]) -> dict:
        """The network on a batch, with the ground truth (supervision signals) and its normals if it uses them."""
        normals = self._normals(batch.get("normals_src"), batch.get("normals_ref"))
        return self.network(batch["points_src"], batch["points_ref"], batch["transform_gt"], **normals)

    def forward(self, points_src: Tensor, points_ref: Tensor, normals_src: Tensor | None = None,
                normals_ref: Tensor | None = None) -> Tensor:
        """Final source→reference transform (B,4,4)."""
        return self.network(points_src, points_ref, **self._normals(normals_src, normals_ref))["transforms"][-1]

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        outputs = self._run(batch)
        losses = self.network.loss(outputs, batch["transform_gt"])
        refuse_non_finite(losses, self.global_step, self.hparams.lr)
        self.log_dict({f"train/{k}": v.detach() for k, v in losses.items()}, prog_bar=False, batch_size=batch["points_src"].shape[0])
        self.log("train_loss", losses["loss"].detach(), prog_bar=True, logger=False)
        return losses["loss"]

    def _evaluate(self, batch: dict[str, Tensor], metrics: RegistrationMetrics, prefix: str) -> dict:
        outputs = self._run(batch)
        losses = self.network.loss(outputs, batch["transform_gt"])
        batch_size = batch["points_src"].shape[0]
        self.eval_losses[prefix].update(losses["loss"].detach(), weight=batch_size)
        self.log(f"{prefix}/loss", self.eval_losses[prefix], on_step=False, on_epoch=True, batch_size=batch_size)
        metrics.update(outputs["transforms"][-1].float(), batch["transform_gt"], batch["points_src"], batch["points_ref"],
                       batch.get("points_raw"))
        return outputs

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, self.val_metrics, "val")

    def on_validation_epoch_end(self) -> None:
        values = self.val_metrics.compute()
        self.log_dict({f"val/{k}": v for k, v in values.items()}, prog_bar=False)
        self.log("val_score", values[SCORE], prog_bar=True, logger=False)
        self.val_metrics.reset()
        self._step_plateau_per_validation({"val/loss": self.eval_losses["val"].compute(),
                                           **{f"val/{k}": v for k, v in values.items()}})

    def _step_plateau_per_validation(self, values: Mapping[str, Tensor]) -> None:
        """Step a ``plateau`` schedule with ``interval: validation`` on this validation's monitored value."""
        spec = self.hparams["scheduler"]
        if not spec or spec["name"] != "plateau" or spec.get("interval") != "validation":
            return
        if self.trainer.sanity_checking or self.trainer.state.fn != "fit":
            return
        monitor = spec.get("monitor", "val/loss")
        if monitor not in values:
            raise ConfigError(f"model.scheduler plateau monitors {monitor!r}; validation logs {sorted(values)}")
        self.lr_schedulers().step(float(values[monitor]))

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> dict:
        """The network's outputs on the batch (for callbacks: the wandb per-pair table)."""
        return self._evaluate(batch, self.test_metrics, "test")

    def on_test_epoch_end(self) -> None:
        self.test_results = self.test_metrics.compute()
        self.log_dict({f"test/{k}": v for k, v in self.test_results.items()})
        self.test_metrics.reset()

    def configure_optimizers(self) -> dict[str, Any]:
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams["lr"], weight_decay=self.hparams["weight_decay"])
        spec = self.hparams["scheduler"]
        if spec is None:
            return {"optimizer": optimizer}
        options = {k: v for k, v in spec.items() if k != "name"}
        scheduler = SCHEDULERS[spec["name"]](optimizer, self._total_steps, **options)
        return {"optimizer": optimizer, "lr_scheduler": scheduler}

    def _total_steps(self) -> int:
        """Optimiser steps of the whole run (trainer.max_steps, or epochs × batches per epoch)."""
        total = self.trainer.estimated_stepping_batches
        if not math.isfinite(total):
            raise ConfigError(f"model.scheduler {self.hparams['scheduler']['name']} needs the run's length: "
                              "set trainer.max_steps or trainer.max_epochs")
        return int(total)
