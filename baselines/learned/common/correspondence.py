"""Correspondence building blocks shared by the learned baselines (one copy each).

Everything works on channel-last tensors: points and per-point features are (B, N, C), per-edge
(neighbourhood) features are (B, N, k, C); the per-element layers are :mod:`baselines.learned.common.layers`.

* :class:`DGCNN` — the DGCNN edge-conv encoder of DCP (static graph on xyz, per-edge features carried
  through the layers, ReLU) and of PRNet (graph recomputed in feature space at every layer,
  LeakyReLU 0.2); :class:`EdgeConv` is one edge-conv layer (also used by IDAM's GNN). The first
  Linear of an edge convolution is computed per point and gathered (:func:`edge_linear`), the same
  function at 1/k of the cost.
* :class:`AttentionPointer` — DCP's "Pointer" φ: a one-block transformer encoder–decoder with
  pre-norm residual sub-layers, shared by both directions, returning φ(X, Y) and φ(Y, X);
  :class:`AuthorsLayerNorm` is the official code's LayerNorm.
* :func:`matching_logits`, :func:`soft_correspondence_svd` — DCP's soft pointer + SVD head, on top of
  :func:`~baselines.learned.common.procrustes.weighted_procrustes`.
* :func:`sinkhorn` — RPMNet's log-domain Sinkhorn normalisation with a slack row and column.
* :func:`gumbel_softmax` — PRNet's (straight-through) Gumbel-softmax with a per-sample temperature.
* :func:`estimate_normals` — batched PCA normals of the k nearest neighbours, signed consistently
  (away from the cloud's centroid, as the classical FGR baseline does), computed from the points a
  network receives (OMNet §4.2: RPMNet's normals are computed after pre-processing).
* :func:`ball_query`, :func:`ppf_features` — RPMNet's radius neighbourhoods and the point-pair
  features (angles via atan2(|a×b|, a·b), as PPFNet/RPMNet) with the xyz / Δxyz features.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.encoders import knn_indices
from baselines.learned.common.layers import MLP
from baselines.learned.common.procrustes import weighted_procrustes

EDGE_MODES = ("concat", "diff")
NORMAL_ORIENTATIONS = ("centroid", "none")


# --- graph / edge convolutions ------------------------------------------------------------------


def gather_neighbours(x: Tensor, idx: Tensor) -> Tensor:
    """Features (B, N, k, C) of the neighbours ``idx`` (B, N', k) of every point, from x (B, N, C)."""
    b, n_query, k = idx.shape
    flat = idx.reshape(b, n_query * k, 1).expand(-1, -1, x.shape[-1])
    return x.gather(1, flat).reshape(b, n_query, k, x.shape[-1])


def edge_features(x: Tensor, idx: Tensor, mode: str = "concat") -> Tensor:
    """Edge features (B, N, k, ·) of x (B, N, C) on the graph ``idx`` (B, N, k).

    ``"concat"``: [x_j, x_i] (DCP/PRNet official code), ``"diff"``: x_j − x_i (IDAM).
    """
    if mode not in EDGE_MODES:
        raise ValueError(f"edge mode must be one of {EDGE_MODES}, got {mode!r}")
    neighbours = gather_neighbours(x, idx)
    centre = x.unsqueeze(2).expand_as(neighbours)
    return torch.cat((neighbours, centre), dim=-1) if mode == "concat" else neighbours - centre


def edge_linear(x: Tensor, idx: Tensor, linear: nn.Linear, mode: str = "concat") -> Tensor:
    """``linear`` applied to the edge features of x (B, N, C) on the graph ``idx``: (B, N, k, C_out).

    Computed per point, then gathered: W[x_j, x_i] = W₁x_j + W₂x_i and W(x_j − x_i) = Wx_j − Wx_i, so
    the product costs N (not N·k) rows and the (B, N, k, 2C) edge tensor is never built. The result
    equals ``linear(edge_features(x, idx, mode))`` up to rounding.
    """
    if mode not in EDGE_MODES:
        raise ValueError(f"edge mode must be one of {EDGE_MODES}, got {mode!r}")
    c = x.shape[-1]
    if mode == "concat":
        neighbours, centre = F.linear(x, linear.weight[:, :c]), F.linear(x, linear.weight[:, c:], linear.bias)
        return gather_neighbours(neighbours, idx) + centre.unsqueeze(2)
    projected = F.linear(x, linear.weight)
    out = gather_neighbours(projected, idx) - projected.unsqueeze(2)
    return out if linear.bias is None else out + linear.bias


class EdgeConv(nn.Module):
    """One edge convolution: MLP on the edge features, then max over the k neighbours."""

    def __init__(self, channels: Sequence[int], mode: str = "concat", norm: str = "batch",
                 negative_slope: float = 0.0, last_activation: bool = True) -> None:
        super().__init__()
        self.mode = mode
        in_channels = channels[0] * (2 if mode == "concat" else 1)
        self.mlp = MLP([in_channels, *channels[1:]], norm=norm, negative_slope=negative_slope,
                       last_activation=last_activation)

    def forward(self, x: Tensor, idx: Tensor) -> Tensor:
        first, rest = self.mlp.layers[0], self.mlp.layers[1:]
        return rest(edge_linear(x, idx, first, self.mode)).amax(dim=2)


class DGCNN(nn.Module):
    """DGCNN encoder (Wang et al., 2019) as used by DCP and PRNet; (B, N, 3) → (B, N, emb_dims).

    ``dynamic=False`` (DCP): one k-NN graph on the coordinates; the per-edge features of the first
    edge convolution go through all the layers, each followed by a max over the neighbours.
    ``dynamic=True`` (PRNet): every layer is an edge convolution on a k-NN graph recomputed in the
    current feature space. In both, the per-layer max-pooled features are concatenated and mapped
    to ``emb_dims`` by a per-point Linear + BatchNorm + activation.
    """

    def __init__(self, channels: Sequence[int] = (64, 64, 128, 256), emb_dims: int = 512, k: int = 20,
                 dynamic: bool = False, negative_slope: float = 0.0) -> None:
        super().__init__()
        self.k, self.dynamic = k, dynamic
        self.layers = nn.ModuleList()
        c_prev = 3
        for i, c in enumerate(channels):
            if dynamic:
                self.layers.append(EdgeConv([c_prev, c], "concat", negative_slope=negative_slope))
            else:
                self.layers.append(MLP([6 if i == 0 else c_prev, c], negative_slope=negative_slope))
            c_prev = c
        self.fuse = MLP([sum(channels), emb_dims], negative_slope=negative_slope)

    @property
    def min_points(self) -> int:
        """Fewest points per cloud for the features it was trained on: the k-NN graph takes each point's k nearest
        (itself included; fewer points shrink every neighbourhood)."""
        return self.k

    def forward(self, points: Tensor) -> Tensor:
        k = min(self.k, points.shape[1])
        pooled: list[Tensor] = []
        if self.dynamic:
            x = points
            for layer in self.layers:
                x = layer(x, knn_indices(x.detach(), k))
                pooled.append(x)
        else:
            idx = knn_indices(points.detach(), k)
            for i, layer in enumerate(self.layers):
                # the first layer's product on the edge features [x_j, x_i], computed per point
                x = layer.layers[1:](edge_linear(points, idx, layer.layers[0])) if i == 0 else layer(x)
                pooled.append(x.amax(dim=2))
        return self.fuse(torch.cat(pooled, dim=-1))


# --- the attention "pointer" ---------------------------------------------------------------------


class _FeedForward(nn.Module):
    def __init__(self, d_model: int, ff_dims: int, dropout: float, negative_slope: float) -> None:
        super().__init__()
        self.w1, self.w2 = nn.Linear(d_model, ff_dims), nn.Linear(ff_dims, d_model)
        self.dropout, self.negative_slope = nn.Dropout(dropout), negative_slope

    def forward(self, x: Tensor) -> Tensor:
        h = F.leaky_relu(self.w1(x), self.negative_slope) if self.negative_slope > 0 else F.relu(self.w1(x))
        return self.w2(self.dropout(h))


class _Attention(nn.Module):
    """Multi-head scaled dot-product attention with q/k/v/out projections (biased)."""

    def __init__(self, d_model: int, n_heads: int, dropout: float) -> None:
        super().__init__()
        if d_model % n_heads:
            raise ValueError(f"d_model ({d_model}) must be divisible by n_heads ({n_heads})")
        self.n_heads, self.dropout = n_heads, dropout
        self.q, self.k, self.v, self.out = (nn.Linear(d_model, d_model) for _ in range(4))

    def forward(self, query: Tensor, key: Tensor, value: Tensor) -> Tensor:
        b, n, d = query.shape
        split = lambda t: t.reshape(b, t.shape[1], self.n_heads, d // self.n_heads).transpose(1, 2)  # noqa: E731
        y = F.scaled_dot_product_attention(split(self.q(query)), split(self.k(key)), split(self.v(value)),
                                           dropout_p=self.dropout if self.training else 0.0)
        return self.out(y.transpose(1, 2).reshape(b, n, d))


class AuthorsLayerNorm(nn.LayerNorm):
    """The official DCP/PRNet code's LayerNorm (PRNet ``model.py:159-169``): ``weight·(x − mean)/(std + ε) + bias``
    with the unbiased std and ε added to it; ``nn.LayerNorm`` takes the biased variance with ε inside the square
    root. The same parameters (``weight``, ``bias``) as ``nn.LayerNorm``."""

    def forward(self, x: Tensor) -> Tensor:
        return self.weight * (x - x.mean(-1, keepdim=True)) / (x.std(-1, keepdim=True) + self.eps) + self.bias


class _EncoderLayer(nn.Module):
    def __init__(self, d_model: int, n_heads: int, ff_dims: int, dropout: float, negative_slope: float,
                 norm: type[nn.LayerNorm]) -> None:
        super().__init__()
        self.self_attn = _Attention(d_model, n_heads, dropout)
        self.ff = _FeedForward(d_model, ff_dims, dropout, negative_slope)
        self.norms = nn.ModuleList(norm(d_model, eps=1e-6) for _ in range(2))

    def forward(self, x: Tensor) -> Tensor:
        h = self.norms[0](x)
        x = x + self.self_attn(h, h, h)
        return x + self.ff(self.norms[1](x))


class _DecoderLayer(nn.Module):
    def __init__(self, d_model: int, n_heads: int, ff_dims: int, dropout: float, negative_slope: float,
                 norm: type[nn.LayerNorm]) -> None:
        super().__init__()
        self.self_attn = _Attention(d_model, n_heads, dropout)
        self.cross_attn = _Attention(d_model, n_heads, dropout)
        self.ff = _FeedForward(d_model, ff_dims, dropout, negative_slope)
        self.norms = nn.ModuleList(norm(d_model, eps=1e-6) for _ in range(3))

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        h = self.norms[0](x)
        x = x + self.self_attn(h, h, h)
        x = x + self.cross_attn(self.norms[1](x), memory, memory)
        return x + self.ff(self.norms[2](x))


#: The LayerNorms of :class:`AttentionPointer`: the official code's (``authors``) and PyTorch's (``torch``).
LAYER_NORMS: dict[str, type[nn.Module]] = {"authors": AuthorsLayerNorm, "torch": nn.LayerNorm}


class AttentionPointer(nn.Module):
    """DCP's attention "pointer" φ (a transformer encoder–decoder, Vaswani et al.).

    ``forward(feat_src, feat_ref)`` returns (φ(src, ref), φ(ref, src)): each cloud's features are
    decoded against the other cloud's encoded features, with the same weights in both directions.
    Pre-norm residual sub-layers and a final LayerNorm in the encoder and the decoder, as the
    official DCP/PRNet code; ``negative_slope`` is the feed-forward LeakyReLU slope (0 = ReLU, DCP;
    0.2 for PRNet); ``layer_norm``: ``authors`` for the code's LayerNorm (:class:`AuthorsLayerNorm`), ``torch``
    for ``nn.LayerNorm``.
    """

    def __init__(self, d_model: int = 512, n_blocks: int = 1, n_heads: int = 4, ff_dims: int = 1024,
                 dropout: float = 0.0, negative_slope: float = 0.0, layer_norm: str = "torch") -> None:
        super().__init__()
        if layer_norm not in LAYER_NORMS:
            raise ValueError(f"layer_norm must be one of {sorted(LAYER_NORMS)}, got {layer_norm!r}")
        norm = LAYER_NORMS[layer_norm]
        args = (d_model, n_heads, ff_dims, dropout, negative_slope, norm)
        self.encoder = nn.ModuleList(_EncoderLayer(*args) for _ in range(n_blocks))
        self.decoder = nn.ModuleList(_DecoderLayer(*args) for _ in range(n_blocks))
        self.encoder_norm = norm(d_model, eps=1e-6)
        self.decoder_norm = norm(d_model, eps=1e-6)

    def attend(self, x: Tensor, other: Tensor) -> Tensor:
        """φ(x, other): ``other`` encoded, ``x`` decoded against it."""
        memory = other
        for layer in self.encoder:
            memory = layer(memory)
        memory = self.encoder_norm(memory)
        for layer in self.decoder:
            x = layer(x, memory)
        return self.decoder_norm(x)

    def forward(self, feat_src: Tensor, feat_ref: Tensor) -> tuple[Tensor, Tensor]:
        return self.attend(feat_src, feat_ref), self.attend(feat_ref, feat_src)


# --- soft correspondences + SVD, Sinkhorn, Gumbel-softmax ---------------------------------------


def matching_logits(feat_src: Tensor, feat_ref: Tensor) -> Tensor:
    """Scaled dot products (B, N, M) = feat_src · feat_refᵀ / √C (DCP's pointer scores)."""
    return feat_src @ feat_ref.transpose(1, 2) / math.sqrt(feat_src.shape[-1])


def soft_correspondence_svd(points_src: Tensor, points_ref: Tensor, matching: Tensor, weights: Tensor | None = None,
                            normalize_rows: bool = False, eps: float = 1e-5) -> tuple[Tensor, Tensor]:
    """Soft correspondences ``matching`` (B,N,M) @ points_ref, then the (weighted) Procrustes solve.

    ``normalize_rows`` divides by the row sums (RPMNet, whose Sinkhorn rows sum to ≤ 1); ``weights``
    (B,N) weight the source points (uniform if None). Returns (transform (B,4,4), corresponding
    points (B,N,3)).
    """
    corr = matching @ points_ref
    if normalize_rows:
        corr = corr / (matching.sum(dim=2, keepdim=True) + eps)
    return weighted_procrustes(points_src, corr, weights, eps=eps), corr


def sinkhorn(log_alpha: Tensor, n_iters: int = 5, slack: bool = True, return_padded: bool = False) -> Tensor:
    """Log-domain Sinkhorn normalisation of log-affinities (B, N, M) (RPMNet).

    With ``slack`` a zero log-affinity row and column are appended and left un-normalised, so every
    real row and column sums to ≤ 1 over the real entries (= 1 with its slack entry at convergence).
    Each iteration normalises the real rows, then the real columns. Returns the log of the matching
    matrix (B, N, M), or (B, N+1, M+1) with the slack row/column if ``return_padded``.
    """
    if not slack:
        for _ in range(n_iters):
            log_alpha = log_alpha - torch.logsumexp(log_alpha, dim=2, keepdim=True)
            log_alpha = log_alpha - torch.logsumexp(log_alpha, dim=1, keepdim=True)
        return log_alpha
    padded = F.pad(log_alpha, (0, 1, 0, 1), value=0.0)
    for _ in range(n_iters):
        rows = padded[:, :-1, :]
        padded = torch.cat((rows - torch.logsumexp(rows, dim=2, keepdim=True), padded[:, -1:, :]), dim=1)
        cols = padded[:, :, :-1]
        padded = torch.cat((cols - torch.logsumexp(cols, dim=1, keepdim=True), padded[:, :, -1:]), dim=2)
    return padded if return_padded else padded[:, :-1, :-1]


def gumbel_softmax(logits: Tensor, tau: Tensor | float = 1.0, hard: bool = True, dim: int = -1,
                   generator: torch.Generator | None = None) -> Tensor:
    """Gumbel-softmax sample of ``logits`` (Jang et al.); ``tau`` a float or a tensor broadcastable
    to ``logits`` (PRNet's per-pair temperature). ``hard``: one-hot forward value of the sampled
    argmax with the soft sample's gradient (straight-through estimator)."""
    uniform = torch.rand(logits.shape, dtype=logits.dtype, device=logits.device, generator=generator)
    gumbels = -torch.log((-torch.log(uniform.clamp_min(1e-20))).clamp_min(1e-20))
    soft = torch.softmax((logits + gumbels) / tau, dim=dim)
    if not hard:
        return soft
    one_hot = torch.zeros_like(soft).scatter_(dim, soft.argmax(dim=dim, keepdim=True), 1.0)
    return one_hot - soft.detach() + soft


# --- normals and point-pair features ------------------------------------------------------------


@torch.no_grad()
def estimate_normals(points: Tensor, k: int = 30, orientation: str = "centroid") -> Tensor:
    """Unit normals (B, N, 3): eigenvector of the smallest eigenvalue of the covariance of each
    point's k nearest neighbours (itself included). ``"centroid"`` signs every normal to point away
    from the cloud's centroid (rigid-motion equivariant, consistent within a cloud); ``"none"``
    keeps the eigen-solver's arbitrary sign. Not differentiated (normals are inputs)."""
    if orientation not in NORMAL_ORIENTATIONS:
        raise ValueError(f"orientation must be one of {NORMAL_ORIENTATIONS}, got {orientation!r}")
    k = min(k, points.shape[1])
    pts = points.double()
    neighbours = gather_neighbours(pts, knn_indices(pts, k))
    centred = neighbours - neighbours.mean(dim=2, keepdim=True)
    cov = centred.transpose(-1, -2) @ centred / k
    normals = torch.linalg.eigh(cov).eigenvectors[..., 0]  # ascending eigenvalues
    if orientation == "centroid":
        outward = pts - pts.mean(dim=1, keepdim=True)
        normals = torch.where((normals * outward).sum(-1, keepdim=True) < 0, -normals, normals)
    return normals.to(points.dtype)


@torch.no_grad()
def ball_query(points: Tensor, radius: float, num_neighbors: int) -> Tensor:
    """Indices (B, N, num_neighbors) of up to ``num_neighbors`` other points within ``radius`` of each
    point, lowest indices first (as PointNet++'s grouping), padded with the point's own index."""
    b, n, _ = points.shape
    sq_dist = torch.cdist(points, points).square()
    index = torch.arange(n, device=points.device)
    invalid = (sq_dist > radius**2) | torch.eye(n, dtype=torch.bool, device=points.device)
    key = torch.where(invalid, index + n, index).expand(b, n, n)  # valid indices first, in order
    k = min(num_neighbors, n)
    picked = key.topk(k, dim=-1, largest=False).values
    own = index.view(1, n, 1).expand(b, n, k)
    idx = torch.where(picked >= n, own, picked)
    if k < num_neighbors:
        idx = torch.cat((idx, own[..., :1].expand(b, n, num_neighbors - k)), dim=-1)
    return idx


def vector_angle(a: Tensor, b: Tensor) -> Tensor:
    """Angle between vectors (..., 3) as atan2(‖a×b‖, a·b) (0 when either is zero)."""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(dim=-1))


def ppf_features(points: Tensor, normals: Tensor, radius: float = 0.3, num_neighbors: int = 64) -> dict[str, Tensor]:
    """RPMNet's raw neighbourhood features of every point i with its ball neighbours j (B, N, k, ·):
    ``xyz`` (the point's coordinates, 3), ``dxyz`` (p_j − p_i, 3) and ``ppf`` (∠(n_i, d), ∠(n_j, d),
    ∠(n_i, n_j), ‖d‖ with d = p_j − p_i, 4)."""
    idx = ball_query(points, radius, num_neighbors)
    d = gather_neighbours(points, idx) - points.unsqueeze(2)
    n_i = normals.unsqueeze(2).expand_as(d)
    n_j = gather_neighbours(normals, idx)
    ppf = torch.stack((vector_angle(n_i, d), vector_angle(n_j, d), vector_angle(n_i, n_j), d.norm(dim=-1)), dim=-1)
    return {"xyz": points.unsqueeze(2).expand_as(d), "dxyz": d, "ppf": ppf}
