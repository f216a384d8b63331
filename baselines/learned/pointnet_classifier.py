"""The first stage of PointNetLK's recipe: a PointNet classifier whose features initialise PointNetLK.

PointNetLK's authors train a classifier on the same categories first and start the registration
training from its PointNet (``experiments/ex1_train.sh``: ``train_classifier.py``, then
``train_pointlk.py --transfer-from <classifier>_feat_best.pth``; learning3d: ``train_pointnet.py``, then
``train_PointNetLK.py --transfer_ptnet_weights best_ptnet_model.t7``).

* network: PointNetLK's encoder (:func:`~baselines.learned.pointnetlk.pointnet_channels`, 3-64-64-64-128-1024,
  BatchNorm + ReLU, max pool) and learning3d's head (``models/classifier.py``): Linear 1024-512-256
  with BatchNorm + ReLU + dropout 0.7, then Linear 256 → classes;
* loss: cross-entropy (``F.nll_loss`` of ``log_softmax`` there, the same); Adam with PyTorch's
  defaults (lr 1e-3), no schedule (``train_pointnet.py``).

:class:`ClassificationModule` trains it with ``src.train`` (``model=pointnet_classifier``) on the
experiment's pairs: the input is each pair's ``points_ref`` centred on its mean (PointNetLK applies the
features to mean-centred clouds), the target the batch's ``label``. It logs ``val/score`` = 1 −
accuracy (the checkpoint monitor) and tests accuracy and loss. Its checkpoint is a
``model.network.feature_init`` for PointNetLK (:func:`baselines.learned.published.pointnet_features`).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import hydra
import lightning as L
import torch
import torch.nn.functional as F
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn
from torchmetrics import MeanMetric

from baselines.learned.common.encoders import PointNetEncoder

from baselines.learned.pointnetlk import pointnet_channels
from src.models.base import MIN_CHANNELS, scaled


class PointNetClassifier(nn.Module):
    """PointNet features (:attr:`encoder`, PointNetLK's) + learning3d's classification head."""

    def __init__(self, num_classes: int = 40, dim_k: int = 1024, width: float = 1.0, dropout: float = 0.7) -> None:
        super().__init__()
        self.encoder = PointNetEncoder(pointnet_channels(dim_k, width))
        hidden = [scaled(c, width, minimum=MIN_CHANNELS) for c in (512, 256)]
        layers: list[nn.Module] = []
        for c_in, c_out in zip([self.encoder.mlp.layers[-3].out_features, hidden[0]], hidden):
            layers += [nn.Linear(c_in, c_out), nn.BatchNorm1d(c_out), nn.ReLU(inplace=True), nn.Dropout(dropout)]
        self.head = nn.Sequential(*layers, nn.Linear(hidden[-1], num_classes))

    def forward(self, points: Tensor) -> Tensor:
        """Class logits (B, classes) of clouds (B, N, 3)."""
        return self.head(self.encoder(points)[1])


class ClassificationModule(L.LightningModule):
    """Trains :class:`PointNetClassifier` (any ``network`` config) with ``src.train``; see the module docstring."""

    #: What each validation logs, that a checkpoint can be selected on (``callbacks.checkpoint.monitor``).
    VALIDATION_METRICS: tuple[str, ...] = ("val/accuracy", "val/loss")

    def __init__(self, network: Mapping[str, Any], lr: float = 1e-3, weight_decay: float = 0.0) -> None:
        super().__init__()
        network = OmegaConf.to_container(network, resolve=True) if isinstance(network, DictConfig) else dict(network)
        self.save_hyperparameters({"network": network, "lr": lr, "weight_decay": weight_decay})
        self.network: nn.Module = hydra.utils.instantiate(network)
        self.sums = nn.ModuleDict({f"{stage}_{name}": MeanMetric() for stage in ("val", "test") for name in ("loss", "acc")})
        self.test_results: dict[str, float] = {}

    @property
    def network_target(self) -> str:
        return self.hparams["network"]["_target_"]

    def _step(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        points = batch["points_ref"]
        logits = self.network(points - points.mean(dim=1, keepdim=True))
        return F.cross_entropy(logits, batch["label"]), (logits.argmax(dim=1) == batch["label"]).float()

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        loss, correct = self._step(batch)
        size = correct.numel()
        self.log_dict({"train/loss": loss.detach(), "train/accuracy": correct.mean()}, batch_size=size)
        return loss

    def _evaluate(self, batch: dict[str, Tensor], stage: str) -> None:
        loss, correct = self._step(batch)
        self.sums[f"{stage}_loss"].update(loss.detach(), weight=correct.numel())
        self.sums[f"{stage}_acc"].update(correct)

    def _results(self, stage: str) -> dict[str, float]:
        values = {"accuracy": float(self.sums[f"{stage}_acc"].compute()),
                  "loss": float(self.sums[f"{stage}_loss"].compute())}
        for name in ("loss", "acc"):
            self.sums[f"{stage}_{name}"].reset()
        return values

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, "val")

    def on_validation_epoch_end(self) -> None:
        values = self._results("val")
        self.log_dict({"val/accuracy": values["accuracy"], "val/loss": values["loss"],
                       "val/score": 1.0 - values["accuracy"]})

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def on_test_epoch_end(self) -> None:
        self.test_results = self._results("test")
        self.log_dict({f"test/{k}": v for k, v in self.test_results.items()})

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.hparams["lr"], weight_decay=self.hparams["weight_decay"])
