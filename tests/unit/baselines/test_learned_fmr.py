"""FMR (supervised): rigid estimates, decoder reconstructions, Chamfer + transform loss, learned step,
training lowers the loss."""

import torch

from baselines.learned.common.global_feature import chamfer_loss
from baselines.learned.fmr import FMR
from src.geometry import se3_inverse
from tests.helpers.registration_helpers import eval_losses_before_after
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import partial_pair_batch as _batch


def test_forward_returns_rigid_transforms_and_reconstructions():
    torch.manual_seed(0)
    model = FMR(width=0.125, decoder_points=50)
    src, ref, gt = _batch(b=3, n=96)
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 10
    for transform in out["transforms"]:
        _assert_rigid(transform)
    rec_ref, rec_src = out["reconstructions"]
    assert rec_ref.shape == rec_src.shape == (3, 50, 3)
    model.eval()
    with torch.no_grad():
        _assert_rigid(model(src, ref)["transforms"][-1])


def test_loss_is_chamfer_plus_transform_and_delta_is_learned():
    model = FMR(width=0.125, decoder_points=40, max_iter=3)
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    losses = model.loss(out, gt)
    (ref_c, src_c), (rec_ref, rec_src) = out["centred"], out["reconstructions"]
    torch.testing.assert_close(ref_c.mean(1), torch.zeros(4, 3), atol=1e-6, rtol=0)
    chamfer = chamfer_loss(ref_c, rec_ref) + chamfer_loss(src_c, rec_src)
    torch.testing.assert_close(losses["loss/chamfer"], chamfer)
    expected = ((out["transforms"][-1] @ se3_inverse(gt) - torch.eye(4)) ** 2).sum((1, 2)).mean()
    torch.testing.assert_close(losses["loss/transform"], expected)
    torch.testing.assert_close(losses["loss"], losses["loss/chamfer"] + losses["loss/transform"])
    losses["loss"].backward()
    assert model.delta.grad is not None and torch.isfinite(model.delta.grad).all() and model.delta.grad.abs().sum() > 0
    assert model.decoder.out.weight.grad.abs().sum() > 0


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    torch.manual_seed(0)
    before, after = eval_losses_before_after(FMR(width=0.125, decoder_points=64), _batch())
    assert after["loss"] < 0.5 * before["loss"]
    assert after["loss/transform"] < 0.5 * before["loss/transform"]
