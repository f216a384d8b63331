"""Metrics against hand-computed values."""

import math

import pytest
import torch

from src.geometry import euler_to_matrix, se3_from_rt
from src.metrics import METRIC_NAMES, MODIFIED_CHAMFER, RegistrationMetrics, chamfer_distance, modified_chamfer


def _transform(angles_deg, trans, seq="zyx"):
    rot = euler_to_matrix(torch.tensor(angles_deg, dtype=torch.float64), seq, degrees=True)
    return se3_from_rt(rot, torch.tensor(trans, dtype=torch.float64))


def test_hand_computed_values():
    # Pair 1: prediction off by 3 degrees about z only, translation off by (0.03, 0.04, 0).
    gt1, pred1 = _transform([10.0, 0, 0], [0.1, 0, 0]), _transform([13.0, 0, 0], [0.13, 0.04, 0])
    # Pair 2: perfect.
    gt2 = _transform([5.0, 20.0, -7.0], [0.0, 0.2, -0.1])
    pred, gt = torch.stack([pred1, gt2]), torch.stack([gt1, gt2])
    points = torch.zeros(2, 4, 3)
    metric = RegistrationMetrics(euler_seq="zyx")
    metric.update(pred, gt, points, points)
    out = metric.compute()
    assert set(out) == set(METRIC_NAMES) - {MODIFIED_CHAMFER}  # the pairs carry no clean full cloud
    # Euler errors: [3,0,0] and [0,0,0] -> squared sum 9 over 6 components.
    assert out["RMSE(R)"] == pytest.approx(math.sqrt(9 / 6))
    assert out["MAE(R)"] == pytest.approx(3 / 6)
    assert out["RMSE(t)"] == pytest.approx(math.sqrt((0.03**2 + 0.04**2) / 6))
    assert out["MAE(t)"] == pytest.approx((0.03 + 0.04) / 6)
    assert out["Error(R)"] == pytest.approx(3 / 2, abs=1e-6)
    assert out["Error(t)"] == pytest.approx(0.05 / 2)
    assert out["success(1deg,0.01)"] == pytest.approx(0.5)
    assert out["success(5deg,0.05)"] == pytest.approx(0.5)  # pair 1 has Error(t) = 0.05, not < 0.05
    assert out["score"] == pytest.approx(0.01 * 1.5 + 0.025, abs=1e-8)


def test_accumulates_sums_not_mean_of_means():
    gt = _transform([0.0, 0, 0], [0, 0, 0]).unsqueeze(0)
    bad = _transform([0.0, 0, 0], [0.3, 0, 0]).unsqueeze(0)
    metric = RegistrationMetrics()
    points = torch.zeros(1, 2, 3)
    metric.update(bad, gt, points, points)  # batch of 1 pair with error 0.3
    metric.update(gt.repeat(3, 1, 1), gt.repeat(3, 1, 1), points.repeat(3, 1, 1), points.repeat(3, 1, 1))
    assert metric.compute()["Error(t)"] == pytest.approx(0.3 / 4)  # mean of means would give 0.15


def test_xyz_convention_differs_from_zyx():
    """A three-axis rotation reads as different Euler angles in the two conventions: the metric must use
    the one it is given (a one-axis rotation would not tell them apart)."""
    from scipy.spatial.transform import Rotation

    angles = [30.0, 20.0, 10.0]
    gt = torch.eye(4, dtype=torch.float64).unsqueeze(0)
    pred = _transform(angles, [0, 0, 0], "xyz").unsqueeze(0)
    points = torch.zeros(1, 2, 3)
    xyz, zyx = RegistrationMetrics("xyz"), RegistrationMetrics("zyx")
    xyz.update(pred, gt, points, points)
    zyx.update(pred, gt, points, points)
    zyx_angles = Rotation.from_matrix(pred[0, :3, :3].numpy()).as_euler("zyx", degrees=True)
    assert xyz.compute()["MAE(R)"] == pytest.approx(sum(angles) / 3)
    assert zyx.compute()["MAE(R)"] == pytest.approx(abs(zyx_angles).sum() / 3)
    assert abs(xyz.compute()["MAE(R)"] - zyx.compute()["MAE(R)"]) > 0.5


