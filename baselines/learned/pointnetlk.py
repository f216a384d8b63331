"""PointNetLK (Aoki et al., CVPR 2019): PointNet global features registered by inverse-compositional
Lucas–Kanade with a finite-difference Jacobian.

``feature_init`` starts the encoder from PointNet features (a ``pointnet_classifier`` checkpoint or
``official:learning3d_pointnet_classifier_features``, :mod:`baselines.learned.published`), loaded when
training starts (:meth:`PointNetLK.train`). The facts taken from the authors' code, learning3d's variant,
the framework mapping and the deviations: ``docs/methods/pointnetlk.md``.
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
    register_lk_delta,
)
from baselines.learned.published import pointnet_features

from src.geometry import se3_inverse
from src.models.base import MIN_CHANNELS, scaled


def learning3d_reported_transform(transform: Tensor, points_src: Tensor, points_ref: Tensor) -> Tensor:
    """What learning3d's PointNetLK reports for the estimate ``transform`` (source → reference, (B,4,4)):
    its ``ops/data_utils.py`` builds the source's shift from the template's mean (``mean_shift``, line 19:
    ``-p0_m``), so ``postprocess_data`` returns ``T(m_ref)·g·T(−m_ref) = transform·T(m_src − m_ref)``."""
    shift = torch.eye(4, dtype=transform.dtype, device=transform.device).repeat(transform.shape[0], 1, 1)
    shift[:, :3, 3] = (points_src.mean(dim=1) - points_ref.mean(dim=1)).to(transform.dtype)
    return transform @ shift


def pointnet_channels(dim_k: int, width: float) -> tuple[int, ...]:
    """PointNetLK's / FMR's encoder channels 3-64-64-64-128-dim_k, scaled by ``width``."""
    return (3, *(scaled(c, width, minimum=MIN_CHANNELS) for c in (64, 64, 64, 128, dim_k)))


class PointNetLK(nn.Module):
    def __init__(
        self,
        dim_k: int = 1024,
        width: float = 1.0,
        max_iter: int = 10,
        eval_max_iter: int = 20,
        delta: float = 1e-2,
        learn_delta: bool = False,
        xtol: float = 1e-7,
        feature_loss_weight: float = 1.0,
        feature_init: str | None = None,
    ) -> None:
        super().__init__()
        self.max_iter, self.eval_max_iter, self.xtol = max_iter, eval_max_iter, xtol
        self.feature_loss_weight, self.feature_init = feature_loss_weight, feature_init
        self.encoder = PointNetEncoder(pointnet_channels(dim_k, width))
        register_lk_delta(self, delta, learn_delta)
        self._weights_loaded = False

    def train(self, mode: bool = True) -> PointNetLK:
        """Also applies ``feature_init`` the first time training starts on fresh weights."""
        if mode and self.feature_init and not self._weights_loaded:
            self.encoder.load_state_dict(pointnet_features(self.feature_init, self.encoder))
            self._weights_loaded = True
        return super().train(mode)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args, **kwargs) -> None:
        self._weights_loaded = True  # trained or imported weights supersede feature_init
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def features(self, points: Tensor) -> Tensor:
        return self.encoder(points)[1]

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None) -> dict:
        if self.training:  # official: update the BatchNorm statistics with both clouds, then freeze them
            with torch.no_grad():
                self.features(points_ref - points_ref.mean(dim=1, keepdim=True))
                self.features(points_src - points_src.mean(dim=1, keepdim=True))
        iterations = self.max_iter if self.training else self.eval_max_iter
        with eval_mode(self.encoder):
            result = lk_register(self.features, points_src, points_ref, self.delta, iterations, self.xtol)
        return {"transforms": result.transforms, "residual": result.residual, "iterations": result.iterations}

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        with full_precision(transform_gt.device):  # float32 even under bf16 autocast
            transform = composed_identity_error(outputs["transforms"][-1], se3_inverse(transform_gt)).mean()
            feature = (outputs["residual"] ** 2).sum()
            total = transform + self.feature_loss_weight * feature
            return {"loss": total, "loss/transform": transform, "loss/feature": feature}
