"""Global-feature registration blocks shared by PointNetLK, FMR and DeepGMR (one copy each).

* :func:`se3_exp` — the se(3) exponential map, twist ``(ω1, ω2, ω3, v1, v2, v3)`` (rotation first, the
  order of PointNetLK's and FMR's code) → (…, 4, 4); closed form (Rodrigues + the left Jacobian V)
  with Taylor series near zero, so it is exact and differentiable everywhere, including at 0.
* :func:`lk_jacobian` — PointNetLK's finite-difference Jacobian of a global feature φ w.r.t. the six
  twist parameters at the template: ``J_k = (φ(P) − φ(exp(−δ_k e_k) P)) / δ_k`` (a backward
  difference of ξ ↦ φ(exp(ξ) P) at ξ = 0, step δ = 1e-2 in both official codes).
* :func:`pointnet_jacobian` — PointNetLK-Revisited's analytical Jacobian of a PointNet's max-pooled
  feature w.r.t. the twist: the chain rule through the per-point layers (Linear, eval-mode BatchNorm,
  ReLU mask) at the point that wins each feature's max pool, times the warp Jacobian of ``exp(ξ)·p``.
* :func:`inverse_compositional_lk` — the inverse-compositional LK loop of PointNetLK, FMR and
  PointNetLK-Revisited: J (finite differences, or a ``jacobian_fn``) and its pseudo-inverse once at
  the template, then ``r = φ(g·source) − φ(template)``, ``Δξ = −J⁺ r``, ``g ← exp(Δξ)·g``, stopped
  when max‖Δξ‖ < xtol (1e-7) or after ``max_iter``. :func:`lk_register` wraps it with the official
  mean-centring of both clouds.
* :class:`FeatureMetricDecoder` and :func:`chamfer_loss` — FMR's decoder (global feature → points
  through FC 1024-1024-512-256-3·n with BatchNorm/ReLU and a final tanh) and its Chamfer loss
  (squared distances, mean of each direction, as FMR's code).
* :func:`gmm_posterior`, :func:`gmm_params` and :func:`gmm_register` — DeepGMR's point-to-component
  responsibilities, the weighted GMM parameters (π, μ, isotropic variance) they induce, and the
  closed-form weighted Procrustes between two GMMs.
* :func:`rri_features` — the rigorously rotation-invariant (RRI) point features of Chen et al.,
  CVPR 2019 (ClusterNet), that DeepGMR feeds its network: the full RRI representation, not a
  simplification (see the function for the one deviation from DeepGMR's NumPy code).
* :func:`eval_mode` — run a module in evaluation mode (PointNetLK/FMR freeze BatchNorm inside LK);
  :func:`full_precision` — switch autocast off: finite differences with δ = 1e-2 and the GMM moments
  are meaningless in bfloat16 (``trainer=gpu`` trains in bf16-mixed), so LK, the Chamfer loss and the
  GMM steps always run in float32 (the networks outside them may still run in bf16).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.encoders import knn_indices
from baselines.learned.common.layers import MLP
from baselines.learned.common.procrustes import kabsch_rotation, weighted_procrustes
from src.geometry import se3_apply, se3_from_rt
from src.metrics import chamfer_distance

# ---------------------------------------------------------------------------------------------
# se(3)
# ---------------------------------------------------------------------------------------------


def skew(w: Tensor) -> Tensor:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): ``skew(w) @ x = w × x``."""
    zero = torch.zeros_like(w[..., 0])
    w1, w2, w3 = w.unbind(-1)
    rows = (zero, -w3, w2, w3, zero, -w1, -w2, w1, zero)
    return torch.stack(rows, dim=-1).reshape(*w.shape[:-1], 3, 3)


_TAYLOR_THETA2 = 1e-2  # below θ² = 0.01 the series (error < 1e-13) replace the cancelling closed forms


