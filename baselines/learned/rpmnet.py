"""RPMNet (Yew & Lee, "RPM-Net: Robust Point Matching using Learned Features", CVPR 2020) for
:class:`~src.models.module.RegistrationModule`.

Learned annealing parameters and PPF features matched by Sinkhorn with slack, a weighted Procrustes per
iteration. Normals are ``"estimated"`` (default, the OMNet paper's protocol) or ``"given"`` (RPMNet's own
code, ``data.normals=cache``). The network, loss, optimiser and deviations from the official code:
``docs/methods/rpmnet.md``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.correspondence import estimate_normals, ppf_features, sinkhorn, soft_correspondence_svd
from baselines.learned.common.layers import MLP
from baselines.learned.common.global_feature import at_least_fp32, full_precision
from src.utils.errors import ConfigError, PointCloudError
from src.geometry import se3_apply
from src.models.base import scaled

FEATURES = ("xyz", "dxyz", "ppf")  # the official concatenation order
FEATURE_SIZES = {"xyz": 3, "dxyz": 3, "ppf": 4}
LOSS_TYPES = ("mae", "mse")
NORMALS = ("estimated", "given")


class ParameterPrediction(nn.Module):
    """β (inverse annealing temperature) and α (outlier threshold) from both clouds (PointNet)."""

    def __init__(self, width: float = 1.0) -> None:
        super().__init__()
        pre = [4] + [scaled(c, width, 16) for c in (64, 64, 64, 128, 1024)]
        post = [pre[-1]] + [scaled(c, width, 16) for c in (512, 256)]
        self.prepool = MLP(pre, norm="group", groups=[8, 8, 8, 8, 16], bias=True)
        self.postpool = MLP(post, norm="group", groups=16, bias=True)
        self.out = nn.Linear(post[-1], 2)

    def forward(self, src: Tensor, ref: Tensor) -> tuple[Tensor, Tensor]:
        both = torch.cat((F.pad(src, (0, 1), value=0.0), F.pad(ref, (0, 1), value=1.0)), dim=1)
        raw = self.out(self.postpool(self.prepool(both).amax(dim=1)))
        return F.softplus(raw[:, 0]), F.softplus(raw[:, 1])


class FeatureExtraction(nn.Module):
    """Early-fusion local features (B, N, feat_dim), unit length."""

    def __init__(self, features: tuple[str, ...] = FEATURES, feat_dim: int = 96, radius: float = 0.3,
                 num_neighbors: int = 64) -> None:
        super().__init__()
        unknown = set(features) - set(FEATURES)
        if unknown or not features:
            raise ValueError(f"features must be a non-empty subset of {FEATURES}, got {features!r}")
        self.features = tuple(f for f in FEATURES if f in features)
        self.radius, self.num_neighbors = radius, num_neighbors
        raw = sum(FEATURE_SIZES[f] for f in self.features)
        self.prepool = MLP([raw, feat_dim, feat_dim, 2 * feat_dim], norm="group", groups=8, bias=True)
        self.postpool = MLP([2 * feat_dim, 2 * feat_dim, feat_dim, feat_dim], norm="group", groups=8,
                            last_activation=False, bias=True)

    def forward(self, points: Tensor, normals: Tensor) -> Tensor:
        raw = ppf_features(points, normals, self.radius, self.num_neighbors)
        x = torch.cat([raw[f] for f in self.features], dim=-1)  # (B, N, k, C)
        b, n, k, c = x.shape
        # channel-first (B, C, N·k) through the GroupNorm stacks (faster on a CPU, same function)
        x = self.prepool.forward_channels_first(x.permute(0, 3, 1, 2).reshape(b, c, n * k))
        x = self.postpool.forward_channels_first(x.reshape(b, -1, n, k).amax(dim=3)).transpose(1, 2)
        return x / x.norm(dim=-1, keepdim=True)


class RPMNet(nn.Module):
    """RPM-Net (early fusion) with normals estimated from its input points or given with them."""

    def __init__(
        self,
        num_iters: int = 5,
        num_train_iters: int = 2,
        num_sk_iter: int = 5,
        slack: bool = True,
        features: tuple[str, ...] = FEATURES,
        feat_dim: int = 96,
        radius: float = 0.3,
        num_neighbors: int = 64,
        normals_k: int = 30,
        normal_orientation: str = "centroid",
        normals: str = "estimated",
        loss_type: str = "mae",
        inlier_weight: float = 0.01,
        discount: float = 0.5,
        width: float = 1.0,
    ) -> None:
        super().__init__()
        if loss_type not in LOSS_TYPES:
            raise ValueError(f"loss_type must be one of {LOSS_TYPES}, got {loss_type!r}")
        if min(num_iters, num_train_iters) < 1:
            raise ValueError("num_iters and num_train_iters must be >= 1")
        if normals not in NORMALS:
            raise ConfigError(f"model.network.normals must be one of {NORMALS}, got {normals!r}")
        self.num_iters, self.num_train_iters, self.num_sk_iter, self.slack = num_iters, num_train_iters, num_sk_iter, slack
        self.normals_k, self.normal_orientation, self.normals = normals_k, normal_orientation, normals
        self.loss_type, self.inlier_weight, self.discount = loss_type, inlier_weight, discount
        self.weights_net = ParameterPrediction(width)
        self.feat_extractor = FeatureExtraction(tuple(features), scaled(feat_dim, width, 8), radius, num_neighbors)

    @property
    def planar_blind(self) -> str:
        """Why a planar cloud leaves its rotation undetermined (``""``: it does not): its point-pair features."""
        if "ppf" not in self.feat_extractor.features:
            return ""
        return "its point-pair features are all alike (the normals are parallel)"

    @property
    def uses_normals(self) -> bool:
        """Whether :meth:`forward` needs ``normals_src``/``normals_ref`` (``normals="given"``)."""
        return self.normals == "given"

    def forward(self, points_src: Tensor, points_ref: Tensor, transform_gt: Tensor | None = None,
                normals_src: Tensor | None = None, normals_ref: Tensor | None = None) -> dict:
        """Normals (B, N, 3) / (B, M, 3) are used with ``normals="given"`` (required then), else ignored."""
        normals_src = self._normals(points_src, normals_src, "normals_src")
        normals_ref = self._normals(points_ref, normals_ref, "normals_ref")
        feat_ref = self.feat_extractor(points_ref, normals_ref)
        src_t, normals_src_t = points_src, normals_src
        out: dict[str, list | Tensor] = {"transforms": [], "row_sums": [], "col_sums": [], "betas": [], "alphas": [],
                                         "points_src": points_src}
        for _ in range(self.num_train_iters if self.training else self.num_iters):
            beta, alpha = self.weights_net(src_t, points_ref)
            feat_src = self.feat_extractor(src_t, normals_src_t)
            feat_dist = (feat_src.square().sum(-1, keepdim=True) + feat_ref.square().sum(-1).unsqueeze(1)
                         - 2 * feat_src @ feat_ref.transpose(1, 2))
            affinity = -beta.view(-1, 1, 1) * (feat_dist - alpha.view(-1, 1, 1))
            perm = torch.exp(sinkhorn(affinity, self.num_sk_iter, self.slack))
            row_sums = perm.sum(dim=2)
            transform, _ = soft_correspondence_svd(points_src, points_ref, perm, weights=row_sums, normalize_rows=True)
            pose = transform.detach()
            with full_precision(points_src.device):  # the moved cloud and normals stay float32 under bf16 autocast
                pose = at_least_fp32(pose)
                src_t = se3_apply(pose, points_src)
                normals_src_t = normals_src @ pose[:, :3, :3].transpose(1, 2)
            out["transforms"].append(transform)
            out["row_sums"].append(row_sums)
            out["col_sums"].append(perm.sum(dim=1))
            out["betas"].append(beta.detach())
            out["alphas"].append(alpha.detach())
        return out

    def _normals(self, points: Tensor, given: Tensor | None, name: str) -> Tensor:
        """The normals the features use: ``given`` (``normals="given"``) or estimated from ``points``."""
        if not self.uses_normals:
            return estimate_normals(points, self.normals_k, self.normal_orientation)
        if given is None:
            raise ConfigError(
                f"RPMNet has model.network.normals=given but got no {name}: use a dataset with normals "
                "(data.normals=cache, e.g. data=modelnet40_resampled) or model.network.normals=estimated"
            )
        if given.shape != points.shape:
            raise PointCloudError(f"{name} has shape {tuple(given.shape)}, its points {tuple(points.shape)}")
        return given.to(points.dtype)

    def loss(self, outputs: dict, transform_gt: Tensor) -> dict[str, Tensor]:
        src = outputs["points_src"]
        target = se3_apply(transform_gt, src)
        n = len(outputs["transforms"])
        zero = transform_gt.new_zeros(())
        terms = {"loss/points": zero, "loss/inlier": zero}
        for i, (pred, row_sums, col_sums) in enumerate(zip(outputs["transforms"], outputs["row_sums"], outputs["col_sums"])):
            w = self.discount ** (n - 1 - i)
            moved = se3_apply(pred, src)
            points = F.l1_loss(moved, target) if self.loss_type == "mae" else F.mse_loss(moved, target)
            inlier = self.inlier_weight * ((1.0 - col_sums).mean() + (1.0 - row_sums).mean())
            terms["loss/points"] = terms["loss/points"] + w * points
            terms["loss/inlier"] = terms["loss/inlier"] + w * inlier
        terms["loss"] = terms["loss/points"] + terms["loss/inlier"]
        return terms
