"""DeepGMR: rigid estimates both ways, GMM posterior, rotation invariance through RRI, loss, training."""

import pytest
import torch

from baselines.learned.deepgmr import DeepGMR
from src.geometry import euler_to_matrix, se3_apply, se3_from_rt
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import partial_pair_batch as _batch
from tests.helpers.registration_helpers import train_losses


@pytest.mark.parametrize("kwargs", [dict(), dict(use_rri=False), dict(exact_procrustes=True)])
def test_forward_returns_rigid_transforms_and_a_posterior(kwargs):
    torch.manual_seed(0)
    model = DeepGMR(width=0.125, k=8, **kwargs)
    src, ref, gt = _batch(b=3, n=96)
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 1
    _assert_rigid(out["transforms"][-1])
    _assert_rigid(out["transform_reverse"])
    for gamma in out["gamma"]:
        assert gamma.shape == (3, 96, 16)
        torch.testing.assert_close(gamma.sum(-1), torch.ones(3, 96))
    model.eval()
    with torch.no_grad():
        _assert_rigid(model(src, ref)["transforms"][-1])


def test_rri_makes_the_estimate_equivariant_to_a_rotated_source():
    # float64: an untrained network's components all sit near the centroid, an ill-conditioned SVD
    torch.manual_seed(0)
    model = DeepGMR(width=0.125, k=8).double().eval()
    src, ref, _ = (x.double() for x in _batch(b=2, n=80))
    f64 = dict(dtype=torch.float64)
    extra = se3_from_rt(euler_to_matrix(torch.rand(2, 3, **f64) * 3, "xyz"), torch.randn(2, 3, **f64))
    with torch.no_grad():
        out = model(src, ref)
        moved = model(se3_apply(extra, src), ref)
    torch.testing.assert_close(moved["gamma"][0], out["gamma"][0])
    torch.testing.assert_close(moved["gmm_src"][1], se3_apply(extra, out["gmm_src"][1]))
    torch.testing.assert_close(moved["transforms"][-1] @ extra, out["transforms"][-1], atol=1e-6, rtol=0)


def test_gmm_steps_run_in_float32_under_bf16_autocast():
    torch.manual_seed(0)
    model = DeepGMR(width=0.125, k=8)
    src, ref, gt = _batch()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(src, ref, gt)
        loss = model.loss(out, gt)["loss"]
    assert out["transforms"][-1].dtype == torch.float32 and loss.dtype == torch.float32
    _assert_rigid(out["transforms"][-1])
    loss.backward()


def test_rri_features_are_the_float32_ones_under_bf16_autocast():
    model = DeepGMR(width=0.125, k=8)
    src, _, _ = _batch()
    plain = model.point_features(src)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        autocast = model.point_features(src)
    assert autocast.dtype == torch.float32 and torch.equal(autocast, plain)


def test_loss_is_the_official_two_way_mse():
    model = DeepGMR(width=0.125, k=8)
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    losses = model.loss(out, gt)
    eye = torch.eye(4).expand(4, 4, 4)
    forward = torch.nn.functional.mse_loss(out["transforms"][-1] @ torch.inverse(gt), eye)
    reverse = torch.nn.functional.mse_loss(out["transform_reverse"] @ gt, eye)
    torch.testing.assert_close(losses["loss"], forward + reverse)
    losses["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    torch.manual_seed(0)
    model = DeepGMR(width=0.125, k=8)
    losses = train_losses(model, _batch(), steps=10)
    assert losses[-1] < 0.2 * losses[0]


def test_the_rri_projection_is_the_codes_unless_a_checkpoint_was_trained_with_the_exact_one():
    from src.utils.paths import SHIPPED_DIR

    assert DeepGMR(width=0.125).rri == "authors" and DeepGMR(width=0.125, rri="exact").rri == "exact"
    with pytest.raises(ValueError, match="rri must be one of"):
        DeepGMR(width=0.125, rri="plane")
    torch.manual_seed(0)
    model, (src, ref, _) = DeepGMR(width=0.125, k=8).eval(), _batch(b=2, n=96)
    with torch.no_grad():
        authors = model(src, ref)["transforms"][-1]
        model.rri = "exact"
        assert not torch.allclose(model(src, ref)["transforms"][-1], authors)
    shipped = torch.load(SHIPPED_DIR / "deepgmr_real_airplane_ts_prnet.ckpt", map_location="cpu", weights_only=False)
    assert shipped["hyper_parameters"]["network"]["rri"] == "exact"  # evaluated as it was trained


def test_a_cloud_with_fewer_points_than_the_rri_neighbours_is_one_line():
    """Found by generated pairs: 3-point clouds reached top-k of the k = 20 neighbours and a RuntimeError traceback."""
    import numpy as np

    from baselines import get_registrator
    from src.utils.errors import PointCloudError

    points = np.random.default_rng(0).normal(size=(20, 3))
    with pytest.raises(PointCloudError, match=r"^deepgmr: each cloud needs at least 21 points for this network, got 20$"):
        get_registrator("deepgmr").register(points, points)
    assert DeepGMR(width=0.125, k=8, use_rri=False).min_points == 3 and DeepGMR(width=0.125, k=8).min_points == 9
