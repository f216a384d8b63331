"""IDAM (Li et al., "Iterative Distance-Aware Similarity Matrix Convolution with Mutual-Supervised Point
Elimination for Efficient Point Cloud Registration", ECCV 2020) for
:class:`~src.models.module.RegistrationModule`.

Network (paper §3 and the official code, github.com/jiahaowork/idam, the GNN variant with the
defaults of ``main.py``):

* embedding: a GNN of 5 edge convolutions on one k-NN graph of the coordinates (k = 12, itself
  included), edge features x_j − x_i, each Linear-BN-ReLU-Linear on the edges, max over the
  neighbours, then a per-point Linear; 3→64→64→64→64→64 (``emb_dims`` = 64);
* hard point elimination: a significance MLP (64-64-32-1, BN + ReLU) scores every point; N // 6
  points of each cloud are kept — at evaluation the top-scored ones; while training (as the code)
  half of them sampled among the source points with a ground-truth neighbour in the reference
  closer than 0.05, half among the others, and as reference points the ground-truth nearest
  neighbours of the chosen source points (so the i-th source and i-th reference point correspond);
* ``num_iters`` = 3 iterations, each with its own weights: the distance-aware similarity "image"
  [f_i, g_j, ‖x_i − y_j‖, (x_i − y_j)/‖x_i − y_j‖] (B, K, K, 2·64+4) → 32-32 (BN + ReLU, last plain);
  soft point elimination: max over j → 32-1 weight logits (the image's first Linear is computed per point and
  broadcast, :func:`similarity_first_layer`, the same function without the (B, K, K, 132) tensor); similarity: 32-32-1, clamped to ±20;
  correspondences = row argmax; weights = sigmoid(logits) zeroed below their median and normalised;
  weighted Procrustes; the pose is detached (no gradient through the SVD) and the selected source
  points are moved before the next iteration.

Loss (paper §3.4–3.5 and the code): per iteration, the point-matching loss −log softmax_j(S)_{i,i*}
averaged over the source points with a true match (i* = its ground-truth correspondence), and the
soft-elimination loss BCE(weight logits, [argmax_j S_ij = i*]); at the first iteration only, the
mutual-supervision (negative-entropy) loss MSE(significance, Σ p log p) for the source (rows of
softmax(S)) and the reference (columns), the targets detached.
Training recipe (official ``main.py``: optimiser, schedule, batch, epochs, checkpoint selection):
``conf/recipe/idam.yaml``.

Deviations: channel-last Linear layers instead of 1×1 convolutions; the weighted Procrustes
centres both clouds on their weighted centroids (the code centres the covariance on the uniform
means but translates by the weighted ones); in evaluation mode with a ground truth given (this
framework's validation loss) the targets are each selected source point's ground-truth nearest
selected reference point (the code refuses a ground truth outside training); the matching loss is
divided by max(1, #true matches) instead of #true matches (no NaN when there is none); ``width``
scales the hidden channel counts (1.0 = paper).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.correspondence import EdgeConv, gather_neighbours
from baselines.learned.common.encoders import knn_indices
from baselines.learned.common.layers import MLP
from baselines.learned.common.procrustes import weighted_procrustes
from src.geometry import se3_apply
from src.models.base import scaled


def _gather(x: Tensor, idx: Tensor) -> Tensor:
    """x (B, N, C) at idx (B, K) → (B, K, C)."""
    return gather_neighbours(x, idx.unsqueeze(1)).squeeze(1)


def similarity_first_layer(linear: nn.Linear, feat_src: Tensor, feat_ref: Tensor, geometry: Tensor) -> Tensor:
    """``linear`` on the distance-aware similarity image [f_i, g_j, geometry_ij] (B, K, M, ·) without building it.

    W[f_i; g_j; e_ij] = W₁f_i + W₂g_j + W₃e_ij: the feature parts are multiplied once per point (K + M
    rows, not K·M) and broadcast; equal to ``linear(torch.cat(...))`` up to rounding."""
    c = feat_src.shape[-1]
    weight = linear.weight
    rows = F.linear(feat_src, weight[:, :c]).unsqueeze(2)
    cols = F.linear(feat_ref, weight[:, c:2 * c]).unsqueeze(1)
    return F.linear(geometry, weight[:, 2 * c:], linear.bias) + rows + cols


class GNN(nn.Module):
    """IDAM's graph embedding: 5 propagations on a static k-NN graph, (B, N, 3) → (B, N, emb_dims)."""

    def __init__(self, emb_dims: int = 64, k: int = 12, hidden: int = 64) -> None:
        super().__init__()
        self.k = k
        dims = [3, hidden, hidden, hidden, hidden, emb_dims]
        self.edges = nn.ModuleList(EdgeConv([a, b, b], mode="diff", last_activation=False) for a, b in zip(dims[:-1], dims[1:]))
        self.points = nn.ModuleList(nn.Linear(b, b) for b in dims[1:])

    def forward(self, points: Tensor) -> Tensor:
        idx = knn_indices(points.detach(), min(self.k, points.shape[1]))
        x = points
        for edge, point in zip(self.edges, self.points):
            x = point(edge(x, idx))
        return x


