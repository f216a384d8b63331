"""OMNet (Xu et al., ICCV 2021): global-feature registration with learned overlapping masks.

Faithful to the paper and the official code (see ``shared/reference/omnet-official-code-notes.md``):
per-iteration weights (optionally shared), masks applied from the third iteration on as the argmax
of the previous iteration's mask logits, a quaternion + translation head, gradients stopped on the
pose between iterations, and mask labels recomputed every iteration. The Table-3 ablations (no mask
module, no mask loss, no fusion layers, no connection, top-k masks) and λ are constructor flags.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.geometry import matrix_to_quat, quat_canonical, quat_multiply, quat_normalize, quat_to_matrix, se3_apply, se3_from_rt

MASK_MODES = ("argmax", "topk")
FUSION_MASKINGS = ("official", "every_layer")
TRANSLATION_LOSSES = ("squared", "l2")


class PointwiseLayer(nn.Module):
    """A shared per-point layer on (B, N, C) features: Linear + BatchNorm + ReLU.

    Identical in function to the official Conv1d(k=1) + BatchNorm1d + ReLU (the batch-norm statistics
    are taken over batch and points alike), but runs as one matrix product, which is much faster
    than a k=1 convolution on the CPU.
    """

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.linear = nn.Linear(c_in, c_out, bias=False)
        self.norm = nn.BatchNorm1d(c_out)

    def forward(self, x: Tensor) -> Tensor:
        return self._normalize_and_activate(self.linear(x))

    def forward_with_global(self, local: Tensor, global_features: Tensor) -> Tensor:
        """``forward(cat(local, global_features broadcast to every point))`` (B,N,Cl), (B,Cg) → (B,N,C_out),
        with the global part of the product computed once per cloud instead of once per point. Same
        parameters and math (up to float summation order); for OMNet's first fusion layer, whose input
        is 97 % broadcast global features, it halves the network's multiply-adds."""
        weight = self.linear.weight
        c_local = local.shape[-1]
        y = F.linear(local, weight[:, :c_local]) + F.linear(global_features, weight[:, c_local:]).unsqueeze(1)
        return self._normalize_and_activate(y)

    def _normalize_and_activate(self, y: Tensor) -> Tensor:
        b, n, _ = y.shape
        return torch.relu(self.norm(y.reshape(b * n, -1))).reshape(b, n, -1)


def _pointwise_stack(channels: list[int]) -> nn.ModuleList:
    """Per-point layers, kept separate so intermediate features are visible."""
    return nn.ModuleList(PointwiseLayer(c_in, c_out) for c_in, c_out in zip(channels[:-1], channels[1:]))


def _masked_max(features: Tensor, mask: Tensor) -> Tensor:
    """max over points of features (B,N,C) × mask (B,N)."""
    return (features * mask.unsqueeze(-1)).amax(dim=1)


