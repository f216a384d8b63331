"""FMR — Feature-Metric Registration (Huang, Mei & Zhang, CVPR 2020), the supervised version.

From the paper: a PointNet encoder gives global features of both clouds; task 1 decodes each feature
back into points (an encoder–decoder trained with the Chamfer distance, which makes the feature
metric meaningful without labels); task 2 minimises the feature-metric projection error
φ(g·Q) − φ(P) with inverse-compositional LK (PointNetLK's solver). The OMNet paper uses the
*supervised* (the FMR paper's "semi-supervised") version: Chamfer loss + transformation loss.

Facts taken from the authors' code (XiaoshuiHuang/fmr, ``model.py``, ``train.py``), not its code:

* encoder: PointNetLK's PointNet, 3-64-64-64-128-1024 (Conv1d + BatchNorm + ReLU), max pooling;
* decoder: FC 1024-1024-512-256 (+ BatchNorm + ReLU) then FC 256 → 3·n and tanh, with n the
  ``--num-points`` of the run, its input size (``decoder_points`` here: :func:`cloud_size` of the data);
* LK: step δ = 1e-2 per twist parameter, **learned** (``dt`` is a Parameter with requires_grad=True),
  10 iterations in training and testing, xtol 1e-7, both clouds mean-centred first;
* BatchNorm: the features for the decoder come from the encoder in training mode (which also
  updates its statistics); the encoder is then switched to eval mode for the LK;
* loss (``--train-type 1``, semi-supervised): ``loss_ende + loss_g`` — the Chamfer loss of the
  template and of the source against their reconstructions (squared distances, mean of each
  direction, on the centred clouds) plus the batch mean of ‖G_est·G_gt⁻¹ − I‖²_F; the feature
  residual is *not* in this loss (it is only in ``--train-type 2``);
* training recipe (optimiser, batch, epochs, checkpoint selection): ``conf/recipe/fmr.yaml``.

Framework mapping: the reference is the template, the source is moved; the estimate maps source →
reference. ``conf/model/fmr.yaml`` sets ``decoder_points`` to the data's cloud size (768 in the PRNet
manner, 717 in the RPMNet manner), as the official run; the class default is the PRNet manner's.

Deviations: hidden Linears have no bias before BatchNorm (same function), a singular JᵀJ gives a
zero update for that sample, ``width`` scales the encoder and decoder (1.0 = the paper's network).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from torch import Tensor, nn

from baselines.learned.common.encoders import PointNetEncoder
from baselines.learned.common.global_feature import (
    FeatureMetricDecoder,
    center,
    chamfer_loss,
    composed_identity_error,
    eval_mode,
    full_precision,
    lk_register,
    register_lk_delta,
)
from baselines.learned.pointnetlk import pointnet_channels
from src.data.pipelines import build_pair_transforms
from src.geometry import se3_inverse


def cloud_size(pair: Mapping[str, Any]) -> int:
    """Points in a source cloud of the pairs that ``data.pair`` describes: one pair drawn from a
    random two-sampling shape by the data's own transforms, so it follows every pair option."""
    rng = np.random.default_rng(0)
    shape = rng.normal(size=(2, pair["num_points"], 3)).astype(np.float32)
    sample = build_pair_transforms("independent_samplings", **pair)({"shape_points": shape}, rng)
    return len(sample["points_src"])


class FMR(nn.Module):
    def __init__(
        self,
        dim_k: int = 1024,
        width: float = 1.0,
        decoder_points: int = 768,
        max_iter: int = 10,
        delta: float = 1e-2,
        learn_delta: bool = True,
        xtol: float = 1e-7,
        chamfer_weight: float = 1.0,
        transform_weight: float = 1.0,
    ) -> None:
        super().__init__()
        self.max_iter, self.xtol = max_iter, xtol
        self.chamfer_weight, self.transform_weight = chamfer_weight, transform_weight
        channels = pointnet_channels(dim_k, width)
        self.encoder = PointNetEncoder(channels)
        self.decoder = FeatureMetricDecoder(channels[-1], decoder_points)
        register_lk_delta(self, delta, learn_delta)

    def features(self, points: Tensor) -> Tensor:
        return self.encoder(points)[1]

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        # Task 1: encode (training-mode BatchNorm in training) and decode both centred clouds.
        src, _ = center(points_src)
        ref, _ = center(points_ref)
        reconstructions = (self.decoder(self.features(ref)), self.decoder(self.features(src)))
        # Task 2: LK with the encoder's BatchNorm frozen.
        with eval_mode(self.encoder):
            result = lk_register(self.features, points_src, points_ref, self.delta, self.max_iter, self.xtol)
        return {
            "transforms": result.transforms,
            "residual": result.residual,
            "iterations": result.iterations,
            "centred": (ref, src),
            "reconstructions": reconstructions,
        }

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        with full_precision(transform_gt.device):  # float32 even under bf16 autocast
            (ref, src), (rec_ref, rec_src) = outputs["centred"], outputs["reconstructions"]
            chamfer = chamfer_loss(ref, rec_ref) + chamfer_loss(src, rec_src)
            transform = composed_identity_error(outputs["transforms"][-1], se3_inverse(transform_gt)).mean()
            total = self.chamfer_weight * chamfer + self.transform_weight * transform
            return {"loss": total, "loss/chamfer": chamfer, "loss/transform": transform}
