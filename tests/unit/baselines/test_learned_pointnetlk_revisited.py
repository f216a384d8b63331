"""PointNetLK-Revisited: the analytical Jacobian, rigid estimates, iteration counts, training subsets,
the loss, training lowers it, and the config/checkpoint round trip."""

import pytest
import torch
from hydra.utils import instantiate

from baselines.learned.common.encoders import PointNetEncoder
from baselines.learned.common.global_feature import eval_mode, lk_jacobian, pointnet_jacobian
from baselines.learned.pointnetlk_revisited import PointNetLKRevisited
from src.compose import compose_model_config
from src.config import register_resolvers
from src.geometry import se3_inverse
from tests.helpers.registration_helpers import assert_reloads_the_same, assert_rigid, eval_losses_before_after
from tests.helpers.registration_helpers import exact_pair_batch as _batch
from tests.helpers.registration_helpers import partial_pair_batch

register_resolvers()


@pytest.mark.parametrize("channels", [(3, 32), (3, 16, 32, 64)])
def test_analytical_jacobian_equals_finite_differences(channels):
    torch.manual_seed(0)
    encoder = PointNetEncoder(channels).double()
    points = torch.randn(2, 120, 3, dtype=torch.float64)
    with torch.no_grad():
        encoder(points), encoder(1.5 * points)  # some BatchNorm statistics
    with torch.no_grad(), eval_mode(encoder):
        features, jacobian = pointnet_jacobian(encoder.mlp, points)
        step = torch.full((6,), 1e-6, dtype=torch.float64)
        numeric = lk_jacobian(lambda p: encoder(p)[1], points, step)
        torch.testing.assert_close(features, encoder(points)[1])
    torch.testing.assert_close(jacobian, numeric, atol=1e-5, rtol=1e-4)


def test_jacobian_needs_eval_mode_and_a_batchnorm_pointnet():
    encoder = PointNetEncoder((3, 8, 16))
    with pytest.raises(ValueError, match="eval mode"):
        pointnet_jacobian(encoder.mlp, torch.randn(1, 10, 3))
    with pytest.raises(ValueError, match="Linear \\+ BatchNorm \\+ ReLU"):
        pointnet_jacobian(PointNetEncoder((3, 8, 16), batch_norm=False).mlp, torch.randn(1, 10, 3))


def test_forward_iterations_subsets_and_batchnorm():
    torch.manual_seed(0)
    model = PointNetLKRevisited(width=0.125, max_iter=3, eval_max_iter=5, num_random_points=40)
    src, ref, gt = _batch(b=2, n=64)
    bn = next(m for m in model.modules() if isinstance(m, torch.nn.BatchNorm1d))
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 3 and out["residual"].shape == (2, 128)
    assert bn.num_batches_tracked.item() == 2 and model.encoder.training  # one pass per cloud, then eval inside LK
    for transform in out["transforms"]:
        assert_rigid(transform)
    model.eval()
    with torch.no_grad():
        out = model(src, ref)
    assert len(out["transforms"]) == 5 and bn.num_batches_tracked.item() == 2


def test_loss_is_pose_error_plus_change_of_the_last_residual():
    torch.manual_seed(0)
    model = PointNetLKRevisited(width=0.125, max_iter=3)
    src, ref, gt = _batch(b=2, n=64)
    out = model(src, ref, gt)
    losses = model.loss(out, gt)
    pose = ((out["transforms"][-1] @ se3_inverse(gt) - torch.eye(4)) ** 2).sum((1, 2)).mean()
    torch.testing.assert_close(losses["loss/transform"], pose)
    torch.testing.assert_close(losses["loss/feature"], ((out["residual"] - out["previous_residual"]) ** 2).sum())
    single = model.loss({**out, "previous_residual": None}, gt)
    torch.testing.assert_close(single["loss/feature"], (out["residual"] ** 2).sum())
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    # noisy partial pairs (on exact copies LK either converges or not, and the loss jumps)
    torch.manual_seed(0)
    model = PointNetLKRevisited(width=0.125, num_random_points=64)
    before, after = eval_losses_before_after(model, partial_pair_batch(b=4, n=64))
    assert after["loss/transform"] < 0.5 * before["loss/transform"]


def test_config_composes_instantiates_and_reloads(tmp_path):
    cfg = compose_model_config("pointnetlk_revisited", 1.0)
    module = instantiate(cfg)
    assert module.network_target == "baselines.learned.pointnetlk_revisited.PointNetLKRevisited"
    assert module.hparams["weight_decay"] == 1e-4 and module.network.eval_max_iter == 20
    # 143,104 published parameters, less the 1,216 convolution biases (folded into the running means)
    assert sum(p.numel() for p in module.network.parameters()) == 141_888
    small = instantiate(compose_model_config("pointnetlk_revisited", 0.125)).eval()
    assert_reloads_the_same(small, tmp_path / "plkr.ckpt", *_batch(b=2)[:2])
