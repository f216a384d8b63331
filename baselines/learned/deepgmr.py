"""DeepGMR — Deep Gaussian Mixture Registration (Yuan et al., ECCV 2020).

From the paper: a network maps every point (through rotation-invariant RRI features) to
responsibilities γ over J latent Gaussian components; the GMM parameters (π, μ, Σ) of each cloud
follow in closed form from γ and the raw points, and the rigid transform between the two GMMs is the
closed-form weighted Procrustes between their means. Both directions are estimated (T₁₂ source →
reference, T₂₁ reference → source) and trained with transform losses only: ``mse(T₁₂·T_gt⁻¹, I) +
mse(T₂₁·T_gt, I)``.

Facts taken from the authors' code (wentaoyuan/deepgmr, ``model.py``, ``data.py``, ``train.py``,
README), not its code:

* input: RRI features of the centred cloud with k = 20 neighbours (4k = 80 channels) — the README's
  training commands all pass ``--use_rri``; without RRI, the centred xyz;
* network: per-point 80-64-128-256-1024 (Conv1d without bias + BatchNorm + ReLU), global max feature
  concatenated to every point, then 2048-512-256-128 (same layers) and a Conv1d 128 → J (with bias);
  J = ``n_clusters`` = 16, ``d_model`` = 1024; the optional T-net is off by default and not provided;
* γ = softmax over J; π = mean γ, μ = γ-weighted means, isotropic variance = γ-weighted mean squared
  distance to μ (summed over the axes); T from ``gmm_register`` (π-weighted centroids, cross-covariance
  weighted by π/σ², SVD with reflection fix) — see :func:`~baselines.learned.common.global_feature.gmm_register`;
* loss: ``F.mse_loss(T₁₂ @ inv(T_gt), I) + F.mse_loss(T₂₁ @ T_gt, I)`` (mean over the 16 entries and
  the batch);
* training recipe (Adam, ReduceLROnPlateau on the validation loss, batch, epochs, checkpoint):
  ``conf/recipe/deepgmr.yaml``.

Deviations: RRI is computed in the network's forward instead of the data loader, with the code's
tangent projection q − (p̂·q̂)p (data.py:35; ``rri=exact``: the exact projection onto the plane ⊥ p,
with which checkpoints written before this option were trained, see
:func:`~baselines.learned.common.global_feature.rri_features`); small ``eps`` guards the GMM
divisions; ``exact_procrustes`` switches to the exact weighted least-squares solve; ``width`` scales
the channels (1.0 = paper).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from baselines.learned.common.global_feature import (
    RRI_PROJECTIONS,
    at_least_fp32,
    composed_identity_error,
    full_precision,
    gmm_params,
    gmm_posterior,
    gmm_register,
    rri_features,
)
from baselines.learned.common.layers import MLP
from src.geometry import se3_inverse
from src.geometry.clouds import MIN_POINTS
from src.models.base import MIN_CHANNELS, scaled


class DeepGMRBackbone(nn.Module):
    """Per-point features → global max → per-point logits over the J components (B, N, J)."""

    def __init__(self, in_channels: int, d_model: int, n_clusters: int, width: float = 1.0) -> None:
        super().__init__()
        w = lambda c: scaled(c, width, minimum=MIN_CHANNELS)  # noqa: E731
        self.encoder = MLP((in_channels, w(64), w(128), w(256), w(d_model)))
        self.decoder = MLP((2 * w(d_model), w(512), w(256), w(128)))
        self.logits = nn.Linear(w(128), n_clusters)

    def forward(self, features: Tensor) -> Tensor:
        local = self.encoder(features)
        glob = local.amax(dim=1, keepdim=True).expand_as(local)
        return self.logits(self.decoder(torch.cat((local, glob), dim=-1)))


class DeepGMR(nn.Module):
    def __init__(
        self,
        d_model: int = 1024,
        n_clusters: int = 16,
        use_rri: bool = True,
        k: int = 20,
        width: float = 1.0,
        exact_procrustes: bool = False,
        rri: str = "authors",
    ) -> None:
        super().__init__()
        if rri not in RRI_PROJECTIONS:
            raise ValueError(f"rri must be one of {RRI_PROJECTIONS}, got {rri!r}")
        self.use_rri, self.k, self.exact_procrustes, self.rri = use_rri, k, exact_procrustes, rri
        self.backbone = DeepGMRBackbone(4 * k if use_rri else 3, d_model, n_clusters, width)

    def point_features(self, points: Tensor) -> Tensor:
        if self.use_rri:
            # neighbours and angles in float32 under bf16 autocast (the official code computes them in its NumPy
            # data loader): in bf16 their products round the angles and change the chosen neighbours
            with full_precision(points.device):
                return rri_features(at_least_fp32(points), self.k, self.rri)
        return points - points.mean(dim=1, keepdim=True)

    @property
    def min_points(self) -> int:
        """Fewest points per cloud: the RRI features take each point's k nearest other points."""
        return self.k + 1 if self.use_rri else MIN_POINTS

    @property
    def planar_blind(self) -> str:
        """Why a planar cloud leaves its rotation undetermined (``""``: it does not): on a plane every neighbour's
        projection (φ of the RRI features) falls on one line, so the features lose the turn's sense."""
        if not self.use_rri:
            return ""
        return "its RRI features lose the sense of each turn (every neighbour's projection falls on one line)"

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        logits_src = self.backbone(self.point_features(points_src))
        logits_ref = self.backbone(self.point_features(points_ref))
        with full_precision(points_src.device):  # GMM moments and Procrustes in float32 even under autocast
            points_src, points_ref = at_least_fp32(points_src), at_least_fp32(points_ref)
            gamma_src = gmm_posterior(logits_src.to(points_src.dtype))
            gamma_ref = gmm_posterior(logits_ref.to(points_ref.dtype))
            pi_s, mu_s, sigma2_s = gmm_params(gamma_src, points_src)
            pi_r, mu_r, sigma2_r = gmm_params(gamma_ref, points_ref)
            src_to_ref = gmm_register(pi_s, mu_s, mu_r, sigma2_r, exact=self.exact_procrustes)
            ref_to_src = gmm_register(pi_r, mu_r, mu_s, sigma2_s, exact=self.exact_procrustes)
        return {
            "transforms": [src_to_ref],
            "transform_reverse": ref_to_src,
            "gamma": (gamma_src, gamma_ref),
            "gmm_src": (pi_s, mu_s, sigma2_s),
            "gmm_ref": (pi_r, mu_r, sigma2_r),
        }

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        with full_precision(transform_gt.device):  # float32 even under bf16 autocast
            forward = composed_identity_error(outputs["transforms"][-1], se3_inverse(transform_gt)).mean() / 16
            reverse = composed_identity_error(outputs["transform_reverse"], transform_gt).mean() / 16
            return {"loss": forward + reverse, "loss/forward": forward, "loss/reverse": reverse}
