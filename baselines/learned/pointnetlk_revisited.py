"""PointNetLK-Revisited (Li, Pontes & Lucey, CVPR 2021): PointNetLK with an analytical Jacobian.

From the paper: the finite-difference Jacobian of PointNetLK is replaced by the exact Jacobian of the
PointNet feature w.r.t. the twist — the chain rule through the per-point layers at the point each
feature's max pool selects, times the warp Jacobian — computed once at the template; the rest is
PointNetLK's inverse-compositional LK.

Facts taken from the authors' code (Lilac-Lee/PointNetLK_Revisited, ``model.py``, ``utils.py``,
``trainer.py``, ``train.py``, ``test.py``), not its code:

* encoder (``model.py`` 50–100, ``mlp_layers`` 9–26): per-point 3-64 | 64-128 | 128-1024 (Conv1d with bias
  + BatchNorm + ReLU each), max pooling, ``dim_k = 1024``;
* Jacobian (``utils.feature_jac`` 286–321, ``compute_warp_jac`` 325–351, ``Cal_Jac`` 222–262): computed
  with the encoder in eval mode from detached weights, BatchNorm scales and ReLU masks (no gradient
  flows through J) — :func:`~baselines.learned.common.global_feature.pointnet_jacobian`;
* LK (``iclk_new`` 264–350, ``do_forward`` 143–202): both clouds mean-centred and the result
  ``T(m_template)·g·T(−m_source)``; ``Δξ = J⁺r``, ``g ← exp(Δξ)·g`` with their J of exp(−ξ)·p (the
  same step as −J⁺r with ours); stop when max‖Δξ‖ < 1e-7 (``trainer.py`` 26); 10 iterations in
  training (``train.py --max_iter 10``), 20 at test (``test.py --max_iter 20``; ``eval_max_iter``);
* training (``iclk_new`` 279–306, 323): the BatchNorm statistics are updated by one training-mode pass
  of ``num_random_points`` = 100 random points of each cloud, then the encoder is frozen in eval mode;
  J and the iterations use another 100 random points (``--num_random_points 100``);
* loss (``trainer.compute_loss`` 231–239, ``comp``/``rsq`` 121–140): the batch mean of
  ‖G_est·G_gt⁻¹ − I‖²_F plus Σ (r − r_prev)², the change of the residual in the last iteration (Σ r² after
  a single iteration);
* optimiser (``train.py`` 57–70, 115–116): Adam, lr 1e-3, weight decay 1e-4, batch 32, 200 epochs, no
  schedule; data (``train.py`` 31–38, 162–172): ModelNet40's first 20 categories, 1,000 points scaled
  into the unit cube (``data_utils.OnUnitCube``), twists of magnitude U[0, 0.8] moving the source.

Framework mapping: the reference is the template (p0), the source the moved cloud (p1).

Deviations: the hidden layers have no bias before BatchNorm (the same function: the published biases
are folded into the running means on import, :mod:`baselines.learned.published`); in training the
random subsets of the two clouds are drawn independently (the official code takes the same indices
of both, which are corresponding points only in its own data, where the source is a moved copy of
the template) and each subset is centred on its own mean (official: the full clouds' means); a
singular JᵀJ gives a zero update for that sample; ``width`` scales the channels (1.0 = the paper's).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from baselines.learned.common.encoders import PointNetEncoder
from baselines.learned.common.global_feature import (
    composed_identity_error,
    eval_mode,
    full_precision,
    lk_register,
    pointnet_jacobian,
)

from src.geometry import se3_inverse
from src.models.base import MIN_CHANNELS, scaled


def random_points(points: Tensor, count: int) -> Tensor:
    """The same ``count`` random points of every cloud of the batch (official: ``np.random.choice``,
    without replacement unless the cloud is smaller)."""
    n = points.shape[1]
    if n >= count:
        index = torch.randperm(n, device=points.device)[:count]
    else:
        index = torch.randint(n, (count,), device=points.device)
    return points[:, index]


class PointNetLKRevisited(nn.Module):
    def __init__(
        self,
        dim_k: int = 1024,
        width: float = 1.0,
        max_iter: int = 10,
        eval_max_iter: int = 20,
        xtol: float = 1e-7,
        num_random_points: int = 100,
    ) -> None:
        super().__init__()
        self.max_iter, self.eval_max_iter, self.xtol = max_iter, eval_max_iter, xtol
        self.num_random_points = num_random_points
        self.encoder = PointNetEncoder((3, *(scaled(c, width, minimum=MIN_CHANNELS) for c in (64, 128, dim_k))))

    def features(self, points: Tensor) -> Tensor:
        return self.encoder(points)[1]

    def linearize(self, template: Tensor) -> tuple[Tensor, Tensor]:
        """φ(template) and its analytical Jacobian (B, K, 6)."""
        return pointnet_jacobian(self.encoder.mlp, template)

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        if self.training:
            with torch.no_grad():  # official: one training-mode pass of a subset of each cloud
                for points in (points_ref, points_src):
                    subset = random_points(points, self.num_random_points)
                    self.features(subset - subset.mean(dim=1, keepdim=True))
            points_src = random_points(points_src, self.num_random_points)
            points_ref = random_points(points_ref, self.num_random_points)
        iterations = self.max_iter if self.training else self.eval_max_iter
        with eval_mode(self.encoder):
            result = lk_register(self.features, points_src, points_ref, None, iterations, self.xtol, self.linearize)
        return {"transforms": result.transforms, "residual": result.residual,
                "previous_residual": result.previous_residual, "iterations": result.iterations}

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        with full_precision(transform_gt.device):  # float32 even under bf16 autocast
            transform = composed_identity_error(outputs["transforms"][-1], se3_inverse(transform_gt)).mean()
            previous = outputs["previous_residual"]
            change = outputs["residual"] if previous is None else outputs["residual"] - previous
            feature = (change**2).sum()
            return {"loss": transform + feature, "loss/transform": transform, "loss/feature": feature}
