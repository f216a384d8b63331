"""DCP (Wang & Solomon, "Deep Closest Point", ICCV 2019) for :class:`~src.models.module.RegistrationModule`.

Network (paper §4 and the official code, github.com/WangYueFt/dcp, README's DCP-v2 command
``--emb_nn dgcnn --pointer transformer --head svd``; DCP-v1 is ``--pointer identity``, ``pointer=False``):

* embedding F: DGCNN with k = 20 on the coordinates, edge features [x_j, x_i], per-edge layers
  64-64-128-256 (BatchNorm + ReLU) with a max over the neighbours after each, concatenated (512) and
  mapped to ``emb_dims`` = 512 (:class:`~baselines.learned.common.correspondence.DGCNN`, static graph);
* pointer φ: one-block transformer encoder–decoder, 4 heads, feed-forward 1024 (ReLU), dropout 0,
  shared by both directions; Φ_X = F_X + φ(F_X, F_Y), Φ_Y = F_Y + φ(F_Y, F_X). DCP-v1's ``Identity``
  pointer returns its inputs, which ``DCP.forward`` then adds to them (``model.py`` lines 340–345 and
  460–463): Φ = 2F, i.e. the head's matching logits are 4× F_X·F_Yᵀ/√d. ``pointer=False`` does the same,
  so the published DCP-v1 weights (trained with that factor) give the official estimates;
* head: soft pointer m(x_i) = softmax(Φ_Y Φ_x_iᵀ / √d) and the SVD (Procrustes) solve between the
  source and its soft correspondences m(x_i)ᵀY (uniform weights), one shot (no iterations).

Loss (paper Eq. 11, official code): MSE(R_predᵀ R_gt, I) + MSE(t_pred, t_gt) (mean over the
entries); the paper's λ‖θ‖² is Adam's weight decay (``conf/recipe/dcp.yaml``). The official
option ``--cycle`` (off by default, not used for DCP-v2) is ``cycle=True``: the reverse transform is
also solved by the head and MSE(R_ba R_ab, I) + mean‖R_baᵀ t_ab + t_ba‖² is added with weight 0.1.
Training recipe (official ``main.py``: optimiser, schedule, batch, epochs, checkpoint selection):
``conf/recipe/dcp.yaml``.

Deviations: channel-last Linear layers instead of 1×1 convolutions (same function); PyTorch's
LayerNorm (biased variance, ε inside the square root) instead of the code's hand-written one
(unbiased std, ε added to the std); the batched SVD of
:func:`~baselines.learned.common.procrustes.weighted_procrustes` (float64) with the reflection fixed
by sign(det) (the code flips V's last column when det < 0: the same rotation); ``width`` scales every
hidden channel count (1.0 = the paper's network; rounded to multiples of ``n_heads``).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.correspondence import AttentionPointer, DGCNN, matching_logits, soft_correspondence_svd
from src.models.base import scaled


class DCP(nn.Module):
    """DCP-v2 (``pointer=True``) or DCP-v1: DGCNN + pointer + soft correspondences + SVD."""

    def __init__(
        self,
        emb_dims: int = 512,
        k: int = 20,
        n_blocks: int = 1,
        n_heads: int = 4,
        ff_dims: int = 1024,
        dropout: float = 0.0,
        pointer: bool = True,
        cycle: bool = False,
        cycle_weight: float = 0.1,
        width: float = 1.0,
    ) -> None:
        super().__init__()
        emb = scaled(emb_dims, width, n_heads)
        self.cycle, self.cycle_weight = cycle, cycle_weight
        self.embedding = DGCNN([scaled(c, width) for c in (64, 64, 128, 256)], emb, k=k, dynamic=False)
        self.pointer = AttentionPointer(emb, n_blocks, n_heads, scaled(ff_dims, width), dropout) if pointer else None

    @property
    def min_points(self) -> int:
        """Fewest points per cloud: its DGCNN's."""
        return self.embedding.min_points

    def head(self, feat_src: Tensor, feat_ref: Tensor, src: Tensor, ref: Tensor) -> Tensor:
        """SVD head: the rigid transform (B,4,4) taking ``src`` to its soft correspondences in ``ref``."""
        return soft_correspondence_svd(src, ref, torch.softmax(matching_logits(feat_src, feat_ref), dim=-1))[0]

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        feat_src, feat_ref = self.embedding(points_src), self.embedding(points_ref)
        if self.pointer is None:  # the official Identity pointer: Φ = F + F
            phi_src, phi_ref = feat_src, feat_ref
        else:
            phi_src, phi_ref = self.pointer(feat_src, feat_ref)
        feat_src, feat_ref = feat_src + phi_src, feat_ref + phi_ref
        transform_ab = self.head(feat_src, feat_ref, points_src, points_ref)
        out = {"transforms": [transform_ab]}
        if self.cycle:
            out["transform_ba"] = self.head(feat_ref, feat_src, points_ref, points_src)
        return out

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        pred = outputs["transforms"][-1]
        rot, trans = pred[:, :3, :3], pred[:, :3, 3]
        eye = torch.eye(3, dtype=pred.dtype, device=pred.device).expand_as(rot)
        terms = {
            "loss/rot": F.mse_loss(rot.transpose(1, 2) @ transform_gt[:, :3, :3], eye),
            "loss/trans": F.mse_loss(trans, transform_gt[:, :3, 3]),
        }
        total = terms["loss/rot"] + terms["loss/trans"]
        if self.cycle:
            ba = outputs["transform_ba"]
            rot_ba, trans_ba = ba[:, :3, :3], ba[:, :3, 3]
            cycle = F.mse_loss(rot_ba @ rot, eye) + ((rot_ba.transpose(1, 2) @ trans.unsqueeze(-1)).squeeze(-1) + trans_ba).square().mean()
            terms["loss/cycle"] = cycle
            total = total + self.cycle_weight * cycle
        terms["loss"] = total
        return terms