def se3_exp(twist: Tensor) -> Tensor:
    """exp: se(3) → SE(3) for twists (..., 6) = (ω, v) → homogeneous (..., 4, 4).

    ``R = I + A W + B W²``, ``t = (I + B W + C W²) v`` with ``W = skew(ω)``, θ = ‖ω‖,
    A = sin θ/θ, B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³ (Taylor series for small θ).
    """
    w, v = twist[..., :3], twist[..., 3:]
    theta2 = (w * w).sum(dim=-1)
    small = theta2 < _TAYLOR_THETA2
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = theta2_safe.sqrt()
    sin, cos = torch.sin(theta), torch.cos(theta)
    t2, t4, t6 = theta2, theta2 * theta2, theta2 * theta2 * theta2
    a = torch.where(small, 1 - t2 / 6 + t4 / 120 - t6 / 5040, sin / theta)
    b = torch.where(small, 0.5 - t2 / 24 + t4 / 720 - t6 / 40320, (1 - cos) / theta2_safe)
    c = torch.where(small, 1 / 6 - t2 / 120 + t4 / 5040 - t6 / 362880, (theta - sin) / (theta2_safe * theta))
    wx = skew(w)
    wx2 = wx @ wx
    eye = torch.eye(3, dtype=twist.dtype, device=twist.device)
    a, b, c = a[..., None, None], b[..., None, None], c[..., None, None]
    rot = eye + a * wx + b * wx2
    left_jacobian = eye + b * wx + c * wx2
    return se3_from_rt(rot, (left_jacobian @ v.unsqueeze(-1)).squeeze(-1))


def translation_matrix(t: Tensor) -> Tensor:
    """Pure translations (..., 4, 4) by (..., 3)."""
    eye = torch.eye(3, dtype=t.dtype, device=t.device).expand(*t.shape[:-1], 3, 3)
    return se3_from_rt(eye, t)


def composed_identity_error(g: Tensor, h: Tensor) -> Tensor:
    """Per-sample ‖g·h − I‖²_F (B,) — the transform losses of PointNetLK/FMR (g = estimate,
    h = inverse ground truth) and DeepGMR, which differ only in reduction."""
    eye = torch.eye(4, dtype=g.dtype, device=g.device)
    return ((g @ h - eye) ** 2).sum(dim=(-2, -1))


# ---------------------------------------------------------------------------------------------
# Lucas–Kanade on global features (PointNetLK, FMR)
# ---------------------------------------------------------------------------------------------

FeatureFn = Callable[[Tensor], Tensor]
#: points (B,N,3) -> (global feature φ (B,K), Jacobian ∂φ(exp(ξ)·P)/∂ξ at ξ = 0 (B,K,6))
JacobianFn = Callable[[Tensor], tuple[Tensor, Tensor]]


@contextlib.contextmanager
def eval_mode(module: nn.Module) -> Iterator[nn.Module]:
    """Temporarily put ``module`` in eval mode (BatchNorm uses its running statistics), then restore."""
    training = module.training
    module.eval()
    try:
        yield module
    finally:
        module.train(training)


def full_precision(device: torch.device | str) -> contextlib.AbstractContextManager:
    """Autocast disabled on ``device``'s type: the enclosed ops run in the inputs' (float32) precision."""
    return torch.autocast(device_type=torch.device(device).type, enabled=False)


def at_least_fp32(x: Tensor) -> Tensor:
    """``x`` in float32 if it is in a lower precision (float64 stays float64)."""
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


def register_lk_delta(module: nn.Module, delta: float, learn: bool) -> None:
    """``module.delta`` (1, 6): the twist steps δ of :func:`lk_jacobian`, all ``delta``; a parameter if
    ``learn`` (FMR learns it), else a buffer (PointNetLK)."""
    step = torch.full((1, 6), float(delta))
    if learn:
        module.delta = nn.Parameter(step)
    else:
        module.register_buffer("delta", step)


def lk_jacobian(feature_fn: FeatureFn, points: Tensor, delta: Tensor, features: Tensor | None = None) -> Tensor:
    """Finite-difference Jacobian (B, K, 6) of the global feature w.r.t. the twist at ``points`` (B,N,3).

    ``J[:, :, k] = (φ(P) − φ(exp(−δ_k e_k) P)) / δ_k`` — PointNetLK's backward difference of
    ξ ↦ φ(exp(ξ) P) at 0 (``approx_Jic`` in its code). ``delta`` is (6,), (1,6) or (B,6); the six
    perturbed copies of every cloud go through ``feature_fn`` as one batch of B·6 clouds, so
    ``feature_fn`` must be per-cloud (BatchNorm in eval mode). ``features`` = φ(P) if already known.
    Differentiable w.r.t. the network (through φ) and δ (FMR learns it).
    """
    b, n, _ = points.shape
    steps = delta.reshape(-1, 6).to(points).expand(b, 6)
    perturbations = se3_exp(-torch.diag_embed(steps))  # (B, 6, 4, 4)
    moved = se3_apply(perturbations, points.unsqueeze(1))  # (B, 6, N, 3)
    if features is None:
        features = feature_fn(points)
    perturbed = feature_fn(moved.reshape(b * 6, n, 3)).reshape(b, 6, -1)
    return ((features.unsqueeze(1) - perturbed) / steps.unsqueeze(-1)).transpose(1, 2)


