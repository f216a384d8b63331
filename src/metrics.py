"""Registration metrics as a torchmetrics ``Metric`` (correct under DDP: every state is a sum).

Anisotropic (paper, following DCP/RPMNet): RMSE and MAE of the Euler angles (degrees) and of the
translation, component-wise between ground truth and prediction. The Euler convention follows the
partial manner: ``zyx`` for PRNet's, ``xyz`` for RPMNet's.
Isotropic: Error(R) = angle of R_gtᵀ R_pred (degrees), Error(t) = ‖t_gt − t_pred‖.
Also: the symmetric Chamfer distance between the source moved by the prediction and the reference;
RPM-Net's modified Chamfer distance (:func:`modified_chamfer`, the "CD" of RPM-Net, Predator and RegTR)
where the pairs carry the reference's clean full cloud (``points_raw``); the fraction of pairs under (1°, 0.01) and (5°, 0.05), and the model-selection score of the official
code, 0.01·Error(R) + Error(t).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric

from src.geometry import matrix_to_euler, rotation_angle, se3_apply, se3_compose, se3_inverse

SUCCESS_THRESHOLDS: tuple[tuple[float, float], ...] = ((1.0, 0.01), (5.0, 0.05))
# The metrics' names, as every table, plot, log and card spells them (one place: import these).
RMSE_R, MAE_R, RMSE_T, MAE_T = "RMSE(R)", "MAE(R)", "RMSE(t)", "MAE(t)"
ERROR_R, ERROR_T, CHAMFER, SCORE = "Error(R)", "Error(t)", "chamfer", "score"
MODIFIED_CHAMFER = "modified_chamfer"
SUCCESS_NAMES: tuple[str, ...] = tuple(f"success({deg:g}deg,{t:g})" for deg, t in SUCCESS_THRESHOLDS)
METRIC_NAMES: tuple[str, ...] = (RMSE_R, MAE_R, RMSE_T, MAE_T, ERROR_R, ERROR_T, CHAMFER, MODIFIED_CHAMFER,
                                  *SUCCESS_NAMES, SCORE)
#: The paper's tables' metrics (anisotropic, then isotropic), and the short summaries' four.
PAPER_METRICS: tuple[str, ...] = (RMSE_R, MAE_R, RMSE_T, MAE_T, ERROR_R, ERROR_T)
SUMMARY_METRICS: tuple[str, ...] = (ERROR_R, ERROR_T, RMSE_R, RMSE_T)
#: Per-pair errors a grid records for every pair.
PAIR_ERRORS: tuple[str, ...] = (ERROR_R, ERROR_T, MAE_R, MAE_T, CHAMFER, MODIFIED_CHAMFER)
#: The validation curve's names as the CSV logger records them.
VAL_ERROR_R, VAL_ERROR_T = f"val/{ERROR_R}", f"val/{ERROR_T}"


def chamfer_distance(a: Tensor, b: Tensor, squared: bool = False) -> Tensor:
    """Symmetric Chamfer distance per pair (B,): the mean distance from each point of a (B,N,3) to its
    nearest point of b (B,M,3), plus the same from b to a; ``squared``: of the squared distances (FMR's
    loss, :func:`baselines.learned.common.global_feature.chamfer_loss`)."""
    dist = torch.cdist(a, b)
    nearest_ab, nearest_ba = dist.amin(dim=2), dist.amin(dim=1)
    if squared:
        nearest_ab, nearest_ba = nearest_ab.square(), nearest_ba.square()
    return nearest_ab.mean(dim=1) + nearest_ba.mean(dim=1)


def modified_chamfer(pred: Tensor, gt: Tensor, points_src: Tensor, points_ref: Tensor, points_raw: Tensor) -> Tensor:
    """RPM-Net's modified Chamfer distance per pair (B,), float64 (RPM-Net ``src/eval.py`` l. 66-72; the
    same code in Predator ``lib/tester.py`` l. 236-242 and RegTR ``src/benchmark/benchmark_modelnet.py``
    l. 64-70): the mean squared distance from each point of the source moved by ``pred`` to the clean
    full reference ``points_raw`` (B,K,3), plus the mean squared distance from each reference point to
    the clean full cloud carried into the source frame by the ground truth and moved by ``pred``
    (``pred · gt⁻¹ · raw``). Noise and cropping of the inputs do not count against a perfect estimate."""
    pred, gt = pred.double(), gt.double()
    values = []
    for k in range(pred.shape[0]):  # one pair at a time: (N, K) distance matrices stay small
        raw = points_raw[k].double()
        src_moved = se3_apply(pred[k], points_src[k].double())
        src_clean = se3_apply(se3_compose(pred[k], se3_inverse(gt[k])), raw)
        to_raw = torch.cdist(src_moved, raw).amin(dim=1).square().mean()
        to_src = torch.cdist(points_ref[k].double(), src_clean).amin(dim=1).square().mean()
        values.append(to_raw + to_src)
    return torch.stack(values)


def pair_errors(pred: Tensor, gt: Tensor, euler_seq: str) -> dict[str, Tensor]:
    """Per-pair errors of predicted vs ground-truth transforms (B,4,4), float64."""
    pred, gt = pred.double(), gt.double()
    euler_err = matrix_to_euler(pred[:, :3, :3], euler_seq, degrees=True) - matrix_to_euler(
        gt[:, :3, :3], euler_seq, degrees=True
    )
    trans_err = pred[:, :3, 3] - gt[:, :3, 3]
    return {
        "euler_err": euler_err,
        "trans_err": trans_err,
        "rot_deg": rotation_angle(gt[:, :3, :3].transpose(-1, -2) @ pred[:, :3, :3]),
        "trans_norm": trans_err.norm(dim=-1),
    }


class RegistrationMetrics(Metric):
    """Accumulates the paper's metrics over batches; ``compute()`` returns a dict of floats."""

    full_state_update = False
    higher_is_better = False

    def __init__(self, euler_seq: str = "zyx", **kwargs) -> None:
        super().__init__(**kwargs)
        if euler_seq not in ("xyz", "zyx"):
            raise ValueError(f"euler_seq must be 'xyz' or 'zyx', got {euler_seq!r}")
        self.euler_seq = euler_seq
        for name in ("sq_euler", "abs_euler", "sq_trans", "abs_trans", "rot_deg", "trans_norm", "chamfer"):
            self.add_state(name, default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("modified_chamfer", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("raw_pairs", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        for k in range(len(SUCCESS_THRESHOLDS)):
            self.add_state(f"success_{k}", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("num_pairs", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, gt: Tensor, points_src: Tensor, points_ref: Tensor,
               points_raw: Tensor | None = None) -> None:
        """pred, gt: (B,4,4) source→reference transforms; points: (B,N,3) and (B,M,3); ``points_raw`` (B,K,3),
        the reference's clean full cloud, if the pairs carry it (else no modified Chamfer distance)."""
        err = pair_errors(pred, gt, self.euler_seq)
        self.sq_euler += err["euler_err"].pow(2).sum()
        self.abs_euler += err["euler_err"].abs().sum()
        self.sq_trans += err["trans_err"].pow(2).sum()
        self.abs_trans += err["trans_err"].abs().sum()
        self.rot_deg += err["rot_deg"].sum()
        self.trans_norm += err["trans_norm"].sum()
        moved = se3_apply(pred.float(), points_src.float())
        self.chamfer += chamfer_distance(moved, points_ref.float()).double().sum()
        if points_raw is not None:
            self.modified_chamfer += modified_chamfer(pred, gt, points_src, points_ref, points_raw).sum()
            self.raw_pairs += pred.shape[0]
        for k, (max_deg, max_t) in enumerate(SUCCESS_THRESHOLDS):
            hit = (err["rot_deg"] < max_deg) & (err["trans_norm"] < max_t)
            setattr(self, f"success_{k}", getattr(self, f"success_{k}") + hit.double().sum())
        self.num_pairs += pred.shape[0]

    def compute(self) -> dict[str, float]:
        """Every name of :data:`METRIC_NAMES`, but the modified Chamfer distance only if every pair carried
        its clean full cloud."""
        n = self.num_pairs.clamp_min(1)
        values = {
            RMSE_R: (self.sq_euler / (3 * n)).sqrt(),
            MAE_R: self.abs_euler / (3 * n),
            RMSE_T: (self.sq_trans / (3 * n)).sqrt(),
            MAE_T: self.abs_trans / (3 * n),
            ERROR_R: self.rot_deg / n,
            ERROR_T: self.trans_norm / n,
            CHAMFER: self.chamfer / n,
            **{name: getattr(self, f"success_{k}") / n for k, name in enumerate(SUCCESS_NAMES)},
        }
        values[SCORE] = 0.01 * values[ERROR_R] + values[ERROR_T]
        if self.raw_pairs > 0 and self.raw_pairs == self.num_pairs:
            values[MODIFIED_CHAMFER] = self.modified_chamfer / self.raw_pairs
        return {k: float(v) for k, v in values.items()}
