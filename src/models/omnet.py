"""OMNet (Xu et al., ICCV 2021): global-feature registration with learned overlapping masks.

Faithful to the paper and the official code (see ``shared/reference/omnet-official-code-notes.md``):
per-iteration weights (optionally shared), masks applied from the third iteration on as the argmax
of the previous iteration's mask logits, a quaternion + translation head, gradients stopped on the
pose between iterations, and mask labels recomputed every iteration. The Table-3 ablations (no mask
module, no mask loss, no fusion layers, no connection, top-k masks) and λ are constructor flags.

Execution (the same math; outputs equal up to float rounding, ``tests/unit/src/test_omnet_fast.py``):

* Batched (training; any evaluation with autograd, on a GPU or under ``torch.compile``): masks are not applied
  while they are all ones, pooled parts are max-pooled one by one (no concatenation of per-point features),
  ReLU runs in place, the close pairs behind the overlap labels are found once per forward pass (only the
  masks change between iterations) and, with shared weights, the reference cloud is encoded once (its
  features do not depend on the masks; the BatchNorm running-statistics updates of the skipped calls are
  replayed).
* CPU inference (eval mode, autograd off): cloud by cloud, on the kept points only (a masked-out point's
  features are zero where they are used, its pooled value 0 never exceeds the kept points' non-negative ReLU
  features, and its mask logits are the decoder's on a zero input), in chunks of points whose activations
  stay in cache, with BatchNorm folded into the linear layers (cached until a weight or statistic changes).
"""

from __future__ import annotations

import math
from functools import partial

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.utils.errors import ConfigError
from src.geometry import matrix_to_quat, quat_canonical, quat_multiply, quat_normalize, quat_to_matrix, se3_apply, se3_from_rt
from src.models.base import MIN_CHANNELS, scaled

MASK_MODES = ("argmax", "topk")
FUSION_MASKINGS = ("official", "every_layer")
TRANSLATION_LOSSES = ("squared", "l2")
#: How the class-weighted mask cross-entropy is normalised: ``per_cloud`` (the official code's
#: ``frequency_weighted_cross_entropy``, official README: Σw·nll/Σw per cloud, then the batch mean) or
#: ``batch`` (Σw·nll/Σw over all B·N points at once, PyTorch's ``F.cross_entropy(weight=...)``).
MASK_CE_REDUCTIONS = ("per_cloud", "batch")
INFERENCE_CHUNK_ROWS = 512  # points per chunk in CPU inference (measured: 256-1024 alike at width 0.25, 512 best at 1.0)

VarMean = tuple[Tensor, Tensor]


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
        self._folded: tuple[tuple, tuple[Tensor, Tensor]] | None = None

    def forward(self, x: Tensor, stats: list[VarMean] | None = None) -> Tensor:
        """``stats`` (training mode): a list to which the batch statistics that updated the running ones are appended,
        recovered from that update (no pass over the features), for ``replay_running_update``."""
        if stats is None:
            return self._normalize_and_activate(self.linear(x))
        norm = self.norm
        before = (norm.running_var.clone(), norm.running_mean.clone())
        out = self._normalize_and_activate(self.linear(x))
        factor = self._running_factor()
        after = (norm.running_var, norm.running_mean)
        stats.append(tuple((new - (1 - factor) * old) / factor for new, old in zip(after, before)))
        return out

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
        return torch.relu_(self.norm(y.reshape(b * n, -1))).reshape(b, n, -1)  # BatchNorm's backward needs its input only

    def replay_running_update(self, var_mean: VarMean) -> None:
        """Update the running statistics as a training-mode call on a batch with these statistics would."""
        norm = self.norm
        if not (norm.training and norm.track_running_stats):
            return
        with torch.no_grad():
            norm.num_batches_tracked.add_(1)
            factor = self._running_factor()
            # through .data, as BatchNorm's own kernel: no version bump, which autograd (saved statistics) would refuse
            norm.running_var.data.lerp_(var_mean[0], factor)
            norm.running_mean.data.lerp_(var_mean[1], factor)

    def _running_factor(self) -> float:
        """The weight of a batch in the running statistics (``BatchNorm``'s, once ``num_batches_tracked`` counts it)."""
        momentum = self.norm.momentum
        return 1.0 / self.norm.num_batches_tracked.item() if momentum is None else momentum

    def folded(self) -> tuple[Tensor, Tensor]:
        """Weight and bias of the linear layer with the eval-mode BatchNorm folded in: ``relu(x W'ᵀ + b')`` is
        ``forward(x)`` in eval mode. Cached until a weight or running statistic changes (in place or replaced; the
        running statistics are updated without a version bump, but each update counts ``num_batches_tracked``)."""
        norm = self.norm
        sources = (self.linear.weight, norm.weight, norm.bias, norm.running_mean, norm.running_var, norm.num_batches_tracked)
        key = tuple((t.data_ptr(), t._version, t.dtype, t.device) for t in sources)
        if self._folded is None or self._folded[0] != key:
            with torch.inference_mode(False), torch.no_grad():
                scale = norm.weight * torch.rsqrt(norm.running_var + norm.eps)
                self._folded = (key, (self.linear.weight * scale.unsqueeze(1), norm.bias - norm.running_mean * scale))
        return self._folded[1]