def lk_pseudo_inverse(jacobian: Tensor) -> Tensor:
    """(JᵀJ)⁻¹Jᵀ (B, 6, K), solved in float64. A singular JᵀJ (the official code then gives up and
    returns the identity) gives a zero row block here, i.e. no update for that sample."""
    j = jacobian.double()
    jt = j.transpose(1, 2)
    inverse, info = torch.linalg.inv_ex(jt @ j)
    ok = (info == 0) & torch.isfinite(inverse).flatten(1).all(dim=1)
    inverse = torch.where(ok[:, None, None], inverse, torch.zeros_like(inverse))
    return (inverse @ jt).to(jacobian.dtype)


@dataclass
class LKResult:
    """``transforms``: g (source → template) after each of the ``max_iter`` iterations (repeated after an
    early stop, as the official ``g_series``); ``residual``: the last φ(g·source) − φ(template) (B, K);
    ``previous_residual``: the one before it (None after a single iteration; the official ``prev_r``);
    ``iterations``: updates actually made; ``jacobian`` (B, K, 6)."""

    transforms: list[Tensor]
    residual: Tensor
    previous_residual: Tensor | None
    iterations: int
    jacobian: Tensor


def inverse_compositional_lk(
    feature_fn: FeatureFn,
    template: Tensor,
    source: Tensor,
    delta: Tensor | None,
    max_iter: int = 10,
    xtol: float = 1e-7,
    jacobian_fn: JacobianFn | None = None,
) -> LKResult:
    """Inverse-compositional LK on global features: find g with φ(g·source) ≈ φ(template).

    J (and J⁺) are computed once at the template — by finite differences with step ``delta``
    (:func:`lk_jacobian`), or by ``jacobian_fn`` (e.g. :func:`pointnet_jacobian`), which also returns
    φ(template); each iteration ``r = φ(g·source) − φ(template)``, ``Δξ = −J⁺ r``, ``g ← exp(Δξ) g``;
    stops when the largest ‖Δξ‖ of the batch is below ``xtol``. Gradients flow through every step
    (the official codes train through the whole loop) and through J unless ``jacobian_fn`` detaches it.
    """
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    b = template.shape[0]
    if jacobian_fn is None:
        f_template = feature_fn(template)
        jacobian = lk_jacobian(feature_fn, template, delta, f_template)
    else:
        f_template, jacobian = jacobian_fn(template)
    pinv = lk_pseudo_inverse(jacobian)
    g = torch.eye(4, dtype=template.dtype, device=template.device).expand(b, 4, 4)
    transforms: list[Tensor] = []
    residual = previous = None
    for _ in range(max_iter):
        previous, residual = residual, feature_fn(se3_apply(g, source)) - f_template
        dx = -(pinv @ residual.unsqueeze(-1)).squeeze(-1)
        if float(dx.detach().norm(dim=1).max()) < xtol:
            break
        g = se3_exp(dx) @ g
        transforms.append(g)
    iterations = len(transforms)
    transforms += [g] * (max_iter - iterations)
    return LKResult(transforms, residual, previous, iterations, jacobian)