def test_chamfer_hand_computed():
    a = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    b = torch.tensor([[[0.0, 0, 0]]])
    # a->b: (0 + 1)/2 = 0.5 ; b->a: 0
    assert chamfer_distance(a, b).item() == pytest.approx(0.5)
    far = torch.tensor([[[0.0, 0, 0], [2.0, 0, 0]], [[1.0, 0, 0], [3.0, 0, 0]]])
    # per pair; squared (FMR's loss): pair 0 a->b (0 + 4)/2, b->a 0; pair 1 a->b (1 + 9)/2, b->a 1
    assert chamfer_distance(far, b.expand(2, 1, 3)).tolist() == pytest.approx([1.0, 3.0])
    assert chamfer_distance(far, b.expand(2, 1, 3), squared=True).tolist() == pytest.approx([2.0, 6.0])


def test_rre_rte_are_rpmnet_isotropic_errors():
    """RRE = arccos((tr(R_gtᵀ R_pred) − 1) / 2) in degrees and RTE = the norm of the translation of gt⁻¹·pred
    (RPM-Net src/eval.py l. 59-64): for rotations about one axis the angle difference, ‖t_pred − t_gt‖."""
    gt, pred = _transform([30.0, 0, 0], [1.0, 0, 0]), _transform([40.0, 0, 0], [1.0, 0.3, 0.4])
    metric = RegistrationMetrics()
    points = torch.zeros(1, 2, 3)
    metric.update(pred[None], gt[None], points, points)
    out = metric.compute()
    assert out["Error(R)"] == pytest.approx(10.0, abs=1e-9)
    assert out["Error(t)"] == pytest.approx(0.5)
    rpmnet_t = (torch.linalg.inv(gt) @ pred)[:3, 3].norm()  # RPM-Net's residual_transmag
    assert out["Error(t)"] == pytest.approx(float(rpmnet_t))


def _modified_chamfer_pair():
    """The clean full cloud (reference frame) {(0,0,0), (1,0,0)}; ground truth: a shift by (0, 0, 1); the
    (noisy, partial) source {(0.1, 0, -1)} and reference {(1, 0.2, 0)}."""
    raw = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    gt = _transform([0.0, 0, 0], [0.0, 0, 1])[None]
    return gt, torch.tensor([[[0.1, 0, -1]]]), torch.tensor([[[1.0, 0.2, 0]]]), raw


def test_modified_chamfer_hand_computed():
    gt, src, ref, raw = _modified_chamfer_pair()
    # pred = identity: source (0.1, 0, -1) -> nearest raw point (0,0,0): 0.01 + 1; the clean cloud in the
    # source frame, pred·gt⁻¹·raw = {(0,0,-1), (1,0,-1)}: reference (1, 0.2, 0) -> (1,0,-1): 0.04 + 1
    identity = torch.eye(4, dtype=torch.float64)[None]
    assert modified_chamfer(identity, gt, src, ref, raw).tolist() == pytest.approx([1.01 + 1.04])
    # pred = gt: only the noise counts: (0.1, 0, 0) -> (0,0,0): 0.01; (1, 0.2, 0) -> (1,0,0): 0.04
    assert modified_chamfer(gt, gt, src, ref, raw).tolist() == pytest.approx([0.05])


def test_modified_chamfer_is_a_metric_only_with_every_clean_cloud():
    gt, src, ref, raw = _modified_chamfer_pair()
    identity = torch.eye(4, dtype=torch.float64)[None]
    metric = RegistrationMetrics()
    metric.update(identity, gt, src, ref, raw)
    metric.update(gt, gt, src, ref, raw)
    assert metric.compute()[MODIFIED_CHAMFER] == pytest.approx((2.05 + 0.05) / 2)
    metric.update(gt, gt, src, ref)  # a pair without its clean cloud: no value rather than a partial mean
    assert MODIFIED_CHAMFER not in metric.compute()


def test_rejects_unknown_convention():
    with pytest.raises(ValueError, match="euler_seq"):
        RegistrationMetrics("abc")
