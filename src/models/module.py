"""One LightningModule that trains and evaluates any registration network."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import hydra
import lightning as L
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn
from torchmetrics import MeanMetric

from src.metrics import RegistrationMetrics


def _plain(cfg: Any) -> Any:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else cfg


class RegistrationModule(L.LightningModule):
    """Wraps a network (see :mod:`src.models.base`) with its loss, the paper's metrics and Adam.

    ``network`` is the Hydra config of the network (``_target_`` + arguments), stored in the
    checkpoint so :meth:`load_from_checkpoint` rebuilds it without the original config. The best
    checkpoint is chosen on ``val/score`` = 0.01·Error(R) + Error(t) (official code).
    """

    def __init__(
        self,
        network: Mapping[str, Any],
        lr: float = 1e-4,
        weight_decay: float = 0.0,
        lr_milestones: Sequence[int] = (220_000,),
        lr_gamma: float = 0.1,
        euler_seq: str = "zyx",
        compile: bool = False,
    ) -> None:
        super().__init__()
        network = _plain(network)
        self.save_hyperparameters({"network": network, "lr": lr, "weight_decay": weight_decay,
                                   "lr_milestones": list(lr_milestones), "lr_gamma": lr_gamma,
                                   "euler_seq": euler_seq, "compile": compile})
        self.network: nn.Module = hydra.utils.instantiate(network)
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

    def forward(self, points_src: Tensor, points_ref: Tensor) -> Tensor:
        """Final source→reference transform (B,4,4)."""
        return self.network(points_src, points_ref)["transforms"][-1]

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        outputs = self.network(batch["points_src"], batch["points_ref"], batch["transform_gt"])
        losses = self.network.loss(outputs, batch["transform_gt"])
        self.log_dict({f"train/{k}": v.detach() for k, v in losses.items()}, prog_bar=False, batch_size=batch["points_src"].shape[0])
        self.log("train_loss", losses["loss"].detach(), prog_bar=True, logger=False)
        return losses["loss"]

    def _evaluate(self, batch: dict[str, Tensor], metrics: RegistrationMetrics, prefix: str) -> None:
        outputs = self.network(batch["points_src"], batch["points_ref"], batch["transform_gt"])
        losses = self.network.loss(outputs, batch["transform_gt"])
        batch_size = batch["points_src"].shape[0]
        self.eval_losses[prefix].update(losses["loss"].detach(), weight=batch_size)
        self.log(f"{prefix}/loss", self.eval_losses[prefix], on_step=False, on_epoch=True, batch_size=batch_size)
        metrics.update(outputs["transforms"][-1].float(), batch["transform_gt"], batch["points_src"], batch["points_ref"])

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, self.val_metrics, "val")

    def on_validation_epoch_end(self) -> None:
        values = self.val_metrics.compute()
        self.log_dict({f"val/{k}": v for k, v in values.items()}, prog_bar=False)
        self.log("val_score", values["score"], prog_bar=True, logger=False)
        self.val_metrics.reset()

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, self.test_metrics, "test")

    def on_test_epoch_end(self) -> None:
        self.test_results = self.test_metrics.compute()
        self.log_dict({f"test/{k}": v for k, v in self.test_results.items()})
        self.test_metrics.reset()

    def configure_optimizers(self):
        optimizer = torch.optim.Adam(self.parameters(), lr=self.hparams["lr"], weight_decay=self.hparams["weight_decay"])
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, self.hparams["lr_milestones"], self.hparams["lr_gamma"])
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}