def pointnet_jacobian(mlp: MLP, points: Tensor) -> tuple[Tensor, Tensor]:
    """Max-pooled PointNet feature φ(P) (B,K) of ``mlp`` and its analytical Jacobian (B,K,6)
    ∂φ(exp(ξ)·P)/∂ξ at ξ = 0 (the sign convention of :func:`lk_jacobian`).

    PointNetLK-Revisited (Li et al., CVPR 2021; ``utils.feature_jac``, ``compute_warp_jac`` and
    ``AnalyticalPointNetLK.Cal_Jac``): per point, ∂f/∂p is the product over the layers of the weight,
    the BatchNorm scale γ/√(σ²+ε) (running statistics: the module must be in eval mode) and the ReLU
    mask (pre-activation > 0); feature k takes it at the point that wins its max pool, times the warp
    Jacobian ∂(exp(ξ)p)/∂ξ = [−[p]× | I]. The official code differentiates exp(−ξ)p and updates with
    +J⁺r: the same step. The last layer is evaluated at the winning points only. J is detached (the
    official code builds it from detached weights and masks); φ keeps its graph. ``mlp`` must be
    Linear / BatchNorm / ReLU triples (a :class:`~baselines.learned.common.layers.MLP` with ``norm="batch"``).
    """
    layers = list(mlp.layers)
    if len(layers) % 3 or not all(
        isinstance(a, nn.Linear) and isinstance(b, nn.BatchNorm1d) and isinstance(c, nn.ReLU)
        for a, b, c in zip(layers[::3], layers[1::3], layers[2::3])
    ):
        raise ValueError("pointnet_jacobian needs Linear + BatchNorm + ReLU layers (an MLP with norm='batch')")
    if any(layer.training for layer in layers[1::3]):
        raise ValueError("pointnet_jacobian needs BatchNorm in eval mode (see eval_mode)")
    x, tangent = points, None  # tangent: ∂x/∂p (B, N, 3, C), per point
    blocks = [layers[i : i + 3] for i in range(0, len(layers), 3)]
    for i, (linear, norm, relu) in enumerate(blocks):
        pre = norm(linear(x))
        scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
        if i == len(blocks) - 1:
            x = relu(pre)
            break
        with torch.no_grad():
            step = linear.weight.t() * scale  # (C_in, C_out)
            tangent = step.expand(*points.shape[:2], *step.shape) if tangent is None else tangent @ step
            tangent = tangent * (pre > 0).unsqueeze(-2)
        x = relu(pre)
    features, winner = x.max(dim=1)  # (B, K): the point each feature's max pool takes
    with torch.no_grad():
        b, k = winner.shape
        index = winner.unsqueeze(-1)
        weight = linear.weight * scale.unsqueeze(-1)  # (K, C)
        if tangent is None:  # a single layer: ∂(Wp)/∂p = W everywhere
            at_winner = weight.expand(b, k, 3)
        else:
            gathered = tangent.gather(1, index.unsqueeze(-1).expand(b, k, 3, tangent.shape[-1]))  # (B,K,3,C)
            at_winner = torch.einsum("bkic,kc->bki", gathered, weight)
        at_winner = at_winner * (features > 0).unsqueeze(-1)  # the ReLU mask at the winner
        point = points.gather(1, index.expand(b, k, 3))  # (B,K,3)
        # ∂f/∂ξ = ∂f/∂p · [−[p]× | I]: the rotation part is p × ∂f/∂p
        jacobian = torch.cat((torch.linalg.cross(point, at_winner, dim=-1), at_winner), dim=-1)
    return features, jacobian


def center(points: Tensor) -> tuple[Tensor, Tensor]:
    """(points − mean, mean (B, 3))."""
    mean = points.mean(dim=1)
    return points - mean.unsqueeze(1), mean


def lk_register(
    feature_fn: FeatureFn,
    points_src: Tensor,
    points_ref: Tensor,
    delta: Tensor | None,
    max_iter: int = 10,
    xtol: float = 1e-7,
    jacobian_fn: JacobianFn | None = None,
) -> LKResult:
    """LK with the official mean-centring (``p0_zero_mean = p1_zero_mean = True``): the reference is the
    template, the source is moved; the returned transforms map the *uncentred* source to the reference,
    ``T(m_ref) · g · T(−m_src)`` (learning3d's ``postprocess_data`` composes ``T(−m_ref)`` instead, see
    :mod:`baselines.learned.pointnetlk`). Run ``feature_fn``'s module in eval mode (see
    :func:`eval_mode`). Runs in float32 even under autocast (:func:`full_precision`)."""
    with full_precision(points_src.device):
        src, mean_src = center(at_least_fp32(points_src))
        ref, mean_ref = center(at_least_fp32(points_ref))
        result = inverse_compositional_lk(feature_fn, ref, src, delta, max_iter, xtol, jacobian_fn)
        left, right = translation_matrix(mean_ref), translation_matrix(-mean_src)
        result.transforms = [left @ g @ right for g in result.transforms]
    return result


