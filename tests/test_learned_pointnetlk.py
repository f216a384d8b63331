"""PointNetLK: rigid per-iteration estimates, BatchNorm handling, loss terms, training lowers the loss."""

import torch

from baselines.learned.pointnetlk import PointNetLK
from src.geometry import se3_inverse
from registration_helpers import warm_up_batchnorm
from registration_helpers import assert_rigid as _assert_rigid
from registration_helpers import partial_pair_batch as _batch


def test_forward_returns_rigid_transforms_per_iteration():
    torch.manual_seed(0)
    model = PointNetLK(width=0.125, max_iter=6)
    src, ref, gt = _batch(b=3, n=96)
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 6 and out["residual"].shape == (3, 128)
    for transform in out["transforms"]:
        _assert_rigid(transform)
    assert model.training and model.encoder.training  # eval mode inside LK only
    model.eval()
    with torch.no_grad():
        _assert_rigid(model(src, ref)["transforms"][-1])


def test_batchnorm_statistics_update_only_in_training():
    model = PointNetLK(width=0.125, max_iter=2)
    src, ref, _ = _batch()
    bn = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d))
    model.eval()
    with torch.no_grad():
        model(src, ref)
    assert bn.num_batches_tracked.item() == 0
    model.train()
    model(src, ref)
    assert bn.num_batches_tracked.item() == 2  # one training-mode pass per cloud, then frozen in LK


def test_loss_terms_and_fixed_delta():
    model = PointNetLK(width=0.125, max_iter=3)
    assert "delta" not in dict(model.named_parameters())  # not learned by default
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    losses = model.loss(out, gt)
    expected = ((out["transforms"][-1] @ se3_inverse(gt) - torch.eye(4)) ** 2).sum((1, 2)).mean()
    torch.testing.assert_close(losses["loss/transform"], expected)
    torch.testing.assert_close(losses["loss"], losses["loss/transform"] + (out["residual"] ** 2).sum())
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())
    transform_only = PointNetLK(width=0.125, max_iter=3, feature_loss_weight=0.0, learn_delta=True)
    assert "delta" in dict(transform_only.named_parameters())
    loss = transform_only.loss(transform_only(src, ref, gt), gt)
    assert loss["loss"].item() == loss["loss/transform"].item()


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    # transform loss only (the paper's loss; the official default adds the summed feature residual,
    # which on a 4-pair batch mostly shrinks the features); BatchNorm statistics are warmed up first,
    # since LK runs on the running statistics and their drift would otherwise mask the learning.
    torch.manual_seed(0)
    model = PointNetLK(width=0.125, feature_loss_weight=0.0)
    src, ref, gt = _batch()
    warm_up_batchnorm(model, src, ref)

    def eval_loss():
        model.eval()
        with torch.no_grad():
            value = model.loss(model(src, ref, gt), gt)["loss"].item()
        model.train()
        return value

    before = eval_loss()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    for _ in range(20):
        optimizer.zero_grad()
        model.loss(model(src, ref, gt), gt)["loss"].backward()
        optimizer.step()
    assert eval_loss() < 0.5 * before