def _full(t: Tensor) -> Tensor:
    """``t`` in float32, or float64 if it is (poses and losses stay in full precision under bf16 autocast)."""
    return t if t.dtype == torch.float64 else t.float()


def _pointwise_stack(channels: list[int]) -> nn.ModuleList:
    """Per-point layers, kept separate so intermediate features are visible."""
    return nn.ModuleList(PointwiseLayer(c_in, c_out) for c_in, c_out in zip(channels[:-1], channels[1:]))


def _masked(features: Tensor, mask: Tensor | None) -> Tensor:
    """features (B,N,C) × mask (B,N); ``None``: every point kept."""
    return features if mask is None else features * mask.unsqueeze(-1)


def _max_over_points(features: Tensor) -> Tensor:
    """(B,N,C) → (B,C). ``max`` rather than ``amax``: its backward scatters the gradient to one point per channel
    (one pass) where ``amax``'s splits it over ties (several passes). The same parameter gradients: the pooled
    features are ReLU outputs or masked, so a tie at 0 gets no gradient either way, and a tie above 0 (a
    duplicated point) passes the same sum through identical computations."""
    return features.max(dim=1).values


def _row_chunks(rows: Tensor, size: int) -> tuple[Tensor, ...]:
    return rows.split(size) if rows.shape[0] else ()


def _max_of_chunks(maxima: list[Tensor], width: int, like: Tensor) -> Tensor:
    """Max over the per-chunk maxima of non-negative features; 0 without points (the masked max's value)."""
    return torch.stack(maxima).amax(0) if maxima else like.new_zeros(width)


Folded = list[tuple[Tensor, Tensor]]  # (weight, bias) of per-point layers with their BatchNorm folded in