class OMNetIteration(nn.Module):
    """The networks of one iteration: encoder f, fusion g, mask head h and regressor r."""

    def __init__(
        self,
        width: float = 1.0,
        mask_module: bool = True,
        fusion: bool = True,
        connection: bool = True,
        fusion_masking: str = "official",
    ) -> None:
        super().__init__()
        w = lambda c: max(8, int(round(c * width)))  # noqa: E731 - channel width scaling
        self.mask_module, self.fusion_enabled = mask_module, fusion
        self.fusion_masking = fusion_masking
        self.connection = connection and mask_module
        self.encoder = _pointwise_stack([3, w(64), w(64), w(64), w(128), w(1024)])
        global_dim, local_dim = w(1024), w(64)
        self.fusion = _pointwise_stack([local_dim + 2 * global_dim, w(1024), w(1024), w(512)]) if (fusion or mask_module) else None
        if mask_module:
            self.decoder = _pointwise_stack([w(512), w(512), w(256), w(256)])
            self.mask_logits = nn.Linear(w(256), 2)
        per_cloud = (w(512) if fusion else global_dim) + (w(512) + 2 * w(256) if self.connection else 0)
        dims = [2 * per_cloud, w(2048), w(1024), w(512), w(256)]
        self.regressor = nn.Sequential(
            *[
                nn.Sequential(nn.Linear(a, b, bias=False), nn.BatchNorm1d(b), nn.ReLU(inplace=True))
                for a, b in zip(dims[:-1], dims[1:])
            ],
            nn.Linear(dims[-1], 7),
        )

    def encode(self, points: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Point features (64-wide local, 1024-wide) and the masked global feature."""
        x, local = points, points
        for k, layer in enumerate(self.encoder):
            x = layer(x)
            if k == 1:
                local = x
        return local, x, _masked_max(x, mask)

    def fuse_and_decode(self, local: Tensor, own: Tensor, other: Tensor, mask: Tensor) -> tuple[Tensor, list[Tensor], Tensor | None]:
        """Fused features g (masked), mask-head intermediates h (masked) and mask logits (B,N,2).

        ``fusion_masking="official"`` (official code, ``model/module.py`` ``Encoder.forward`` and
        ``Fusion.forward``): the 64-wide local feature is masked before fusion and only the fusion
        output is masked. ``"every_layer"``: the local input unmasked, every fusion layer's output masked.
        """
        m = mask.unsqueeze(-1)
        every_layer = self.fusion_masking == "every_layer"
        if not every_layer:
            local = local * m
        # fusion input: cat(local, own, other) per point, the two global features broadcast
        x = self.fusion[0].forward_with_global(local, torch.cat((own, other), dim=-1))
        for layer in self.fusion[1:]:
            x = layer(x * m if every_layer else x)
        x = x * m
        intermediates: list[Tensor] = []
        logits = None
        if self.mask_module:
            h = x
            for layer in self.decoder:
                h = layer(h)
                intermediates.append(h * m)
            logits = self.mask_logits(h)
        return x, intermediates, logits

    def forward(self, src: Tensor, ref: Tensor, mask_src: Tensor, mask_ref: Tensor) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """Quaternion (B,4), translation (B,3) and mask logits of both clouds."""
        local_s, feat_s, glob_s = self.encode(src, mask_src)
        local_r, feat_r, glob_r = self.encode(ref, mask_ref)
        pooled, logits = [], []
        for local, feat, own, other, mask in ((local_s, feat_s, glob_s, glob_r, mask_src), (local_r, feat_r, glob_r, glob_s, mask_ref)):
            fused, inter, lg = (None, [], None)
            if self.fusion is not None:
                fused, inter, lg = self.fuse_and_decode(local, own, other, mask)
            parts = [fused if self.fusion_enabled else feat * mask.unsqueeze(-1)]
            if self.connection:
                parts += inter
            pooled.append(_masked_max(torch.cat(parts, dim=-1), mask))
            logits.append(lg)
        out = self.regressor(torch.cat(pooled, dim=-1))
        return quat_normalize(out[:, :4]), out[:, 4:], logits[0], logits[1]


class OMNet(nn.Module):
    """Iterative OMNet; ``forward`` returns every iteration's pose, mask logits and mask labels."""

    def __init__(
        self,
        num_iters: int = 4,
        share_weights: bool = False,
        width: float = 1.0,
        mask_module: bool = True,
        mask_loss: bool = True,
        fusion: bool = True,
        connection: bool = True,
        mask_start_iter: int = 2,
        mask_mode: str = "argmax",
        topk: int = 500,
        overlap_dist: float = 0.1,
        mask_class_weights: tuple[float, float] = (0.7, 0.3),
        rot_loss_weight: float = 1.0,
        trans_loss_weight: float = 4.0,
        trans_loss: str = "squared",
        fusion_masking: str = "official",
    ) -> None:
        super().__init__()
        if fusion_masking not in FUSION_MASKINGS:
            raise ValueError(f"fusion_masking must be one of {FUSION_MASKINGS}, got {fusion_masking!r}")
        if mask_mode not in MASK_MODES:
            raise ValueError(f"mask_mode must be one of {MASK_MODES}, got {mask_mode!r}")
        if trans_loss not in TRANSLATION_LOSSES:
            raise ValueError(f"trans_loss must be one of {TRANSLATION_LOSSES}, got {trans_loss!r}")
        if num_iters < 1:
            raise ValueError(f"num_iters must be >= 1, got {num_iters}")
        self.num_iters, self.share_weights = num_iters, share_weights
        self.mask_module, self.mask_loss_enabled = mask_module, mask_loss and mask_module
        self.mask_start_iter, self.mask_mode, self.topk = mask_start_iter, mask_mode, topk
        self.overlap_dist = overlap_dist
        self.rot_loss_weight, self.trans_loss_weight, self.trans_loss = rot_loss_weight, trans_loss_weight, trans_loss
        self.register_buffer("mask_class_weights", torch.tensor(mask_class_weights, dtype=torch.float32))
        blocks = 1 if share_weights else num_iters
        self.iterations = nn.ModuleList(OMNetIteration(width, mask_module, fusion, connection, fusion_masking) for _ in range(blocks))
        self.apply(_init_weights)

    def block(self, i: int) -> OMNetIteration:
        return self.iterations[0 if self.share_weights else i]

    def next_mask(self, logits: Tensor) -> Tensor:
        """Hard 0/1 mask from mask logits (B,N,2): argmax, or the top-k overlap probabilities."""
        if self.mask_mode == "argmax":
            return logits.argmax(dim=-1).to(logits.dtype)
        k = min(self.topk, logits.shape[1])
        idx = logits.softmax(dim=-1)[..., 1].topk(k, dim=1).indices
        return torch.zeros_like(logits[..., 0]).scatter_(1, idx, 1.0)

    @torch.no_grad()
    def overlap_labels(self, src: Tensor, ref: Tensor, transform_gt: Tensor, mask_src: Tensor, mask_ref: Tensor) -> tuple[Tensor, Tensor]:
        """1 where a point's nearest neighbour in the other cloud, under the ground truth, is closer than
        ``overlap_dist``; points already masked out never match."""
        dist = torch.cdist(se3_apply(transform_gt.float(), src.float()), ref.float())
        far = 1e6
        dist = dist + far * (1 - mask_src).unsqueeze(2) + far * (1 - mask_ref).unsqueeze(1)
        return (dist.amin(dim=2) < self.overlap_dist).long(), (dist.amin(dim=1) < self.overlap_dist).long()

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        b = points_src.shape[0]
        mask_src = points_src.new_ones(b, points_src.shape[1])
        mask_ref = points_ref.new_ones(b, points_ref.shape[1])
        quat = points_src.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(b, 4)
        trans = points_src.new_zeros(b, 3)
        out: dict[str, list] = {"transforms": [], "quats": [], "translations": [], "mask_logits": [], "mask_labels": [], "masks": []}
        full_precision = torch.autocast(points_src.device.type, enabled=False)  # poses stay float32 under bf16
        for i in range(self.num_iters):
            with full_precision:
                moved = se3_apply(se3_from_rt(quat_to_matrix(quat), trans).detach(), points_src.float())
            d_quat, d_trans, logits_src, logits_ref = self.block(i)(moved, points_ref, mask_src, mask_ref)
            with full_precision:
                d_quat, d_trans = quat_normalize(d_quat.float()), d_trans.float()
                quat_prev, trans_prev = quat.detach(), trans.detach()
                quat = quat_multiply(d_quat, quat_prev)
                trans = (quat_to_matrix(d_quat) @ trans_prev.unsqueeze(-1)).squeeze(-1) + d_trans
                out["transforms"].append(se3_from_rt(quat_to_matrix(quat), trans))
            out["quats"].append(quat)
            out["translations"].append(trans)
            out["masks"].append((mask_src, mask_ref))
            if self.mask_module:
                out["mask_logits"].append((logits_src, logits_ref))
                if transform_gt is not None:
                    out["mask_labels"].append(self.overlap_labels(points_src, points_ref, transform_gt, mask_src, mask_ref))
                if i + 1 >= self.mask_start_iter:
                    mask_src, mask_ref = self.next_mask(logits_src.detach()), self.next_mask(logits_ref.detach())
        return out

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        """Sum over iterations (equal weights) of mask CE + |q − q_gt|₁ + λ·translation error."""
        quat_gt = quat_canonical(matrix_to_quat(transform_gt[:, :3, :3]))
        trans_gt = transform_gt[:, :3, 3]
        zero = transform_gt.new_zeros((), dtype=torch.float32)
        terms = {"loss/quat": zero, "loss/trans": zero, "loss/mask": zero}
        for i, (quat, trans) in enumerate(zip(outputs["quats"], outputs["translations"])):
            terms["loss/quat"] = terms["loss/quat"] + F.l1_loss(quat, quat_gt)
            if self.trans_loss == "squared":
                terms["loss/trans"] = terms["loss/trans"] + F.mse_loss(trans, trans_gt)
            else:
                terms["loss/trans"] = terms["loss/trans"] + (trans - trans_gt).norm(dim=-1).mean()
            if self.mask_loss_enabled:
                (logits_src, logits_ref), (labels_src, labels_ref) = outputs["mask_logits"][i], outputs["mask_labels"][i]
                ce = lambda lg, lb: F.cross_entropy(lg.reshape(-1, 2).float(), lb.reshape(-1), weight=self.mask_class_weights)  # noqa: E731
                terms["loss/mask"] = terms["loss/mask"] + 0.5 * (ce(logits_src, labels_src) + ce(logits_ref, labels_ref))
        terms["loss"] = self.rot_loss_weight * terms["loss/quat"] + self.trans_loss_weight * terms["loss/trans"] + terms["loss/mask"]
        return terms


def _init_weights(module: nn.Module) -> None:
    """Official init: Kaiming-normal weights (a=√5), biases uniform in ±1/√fan_in."""
    if isinstance(module, nn.Linear):
        nn.init.kaiming_normal_(module.weight, a=math.sqrt(5))
        if module.bias is not None:
            fan_in = module.weight[0].numel()
            bound = 1 / math.sqrt(fan_in)
            nn.init.uniform_(module.bias, -bound, bound)
