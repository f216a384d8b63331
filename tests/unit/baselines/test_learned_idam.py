"""IDAM: point elimination, iterative rigid estimates, losses, a few steps lower the loss, config and checkpoint."""


import pytest
import torch
from hydra.utils import instantiate

from baselines.learned.idam import IDAM
from src.compose import compose_model_config
from src.config import register_resolvers
from src.models.module import RegistrationModule
from tests.helpers.registration_helpers import seeded_losses_before_after
from tests.helpers.registration_helpers import assert_reloads_the_same
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import exact_pair_batch as _batch

register_resolvers()


def test_training_forward_keeps_a_sixth_in_corresponding_order_and_gives_rigid_transforms():
    torch.manual_seed(0)
    model = IDAM(width=0.5)
    src, ref, gt = _batch(n=96)
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 3
    for transform in out["transforms"]:
        _assert_rigid(transform)
    assert out["similarities"][0].shape == (3, 16, 16) and out["weight_logits"][0].shape == (3, 16)
    assert out["targets"].tolist() == [list(range(16))] * 3  # the i-th source point matches the i-th reference point
    assert out["match_labels"][:, :8].sum() > 0  # the first half sampled among true matches
    losses = model.loss(out, gt)
    assert set(losses) == {"loss", "loss/match", "loss/weight", "loss/negative_entropy"}
    assert all(torch.isfinite(v) for v in losses.values())
    with pytest.raises(ValueError):
        model(src, ref)  # training needs the ground truth


def test_evaluation_selects_by_significance_with_or_without_ground_truth():
    torch.manual_seed(0)
    model = IDAM(width=0.5).eval()
    src, ref, gt = _batch(n=96)
    with torch.no_grad():
        plain = model(src, ref)
        with_gt = model(src, ref, gt)
    _assert_rigid(plain["transforms"][-1])
    torch.testing.assert_close(plain["transforms"][-1], with_gt["transforms"][-1])
    assert torch.isfinite(model.loss(with_gt, gt)["loss"])
    with pytest.raises(ValueError):
        model.loss(plain, gt)


def test_a_few_training_steps_lower_the_loss():
    torch.manual_seed(0)
    model = IDAM(width=0.5)
    src, ref, gt = _batch(b=4, n=96)
    # IDAM draws its training point selection at random: compare losses over fixed seeds
    before, after = seeded_losses_before_after(model, (src, ref, gt), steps=10, lr=1e-2)
    assert after < before


def test_config_composes_instantiates_and_reloads_from_a_checkpoint(tmp_path):
    cfg, small = compose_model_config("idam", 1.0), compose_model_config("idam", 0.5)
    module = instantiate(cfg)
    assert isinstance(module, RegistrationModule) and module.network_target == "baselines.learned.idam.IDAM"
    assert module.hparams["lr"] == 1e-4 and module.hparams["weight_decay"] == 1e-3
    module.configure_optimizers()
    module = instantiate(small).eval()
    assert_reloads_the_same(module, tmp_path / "idam.ckpt", *_batch(b=2, n=96)[:2])


def test_the_similarity_images_first_layer_per_point_equals_the_layer_on_the_built_image():
    """Values and gradients, float64: W[f_i; g_j; e_ij] computed per point = the Linear on the concatenation."""
    from baselines.learned.idam import similarity_first_layer

    torch.manual_seed(0)
    linear = torch.nn.Linear(2 * 5 + 4, 7).double()
    feat_src = torch.randn(2, 6, 5, dtype=torch.float64, requires_grad=True)
    feat_ref = torch.randn(2, 4, 5, dtype=torch.float64, requires_grad=True)
    geometry = torch.randn(2, 6, 4, 4, dtype=torch.float64, requires_grad=True)
    image = torch.cat((feat_src.unsqueeze(2).expand(-1, -1, 4, -1), feat_ref.unsqueeze(1).expand(-1, 6, -1, -1), geometry), dim=-1)
    expected = linear(image)
    got = similarity_first_layer(linear, feat_src, feat_ref, geometry)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    weights = torch.randn_like(expected)
    grads = lambda out: torch.autograd.grad((out * weights).sum(), (feat_src, feat_ref, geometry, linear.weight))  # noqa: E731
    for a, b in zip(grads(got), grads(expected)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
