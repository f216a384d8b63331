"""Shared learned building blocks."""

import torch

from baselines.learned.common.encoders import PointNetEncoder, knn_indices
from baselines.learned.common.procrustes import weighted_procrustes
from src.geometry import euler_to_matrix, se3_apply, se3_from_rt


def test_procrustes_recovers_transform_and_ignores_zero_weight_outliers():
    torch.manual_seed(0)
    src = torch.randn(3, 50, 3, dtype=torch.float64)
    gt = se3_from_rt(euler_to_matrix(torch.rand(3, 3, dtype=torch.float64) * 2, "xyz"), torch.randn(3, 3, dtype=torch.float64))
    tgt = se3_apply(gt, src)
    tgt[:, :5] += 10.0  # outliers
    weights = torch.ones(3, 50, dtype=torch.float64)
    weights[:, :5] = 0
    torch.testing.assert_close(weighted_procrustes(src, tgt, weights), gt)
    rot = weighted_procrustes(src, -src)[:, :3, :3]  # a reflection is the best linear fit
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(3, dtype=torch.float64))


def test_pointnet_shapes_and_knn():
    feats, glob = PointNetEncoder((3, 8, 16))(torch.randn(2, 10, 3))
    assert feats.shape == (2, 10, 16) and glob.shape == (2, 16)
    pts = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [0.1, 0, 0]]])
    assert knn_indices(pts, 2)[0, 0].tolist() == [0, 2]