# ---------------------------------------------------------------------------------------------
# FMR's feature-metric decoder
# ---------------------------------------------------------------------------------------------


class FeatureMetricDecoder(nn.Module):
    """FMR's decoder: global feature (B, K) → ``num_points`` points (B, n, 3) in [−1, 1]³.

    FC K→K→K/2→K/4 (each Linear + BatchNorm + ReLU) then Linear K/4 → 3n and tanh, as FMR's
    ``Decoder(bottleneck_size=1024)``. The hidden Linears drop their bias (BatchNorm follows, same function).
    """

    def __init__(self, feature_dim: int = 1024, num_points: int = 2048) -> None:
        super().__init__()
        self.num_points = num_points
        dims = [feature_dim, feature_dim, feature_dim // 2, feature_dim // 4]
        layers: list[nn.Module] = []
        for c_in, c_out in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(c_in, c_out, bias=False), nn.BatchNorm1d(c_out), nn.ReLU(inplace=True)]
        self.mlp = nn.Sequential(*layers)
        self.out = nn.Linear(dims[-1], 3 * num_points)

    def forward(self, features: Tensor) -> Tensor:
        # The official output is viewed as (B, 3, n) then transposed; the order of a fully connected
        # output is arbitrary, so (B, n, 3) is the same family of functions.
        return torch.tanh(self.out(self.mlp(features))).reshape(-1, self.num_points, 3)


def chamfer_loss(a: Tensor, b: Tensor) -> Tensor:
    """Chamfer loss of FMR's code: mean over batch and points of the squared distance to the nearest
    point of the other cloud, summed over both directions (:func:`src.metrics.chamfer_distance` of
    squared distances, averaged over the batch). a (B,N,3), b (B,M,3) → scalar, in float32 even under
    autocast."""
    with full_precision(a.device):
        return chamfer_distance(at_least_fp32(a), at_least_fp32(b), squared=True).mean()


# ---------------------------------------------------------------------------------------------
# DeepGMR: GMM posterior, GMM parameters, closed-form GMM registration, RRI features
# ---------------------------------------------------------------------------------------------


def gmm_posterior(logits: Tensor) -> Tensor:
    """Point-to-component responsibilities γ (B, N, J): softmax of the network's logits over J."""
    return F.softmax(logits, dim=-1)


def gmm_params(gamma: Tensor, points: Tensor, eps: float = 1e-9) -> tuple[Tensor, Tensor, Tensor]:
    """GMM parameters induced by responsibilities γ (B,N,J) on points (B,N,3) (DeepGMR's M-step).

    Returns π (B,J) = mean_n γ, μ (B,J,3) = Σ_n γ x / (Nπ), and the isotropic variance (B,J)
    σ² = Σ_n γ ‖x − μ‖² / (Nπ). As DeepGMR's code, σ² is the *total* variance (sum over the three
    axes; the code returns it times I₃) — only ratios between components matter downstream.
    ``eps`` guards the divisions (the code has none; γ > 0 keeps Nπ > 0 except on underflow).
    """
    pi = gamma.mean(dim=1)
    npi = (pi * gamma.shape[1]).clamp_min(eps)
    mu = gamma.transpose(1, 2) @ points / npi.unsqueeze(-1)
    sq = ((points.unsqueeze(2) - mu.unsqueeze(1)) ** 2).sum(dim=-1)  # (B, N, J)
    sigma2 = (gamma * sq).sum(dim=1) / npi
    return pi, mu, sigma2


