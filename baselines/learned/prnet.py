"""PRNet (Wang & Solomon, "PRNet: Self-Supervised Learning for Partial-to-Partial Registration",
NeurIPS 2019) for :class:`~src.models.module.RegistrationModule`.

Network (paper §3–4 and the official code, github.com/WangYueFt/prnet, defaults of ``main.py``):

* embedding: DGCNN with k = 20, a k-NN graph recomputed in feature space at every layer (edge
  features [x_j, x_i]), layers 64-64-128-256 with BatchNorm + LeakyReLU(0.2), concatenated and mapped
  to ``emb_dims`` = 512 (:class:`~baselines.learned.common.correspondence.DGCNN`, ``dynamic=True``);
* attention: DCP's transformer pointer (1 block, 4 heads, feed-forward 1024 with LeakyReLU 0.2,
  dropout 0) with the code's LayerNorm (unbiased std, ε added to it: model.py:159-169; PyTorch's moves
  the hard Gumbel samples, and with them the estimates, by degrees), Φ = F + φ;
* keypoints: the ``num_keypoints`` = 512 points of each cloud with the largest ‖Φ‖₂ (768 inputs);
* temperature: an MLP (512→128→128→128→1, BatchNorm + ReLU, final ReLU) on |mean Φ_X − mean Φ_Y| over
  the keypoints, clamped to [1/100, 100];
* matching: hard Gumbel-softmax (straight-through) of the scaled keypoint-feature dot products with
  that temperature, then the SVD solve (uniform weights) — for X→Y and, with the same features and
  temperature, Y→X;
* ``num_iters`` = 3 iterations, the source moved by each iteration's estimate (not detached, as the
  code) and the estimates composed.

Loss (official code; the paper's pose, cycle-consistency and global-feature-alignment terms): per
iteration i, discounted by 0.9^i, MSE(R_iᵀ R_gt, I) + MSE(t_i, t_gt) on the composed estimate,
+ 0.1·mean|mean Φ_X − mean Φ_Y| (feature alignment), + 0.1·[MSE(R_ab R_ba, I) + MSE(t_ab, −t_ba)]
on the iteration's own X→Y / Y→X estimates (cycle consistency; the code compares t_ab with −t_ba
literally). There is no separate keypoint loss: the keypoint detector is learned through these terms.
Training recipe (official ``main.py``: optimiser, schedule, batch, epochs, checkpoint selection):
``conf/recipe/prnet.yaml``.

Deviations: channel-last Linear layers instead of 1×1 convolutions; batched float64 SVD with a sign(det)
reflection fix and uniform weights 1/(K + 1e-5) (the code's 1/K: translations ~1e-8 apart); the Gumbel noise is
drawn at evaluation too, as the official test loop does (``deterministic_eval=True`` uses the plain
argmax instead — the hard sample's value does not depend on the temperature); with fewer points than
``num_keypoints`` all points are keypoints; ``width`` scales every hidden channel count (1.0 = paper).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.correspondence import (
    DGCNN,
    AttentionPointer,
    gather_neighbours,
    gumbel_softmax,
    matching_logits,
    soft_correspondence_svd,
)
from baselines.learned.common.layers import MLP
from src.geometry import se3_apply
from src.models.base import scaled

SAMPLERS = ("gumbel_softmax", "softmax")


class PRNet(nn.Module):
    """Iterative PRNet (ACPNet applied ``num_iters`` times)."""

    def __init__(
        self,
        emb_dims: int = 512,
        k: int = 20,
        n_blocks: int = 1,
        n_heads: int = 4,
        ff_dims: int = 1024,
        dropout: float = 0.0,
        num_iters: int = 3,
        num_keypoints: int = 512,
        temp_factor: float = 100.0,
        sampler: str = "gumbel_softmax",
        deterministic_eval: bool = False,
        discount: float = 0.9,
        cycle_weight: float = 0.1,
        feature_alignment_weight: float = 0.1,
        width: float = 1.0,
        layer_norm: str = "authors",
    ) -> None:
        super().__init__()
        if sampler not in SAMPLERS:
            raise ValueError(f"sampler must be one of {SAMPLERS}, got {sampler!r}")
        if num_iters < 1:
            raise ValueError(f"num_iters must be >= 1, got {num_iters}")
        emb, hidden = scaled(emb_dims, width, n_heads), scaled(128, width)
        self.num_iters, self.num_keypoints, self.temp_factor = num_iters, num_keypoints, temp_factor
        self.sampler, self.deterministic_eval = sampler, deterministic_eval
        self.discount, self.cycle_weight, self.feature_alignment_weight = discount, cycle_weight, feature_alignment_weight
        self.embedding = DGCNN([scaled(c, width) for c in (64, 64, 128, 256)], emb, k=k, dynamic=True, negative_slope=0.2)
        self.pointer = AttentionPointer(emb, n_blocks, n_heads, scaled(ff_dims, width), dropout, negative_slope=0.2,
                                        layer_norm=layer_norm)
        self.temperature_net = MLP([emb, hidden, hidden, hidden, 1], last_activation=False, bias=True)

    @property
    def samples_at_test(self) -> bool:
        """Whether its estimates at test are random draws (the Gumbel noise of the official test loop)."""
        return self.sampler == "gumbel_softmax" and not self.deterministic_eval

    @property
    def min_points(self) -> int:
        """Fewest points per cloud: its DGCNN's."""
        return self.embedding.min_points

    def keypoints(self, points: Tensor, feat: Tensor) -> tuple[Tensor, Tensor]:
        """The ``num_keypoints`` points (and features) with the largest feature norms."""
        if feat.shape[1] <= self.num_keypoints:
            return points, feat
        idx = feat.norm(dim=-1).topk(self.num_keypoints, dim=1).indices.unsqueeze(1)  # (B,1,K)
        return gather_neighbours(points, idx).squeeze(1), gather_neighbours(feat, idx).squeeze(1)

    def match(self, feat_a: Tensor, feat_b: Tensor, temperature: Tensor) -> Tensor:
        logits = matching_logits(feat_a, feat_b)
        tau = temperature.view(-1, 1, 1)
        if self.sampler == "softmax":
            return torch.softmax(tau * logits, dim=-1)
        if not self.training and self.deterministic_eval:
            return F.one_hot(logits.argmax(dim=-1), logits.shape[-1]).to(logits.dtype)
        return gumbel_softmax(logits, tau, hard=True)

    def step(self, src: Tensor, ref: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """One ACPNet pass: X→Y and Y→X transforms (B,4,4) and the feature disparity (B,C)."""
        feat_src, feat_ref = self.embedding(src), self.embedding(ref)
        phi_src, phi_ref = self.pointer(feat_src, feat_ref)
        feat_src, feat_ref = feat_src + phi_src, feat_ref + phi_ref
        kp_src, feat_src = self.keypoints(src, feat_src)
        kp_ref, feat_ref = self.keypoints(ref, feat_ref)
        disparity = (feat_src.mean(dim=1) - feat_ref.mean(dim=1)).abs()
        temperature = torch.relu(self.temperature_net(disparity)).clamp(1.0 / self.temp_factor, self.temp_factor)
        transform_ab = soft_correspondence_svd(kp_src, kp_ref, self.match(feat_src, feat_ref, temperature))[0]
        transform_ba = soft_correspondence_svd(kp_ref, kp_src, self.match(feat_ref, feat_src, temperature))[0]
        return transform_ab, transform_ba, disparity

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        b = points_src.shape[0]
        total = torch.eye(4, dtype=points_src.dtype, device=points_src.device).expand(b, 4, 4)
        out: dict[str, list] = {"transforms": [], "steps_ab": [], "steps_ba": [], "disparities": []}
        src = points_src
        for _ in range(self.num_iters):
            step_ab, step_ba, disparity = self.step(src, points_ref)
            total = step_ab @ total
            src = se3_apply(step_ab, src)
            out["transforms"].append(total)
            out["steps_ab"].append(step_ab)
            out["steps_ba"].append(step_ba)
            out["disparities"].append(disparity)
        return out

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        rot_gt, trans_gt = transform_gt[:, :3, :3], transform_gt[:, :3, 3]
        eye = torch.eye(3, dtype=rot_gt.dtype, device=rot_gt.device).expand_as(rot_gt)
        zero = transform_gt.new_zeros(())
        terms = {"loss/pose": zero, "loss/feature_alignment": zero, "loss/cycle": zero}
        for i, (pred, ab, ba, disparity) in enumerate(
            zip(outputs["transforms"], outputs["steps_ab"], outputs["steps_ba"], outputs["disparities"])
        ):
            w = self.discount**i
            pose = F.mse_loss(pred[:, :3, :3].transpose(1, 2) @ rot_gt, eye) + F.mse_loss(pred[:, :3, 3], trans_gt)
            cycle = F.mse_loss(ab[:, :3, :3] @ ba[:, :3, :3], eye) + F.mse_loss(ab[:, :3, 3], -ba[:, :3, 3])
            terms["loss/pose"] = terms["loss/pose"] + w * pose
            terms["loss/feature_alignment"] = terms["loss/feature_alignment"] + w * self.feature_alignment_weight * disparity.mean()
            terms["loss/cycle"] = terms["loss/cycle"] + w * self.cycle_weight * cycle
        terms["loss"] = terms["loss/pose"] + terms["loss/feature_alignment"] + terms["loss/cycle"]
        return terms