def _run_folded(x: Tensor, layers: Folded, keep: int | None = None) -> tuple[Tensor, Tensor | None]:
    """Rows (M, C) through folded per-point layers (``relu(x Wᵀ + b)``): the output and layer ``keep``'s."""
    kept = None
    for k, (weight, bias) in enumerate(layers):
        x = F.linear(x, weight, bias).relu_()
        if k == keep:
            kept = x
    return x, kept


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
        w = partial(scaled, width=width, minimum=MIN_CHANNELS)
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
        self.pooled_point_dim = per_cloud - (0 if fusion else global_dim)  # pooled per-point features (the rest: global)
        self.chunk_rows = INFERENCE_CHUNK_ROWS
        dims = [2 * per_cloud, w(2048), w(1024), w(512), w(256)]
        self.regressor = nn.Sequential(
            *[
                nn.Sequential(nn.Linear(a, b, bias=False), nn.BatchNorm1d(b), nn.ReLU(inplace=True))
                for a, b in zip(dims[:-1], dims[1:])
            ],
            nn.Linear(dims[-1], 7),
        )

    def encode(self, points: Tensor, stats: list[VarMean] | None = None) -> tuple[Tensor, Tensor]:
        """Per-point features, independent of the masks: the 64-wide local one and the last (1024-wide) one.
        ``stats`` collects each layer's BatchNorm batch statistics."""
        x, local = points, points
        for k, layer in enumerate(self.encoder):
            x = layer(x, stats)
            if k == 1:
                local = x
        return local, x

    def fuse_and_decode(
        self, local: Tensor, own: Tensor, other: Tensor, mask: Tensor | None
    ) -> tuple[Tensor, list[Tensor], Tensor | None]:
        """Fused features g (masked), mask-head intermediates h (masked) and mask logits (B,N,2); ``mask``
        None: every point kept.

        ``fusion_masking="official"`` (official code, ``model/module.py`` ``Encoder.forward`` and
        ``Fusion.forward``): the 64-wide local feature is masked before fusion and only the fusion
        output is masked. ``"every_layer"``: the local input unmasked, every fusion layer's output masked.
        """
        every_layer = self.fusion_masking == "every_layer"
        # fusion input: cat(local, own, other) per point, the two global features broadcast
        x = self.fusion[0].forward_with_global(local if every_layer else _masked(local, mask), torch.cat((own, other), dim=-1))
        for layer in self.fusion[1:]:
            x = layer(_masked(x, mask) if every_layer else x)
        x = _masked(x, mask)
        intermediates: list[Tensor] = []
        logits = None
        if self.mask_module:
            h = x
            for layer in self.decoder:
                h = layer(h)
                intermediates.append(_masked(h, mask))
            logits = self.mask_logits(h)
        return x, intermediates, logits

    def forward(
        self, src: Tensor, ref: Tensor, mask_src: Tensor | None, mask_ref: Tensor | None, ref_cache: dict | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """Quaternion (B,4), translation (B,3) and mask logits of both clouds. Masks (B,N) of 0/1, or None when
        every point is kept. ``ref_cache`` (weights shared over iterations): one dict for all the iterations of
        a forward pass, in which the reference cloud's encoding is kept for reuse."""
        if not (self.training or torch.is_grad_enabled() or torch.compiler.is_compiling()) and src.device.type == "cpu":
            return self._infer(src, ref, mask_src, mask_ref, ref_cache)
        local_s, feat_s = self.encode(src)
        local_r, feat_r = self._encode_reference(ref, ref_cache)
        glob_s, glob_r = _max_over_points(_masked(feat_s, mask_src)), _max_over_points(_masked(feat_r, mask_ref))
        pooled, logits = [], []
        for local, own, other, mask in ((local_s, glob_s, glob_r, mask_src), (local_r, glob_r, glob_s, mask_ref)):
            fused, inter, lg = (None, [], None)
            if self.fusion is not None:
                fused, inter, lg = self.fuse_and_decode(local, own, other, mask)
            # the parts are masked already; the masked max of the masked 1024-wide feature is the global feature
            parts = [_max_over_points(fused) if self.fusion_enabled else own]
            if self.connection:
                parts += [_max_over_points(h) for h in inter]
            pooled.append(torch.cat(parts, dim=-1))
            logits.append(lg)
        return self._regress(pooled) + (logits[0], logits[1])

    def _regress(self, pooled: list[Tensor]) -> tuple[Tensor, Tensor]:
        out = self.regressor(torch.cat(pooled, dim=-1))
        return quat_normalize(out[:, :4]), out[:, 4:]

    def _encode_reference(self, ref: Tensor, cache: dict | None) -> tuple[Tensor, Tensor]:
        """``encode(ref)``, computed once per forward pass when the weights are shared (``cache``); the later
        calls' BatchNorm running-statistics updates are replayed from the first call's batch statistics."""
        if cache is None:
            return self.encode(ref)
        if "batched" not in cache:
            stats: list[VarMean] | None = [] if self.training else None
            cache["batched"] = (*self.encode(ref, stats), stats)
        else:
            for layer, var_mean in zip(self.encoder, cache["batched"][2] or ()):
                layer.replay_running_update(var_mean)
        return cache["batched"][:2]

    def _infer(
        self, src: Tensor, ref: Tensor, mask_src: Tensor | None, mask_ref: Tensor | None, ref_cache: dict | None
    ) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """``forward`` in CPU inference: cloud by cloud, kept points only, in cache-sized chunks, BatchNorm folded."""
        encoder = [layer.folded() for layer in self.encoder]
        local_s, glob_s = self._encode_kept(src, mask_src, encoder)
        cached = (ref_cache or {}).get("kept")
        if cached is not None and cached[0] is mask_ref:  # the same weights and kept points: the same features
            local_r, glob_r = cached[1]
        else:
            local_r, glob_r = self._encode_kept(ref, mask_ref, encoder)
            if ref_cache is not None:
                ref_cache["kept"] = (mask_ref, (local_r, glob_r))
        if self.fusion is None:
            return self._regress([glob_s, glob_r]) + (None, None)
        fusion = [layer.folded() for layer in self.fusion]
        decoder = [layer.folded() for layer in self.decoder] if self.mask_module else []
        pooled_s, logits_s = self._fuse_kept(local_s, glob_s, glob_r, mask_src, src.shape[1], fusion, decoder)
        pooled_r, logits_r = self._fuse_kept(local_r, glob_r, glob_s, mask_ref, ref.shape[1], fusion, decoder)
        return self._regress([pooled_s, pooled_r]) + (logits_s, logits_r)

    def _encode_kept(self, points: Tensor, mask: Tensor | None, encoder: Folded) -> tuple[list[list[Tensor]], Tensor]:
        """Per cloud: the local features of its kept points, chunk by chunk, and the masked global features (B, C)."""
        local, glob = [], []
        for b, cloud in enumerate(points):
            chunks, maxima = [], []
            for x in _row_chunks(cloud if mask is None else cloud[mask[b] > 0], self.chunk_rows):
                x, local_rows = _run_folded(x, encoder, keep=1)
                chunks.append(local_rows)
                maxima.append(x.amax(0))
            local.append(chunks)
            glob.append(_max_of_chunks(maxima, encoder[-1][0].shape[0], points))
        return local, torch.stack(glob)

    def _fuse_kept(
        self, local: list[list[Tensor]], own: Tensor, other: Tensor, mask: Tensor | None, n: int, fusion: Folded, decoder: Folded
    ) -> tuple[Tensor, Tensor | None]:
        """Pooled features (B, P) and mask logits (B, N, 2) (None without a mask module) from ``_encode_kept``."""
        (weight, bias), *later = fusion  # the first layer's input: local features, and global ones per cloud
        c_local = weight.shape[1] - 2 * own.shape[1]
        biases = F.linear(torch.cat((own, other), dim=-1), weight[:, c_local:], bias)  # the global part, once per cloud
        first = weight[:, :c_local].contiguous()
        masked_logits = None
        if mask is not None and self.mask_module:  # a masked-out point's: the decoder's on zero fused features
            masked_logits = self.mask_logits(_run_folded(own.new_zeros(1, decoder[0][0].shape[1]), decoder)[0])[0]
        pooled, logits = [], []
        for b, chunks in enumerate(local):
            maxima, kept_logits = [], []
            for x in chunks:
                x = F.linear(x, first, biases[b]).relu_()
                parts, lg = self._fuse_rows(x, later, decoder)
                if parts:
                    maxima.append(torch.cat([p.amax(0) for p in parts]))
                kept_logits.append(lg)
            point_part = _max_of_chunks(maxima, self.pooled_point_dim, own)
            pooled.append(point_part if self.fusion_enabled else torch.cat((own[b], point_part)))
            if masked_logits is not None:
                cloud_logits = masked_logits.expand(n, 2).clone()
                if kept_logits:
                    cloud_logits[mask[b] > 0] = torch.cat(kept_logits)
                logits.append(cloud_logits)
            elif self.mask_module:
                logits.append(torch.cat(kept_logits))
        return torch.stack(pooled), torch.stack(logits) if self.mask_module else None

    def _fuse_rows(self, x: Tensor, later: Folded, decoder: Folded) -> tuple[list[Tensor], Tensor | None]:
        """A chunk of kept points after fusion's first layer → the per-point features to pool and the mask logits."""
        x, _ = _run_folded(x, later)
        parts = [x] if self.fusion_enabled else []
        if not self.mask_module:
            return parts, None
        for weight, bias in decoder:
            x = F.linear(x, weight, bias).relu_()
            if self.connection:
                parts.append(x)
        return parts, self.mask_logits(x)


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
        mask_ce_reduction: str = "per_cloud",
    ) -> None:
        super().__init__()
        if mask_ce_reduction not in MASK_CE_REDUCTIONS:
            raise ValueError(f"mask_ce_reduction must be one of {MASK_CE_REDUCTIONS}, got {mask_ce_reduction!r}")
        if fusion_masking not in FUSION_MASKINGS:
            raise ValueError(f"fusion_masking must be one of {FUSION_MASKINGS}, got {fusion_masking!r}")
        if mask_mode not in MASK_MODES:
            raise ValueError(f"mask_mode must be one of {MASK_MODES}, got {mask_mode!r}")
        if trans_loss not in TRANSLATION_LOSSES:
            raise ValueError(f"trans_loss must be one of {TRANSLATION_LOSSES}, got {trans_loss!r}")
        if num_iters < 1:
            raise ValueError(f"num_iters must be >= 1, got {num_iters}")
        for name, value in (("mask_loss", mask_loss), ("connection", connection)):
            if value and not mask_module:  # (recorded true, but there would be no mask to train or connect)
                raise ValueError(f"{name}=true needs the mask module, which mask_module=false removes: set "
                                 f"model.network.{name}=false too (Table 3's B: +model/ablation=B)")
        self.num_iters, self.share_weights = num_iters, share_weights
        self.mask_module, self.mask_loss_enabled = mask_module, mask_loss and mask_module
        self.mask_start_iter, self.mask_mode, self.topk = mask_start_iter, mask_mode, topk
        self.overlap_dist = overlap_dist
        self.rot_loss_weight, self.trans_loss_weight, self.trans_loss = rot_loss_weight, trans_loss_weight, trans_loss
        self.mask_ce_reduction = mask_ce_reduction
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
        if self.topk >= logits.shape[1]:
            raise ConfigError(f"model.network.topk={self.topk} keeps every one of the {logits.shape[1]} points of a "
                              f"cloud: the top-k masks would mask nothing; choose topk < {logits.shape[1]}")
        k = self.topk
        idx = logits.softmax(dim=-1)[..., 1].topk(k, dim=1).indices
        return torch.zeros_like(logits[..., 0]).scatter_(1, idx, 1.0)

    @torch.no_grad()
    def overlap_labels(
        self, src: Tensor, ref: Tensor, transform_gt: Tensor, mask_src: Tensor | None, mask_ref: Tensor | None
    ) -> tuple[Tensor, Tensor]:
        """1 where a point's nearest neighbour in the other cloud, under the ground truth, is closer than
        ``overlap_dist``; points already masked out never match (masks: both, or None for every point kept)."""
        return self._labels(self._close_pairs(src, ref, transform_gt), mask_src, mask_ref)

    @torch.no_grad()
    def _close_pairs(self, src: Tensor, ref: Tensor, transform_gt: Tensor) -> Tensor:
        """(B,N,M) 1.0 where the source point moved by the ground truth lies closer than ``overlap_dist`` to the
        reference point: the same in every iteration, only the masks change."""
        return (torch.cdist(se3_apply(_full(transform_gt), _full(src)), _full(ref)) < self.overlap_dist).to(_full(src).dtype)

    def step_bytes(self, batch: int, n: int, m: int, training: bool) -> int:
        """A lower bound of the memory a forward pass on ``batch`` pairs of ``n`` and ``m`` points with the ground
        truth holds (its point budget, :mod:`src.run.memory`): the (B,N,M) close pairs (float32, made from a bool
        matrix while the distances or the float32 copy exist: 5 bytes a pair at the peak, 4 kept) and, in training,
        one float32 output per point-wise layer and iteration, kept for the backward pass (the reference's encoder
        outputs once, as with shared weights)."""
        pairs = batch * n * m if self.mask_module else 0
        if not training:
            return 5 * pairs
        block = self.block(0)
        width = {name: sum(layer.linear.out_features for layer in getattr(block, name, None) or ())
                 for name in ("encoder", "fusion", "decoder")}
        later = width["fusion"] + width["decoder"]
        outputs = self.num_iters * (n * (width["encoder"] + later) + m * later) + m * width["encoder"]
        return 4 * pairs + 4 * batch * outputs

    @torch.no_grad()
    def _labels(self, close: Tensor, mask_src: Tensor | None, mask_ref: Tensor | None) -> tuple[Tensor, Tensor]:
        if mask_src is None:
            return close.amax(dim=2).long(), close.amax(dim=1).long()
        mask_src, mask_ref = mask_src.to(close.dtype), mask_ref.to(close.dtype)
        kept_neighbours_src = torch.bmm(close, mask_ref.unsqueeze(2)).squeeze(2)  # counts of kept close points
        kept_neighbours_ref = torch.bmm(mask_src.unsqueeze(1), close).squeeze(1)
        return ((kept_neighbours_src > 0) & (mask_src > 0)).long(), ((kept_neighbours_ref > 0) & (mask_ref > 0)).long()

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        b = points_src.shape[0]
        all_kept = (points_src.new_ones(b, points_src.shape[1]), points_ref.new_ones(b, points_ref.shape[1]))
        mask_src = mask_ref = None  # every point kept until the first masks (computed as None: not applied)
        ref_cache: dict | None = {} if self.share_weights else None
        close = None  # (B,N,M) close pairs under the ground truth, for the mask labels
        quat = points_src.new_tensor([1.0, 0.0, 0.0, 0.0]).expand(b, 4)
        trans = points_src.new_zeros(b, 3)
        transform = se3_from_rt(quat_to_matrix(quat), trans)
        out: dict[str, list] = {"transforms": [], "quats": [], "translations": [], "mask_logits": [], "mask_labels": [], "masks": []}
        full_precision = torch.autocast(points_src.device.type, enabled=False)  # poses stay float32 under bf16
        for i in range(self.num_iters):
            with full_precision:
                moved = se3_apply(transform.detach(), _full(points_src))
            d_quat, d_trans, logits_src, logits_ref = self.block(i)(moved, points_ref, mask_src, mask_ref, ref_cache)
            with full_precision:
                d_quat, d_trans = quat_normalize(_full(d_quat)), _full(d_trans)
                quat_prev, trans_prev = quat.detach(), trans.detach()
                quat = quat_multiply(d_quat, quat_prev)
                trans = (quat_to_matrix(d_quat) @ trans_prev.unsqueeze(-1)).squeeze(-1) + d_trans
                transform = se3_from_rt(quat_to_matrix(quat), trans)
                out["transforms"].append(transform)
            out["quats"].append(quat)
            out["translations"].append(trans)
            out["masks"].append(all_kept if mask_src is None else (mask_src, mask_ref))
            if self.mask_module:
                out["mask_logits"].append((logits_src, logits_ref))
                if transform_gt is not None:
                    with full_precision:
                        close = self._close_pairs(points_src, points_ref, transform_gt) if close is None else close
                        unchanged = mask_src is None and out["mask_labels"]  # still no masks: the same labels
                        out["mask_labels"].append(out["mask_labels"][-1] if unchanged else self._labels(close, mask_src, mask_ref))
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
                ce = partial(weighted_mask_cross_entropy, class_weights=self.mask_class_weights, reduction=self.mask_ce_reduction)
                terms["loss/mask"] = terms["loss/mask"] + 0.5 * (ce(logits_src, labels_src) + ce(logits_ref, labels_ref))
        terms["loss"] = self.rot_loss_weight * terms["loss/quat"] + self.trans_loss_weight * terms["loss/trans"] + terms["loss/mask"]
        return terms


def weighted_mask_cross_entropy(logits: Tensor, labels: Tensor, class_weights: Tensor, reduction: str = "per_cloud") -> Tensor:
    """Class-weighted two-class cross-entropy of mask logits (B,N,2) against labels (B,N).

    ``per_cloud``: Σₙ w·nll / Σₙ w for each cloud, then the mean over the batch (the official
    ``frequency_weighted_cross_entropy``); ``batch``: one ratio over all B·N points."""
    nll = F.cross_entropy(_full(logits).reshape(-1, 2), labels.reshape(-1), reduction="none").view(labels.shape)
    weights = class_weights[labels]
    if reduction == "per_cloud":
        return ((weights * nll).sum(dim=1) / weights.sum(dim=1)).mean()
    return (weights * nll).sum() / weights.sum()


def _init_weights(module: nn.Module) -> None:
    """Official init: Kaiming-normal weights (a=√5), biases uniform in ±1/√fan_in."""
    if isinstance(module, nn.Linear):
        nn.init.kaiming_normal_(module.weight, a=math.sqrt(5))
        if module.bias is not None:
            fan_in = module.weight[0].numel()
            bound = 1 / math.sqrt(fan_in)
            nn.init.uniform_(module.bias, -bound, bound)