def gmm_register(
    pi_s: Tensor, mu_s: Tensor, mu_t: Tensor, sigma2_t: Tensor, exact: bool = False, eps: float = 1e-9
) -> Tensor:
    """Rigid (B,4,4) T aligning the source GMM's means to the target's: DeepGMR's closed-form
    minimiser of Σ_j π_j ‖T μ^s_j − μ^t_j‖² / σ²_j (isotropic target covariances).

    ``exact=False`` (DeepGMR's code, ``gmm_register``): cross-covariance weighted by π_j/σ²_j but
    both centroids weighted by π only. ``exact=True``: the exact weighted least-squares solution,
    :func:`weighted_procrustes` with weights π_j/σ²_j (centroids weighted the same way).
    """
    weights = pi_s / sigma2_t.clamp_min(eps)
    if exact:
        return weighted_procrustes(mu_s, mu_t, weights)
    c_s = (pi_s.unsqueeze(-1) * mu_s).sum(dim=1)
    c_t = (pi_s.unsqueeze(-1) * mu_t).sum(dim=1)
    cov = (mu_s - c_s.unsqueeze(1)).transpose(1, 2) @ (weights.unsqueeze(-1) * (mu_t - c_t.unsqueeze(1)))
    rot = kabsch_rotation(cov).to(mu_s.dtype)
    return se3_from_rt(rot, c_t - (rot @ c_s.unsqueeze(-1)).squeeze(-1))


#: The tangent projection of the RRI features: DeepGMR's code's, or the exact one (:func:`rri_features`).
RRI_PROJECTIONS = ("authors", "exact")


@torch.no_grad()
def rri_features(points: Tensor, k: int = 20, projection: str = "authors") -> Tensor:
    """Rigorously rotation-invariant features (B, N, 4k) of points (B, N, 3), as DeepGMR's input.

    Points are centred on their mean (DeepGMR's ``get_rri(pts - pts.mean(0), k)``). For each point p
    and each of its k nearest neighbours q (self excluded, nearest first): ``[‖p‖, ‖q‖, θ, φ]`` with
    θ = ∠(p, q) and φ ∈ [0, 2π) the smallest angle through which the projection (onto the plane ⊥ p)
    of another of the k neighbours turns, counter-clockwise about p̂, onto that of q (the RRI of
    Chen et al., ClusterNet, CVPR 2019, as DeepGMR's ``get_rri`` computes it). ``projection``:
    ``authors`` takes DeepGMR's q − (p̂·q̂)p (wentaoyuan/deepgmr data.py:35, rri.cu alike), which leaves
    the plane ⊥ p when ‖q‖ ≠ ‖p‖ and so changes φ's cosine; ``exact`` the projection q − (q·p̂)p̂.
    Both are rotation invariant.
    Not differentiable (computed once per cloud, as the official data loader does).
    """
    if projection not in RRI_PROJECTIONS:
        raise ValueError(f"projection must be one of {RRI_PROJECTIONS}, got {projection!r}")
    b, n, _ = points.shape
    p = points - points.mean(dim=1, keepdim=True)
    idx = knn_indices(p, k + 1)[..., 1:]  # (B, N, k)
    q = torch.gather(p.unsqueeze(1).expand(b, n, n, 3), 2, idx.unsqueeze(-1).expand(b, n, k, 3))
    r_p = p.norm(dim=-1, keepdim=True).clamp_min(1e-12)  # (B, N, 1)
    r_q = q.norm(dim=-1).clamp_min(1e-12)  # (B, N, k)
    p_hat = p / r_p
    dot = ((q / r_q.unsqueeze(-1)) * p_hat.unsqueeze(2)).sum(-1)  # p̂·q̂ (B, N, k)
    theta = torch.acos(dot.clamp(-1, 1))
    if projection == "authors":
        tangent = q - dot.unsqueeze(-1) * p.unsqueeze(2)  # (B, N, k, 3)
    else:
        tangent = q - (q * p_hat.unsqueeze(2)).sum(-1, keepdim=True) * p_hat.unsqueeze(2)
    # psi[a, b]: angle about p̂ from neighbour b's projection to neighbour a's, in [0, 2π)
    axis_cross = torch.cross(tangent, p_hat.unsqueeze(2).expand_as(tangent), dim=-1)  # T_a × p̂
    sin_psi = axis_cross @ tangent.transpose(-1, -2)  # [a, b] = T_b · (T_a × p̂) = (T_b × T_a) · p̂
    cos_psi = tangent @ tangent.transpose(-1, -2)
    psi = torch.remainder(torch.atan2(sin_psi, cos_psi), 2 * math.pi)
    psi = psi + torch.diag(torch.full((k,), float("inf"), dtype=psi.dtype, device=psi.device))
    phi = psi.amin(dim=-1)
    feats = torch.stack((r_p.expand(b, n, k), r_q, theta, phi), dim=-1)  # (B, N, k, 4)
    return feats.reshape(b, n, 4 * k)