class IDAM(nn.Module):
    """IDAM with the GNN embedding, hard + hybrid point elimination and iterative similarity convolution."""

    def __init__(
        self,
        emb_dims: int = 64,
        k: int = 12,
        num_iters: int = 3,
        keep_divisor: int = 6,
        match_dist: float = 0.05,
        width: float = 1.0,
    ) -> None:
        super().__init__()
        if num_iters < 1:
            raise ValueError(f"num_iters must be >= 1, got {num_iters}")
        emb, c32 = scaled(emb_dims, width), scaled(32, width)
        self.num_iters, self.keep_divisor, self.match_dist = num_iters, keep_divisor, match_dist
        self.embedding = GNN(emb, k, scaled(64, width))
        self.significance = MLP([emb, scaled(64, width), c32, 1], last_activation=False)
        self.sim_features = nn.ModuleList(MLP([2 * emb + 4, c32, c32], last_activation=False) for _ in range(num_iters))
        self.sim_scores = nn.ModuleList(MLP([c32, c32, 1], last_activation=False) for _ in range(num_iters))
        self.weight_logits = nn.ModuleList(MLP([c32, c32, 1], last_activation=False) for _ in range(num_iters))

    @property
    def min_points(self) -> int:
        """Fewest points per cloud: its k-NN graph takes each point's k nearest (itself included), and the hard point
        elimination keeps N // keep_divisor points for the rotation, which needs 3."""
        return max(self.embedding.k, 3 * self.keep_divisor)

    @torch.no_grad()
    def _training_selection(self, src: Tensor, ref: Tensor, transform_gt: Tensor, num_keep: int) -> tuple[Tensor, ...]:
        """Source indices (half true matches, half not), their GT nearest reference points, labels."""
        min_dist, min_idx = torch.cdist(se3_apply(transform_gt, src), ref).min(dim=-1)
        labels = (min_dist < self.match_dist).to(src.dtype)
        pos = torch.multinomial(labels + 1e-5, num_keep // 2, replacement=False)
        neg = torch.multinomial(1.0 + 1e-5 - labels, num_keep - num_keep // 2, replacement=False)
        src_idx = torch.cat((pos, neg), dim=1)
        targets = torch.arange(num_keep, device=src.device).expand(src.shape[0], -1)
        return src_idx, min_idx.gather(1, src_idx), targets, labels.gather(1, src_idx)

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        b, n, _ = points_src.shape
        feat_src, feat_ref = self.embedding(points_src), self.embedding(points_ref)
        sig_src, sig_ref = self.significance(feat_src).squeeze(-1), self.significance(feat_ref).squeeze(-1)
        num_keep = max(2, min(n // self.keep_divisor, points_ref.shape[1]))
        targets = match_labels = None
        if self.training:
            if transform_gt is None:
                raise ValueError("IDAM needs transform_gt while training (supervised point selection)")
            src_idx, ref_idx, targets, match_labels = self._training_selection(points_src, points_ref, transform_gt, num_keep)
        else:
            src_idx, ref_idx = sig_src.topk(num_keep, dim=1).indices, sig_ref.topk(num_keep, dim=1).indices
        src, ref = _gather(points_src, src_idx), _gather(points_ref, ref_idx)
        feat_src, feat_ref = _gather(feat_src, src_idx), _gather(feat_ref, ref_idx)
        if not self.training and transform_gt is not None:
            with torch.no_grad():
                min_dist, targets = torch.cdist(se3_apply(transform_gt, src), ref).min(dim=-1)
                match_labels = (min_dist < self.match_dist).to(src.dtype)
        total = torch.eye(4, dtype=points_src.dtype, device=points_src.device).expand(b, 4, 4)
        out: dict = {"transforms": [], "similarities": [], "weight_logits": [], "correspondences": [],
                     "significance": (_gather(sig_src.unsqueeze(-1), src_idx).squeeze(-1),
                                      _gather(sig_ref.unsqueeze(-1), ref_idx).squeeze(-1)),
                     "targets": targets, "match_labels": match_labels}
        for i in range(self.num_iters):
            diff = src.unsqueeze(2) - ref.unsqueeze(1)
            dist = diff.norm(dim=-1, keepdim=True)
            first, rest = self.sim_features[i].layers[0], self.sim_features[i].layers[1:]
            hidden = rest(similarity_first_layer(first, feat_src, feat_ref, torch.cat((dist, diff / (dist + 1e-8)), dim=-1)))
            logits = self.weight_logits[i](hidden.amax(dim=2)).squeeze(-1)
            similarity = self.sim_scores[i](hidden).squeeze(-1).clamp(-20.0, 20.0)
            corr = similarity.argmax(dim=-1)
            weights = torch.sigmoid(logits.detach())
            weights = weights * (weights >= weights.median(dim=-1, keepdim=True).values)
            weights = weights / (weights.sum(dim=-1, keepdim=True) + 1e-8)
            step = weighted_procrustes(src, _gather(ref, corr), weights).detach()
            src = se3_apply(step, src)
            total = step @ total
            out["transforms"].append(total)
            out["similarities"].append(similarity)
            out["weight_logits"].append(logits)
            out["correspondences"].append(corr)
        return out

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        targets, labels = outputs["targets"], outputs["match_labels"]
        if targets is None:
            raise ValueError("IDAM's loss needs the ground-truth correspondences: pass transform_gt to forward")
        zero = transform_gt.new_zeros(())
        terms = {"loss/match": zero, "loss/weight": zero, "loss/negative_entropy": zero}
        for i, (similarity, logits, corr) in enumerate(zip(outputs["similarities"], outputs["weight_logits"], outputs["correspondences"])):
            log_p = torch.log_softmax(similarity, dim=-1).gather(-1, targets.unsqueeze(-1)).squeeze(-1)
            terms["loss/match"] = terms["loss/match"] + -(log_p * labels).sum() / labels.sum().clamp_min(1.0)
            terms["loss/weight"] = terms["loss/weight"] + F.binary_cross_entropy_with_logits(logits, (corr == targets).to(logits.dtype))
            if i == 0:
                sig_src, sig_ref = outputs["significance"]
                log_rows, log_cols = torch.log_softmax(similarity, dim=-1), torch.log_softmax(similarity, dim=-2)
                neg_ent_src = (log_rows.exp() * log_rows).sum(dim=-1).detach()
                neg_ent_ref = (log_cols.exp() * log_cols).sum(dim=-2).detach()
                terms["loss/negative_entropy"] = F.mse_loss(sig_src, neg_ent_src) + F.mse_loss(sig_ref, neg_ent_ref)
        terms["loss"] = terms["loss/match"] + terms["loss/weight"] + terms["loss/negative_entropy"]
        return terms
