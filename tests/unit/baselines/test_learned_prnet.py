"""PRNet: iterative rigid estimates, keypoints, loss terms, a few steps lower the loss, config and checkpoint."""


import pytest
import torch
from hydra.utils import instantiate

from baselines.learned.prnet import PRNet
from src.compose import compose_model_config
from src.config import register_resolvers
from src.models.module import RegistrationModule
from src.utils.paths import SHIPPED_DIR
from tests.helpers.registration_helpers import seeded_losses_before_after
from tests.helpers.registration_helpers import reload_via_checkpoint
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import exact_pair_batch as _batch

register_resolvers()


def _small(**kwargs):
    return PRNet(width=0.125, k=8, num_keypoints=48, **kwargs)


def test_forward_composes_three_rigid_iterations():
    torch.manual_seed(0)
    model = _small()
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 3 and len(out["steps_ab"]) == 3 and len(out["steps_ba"]) == 3
    for transform in out["transforms"] + out["steps_ba"]:
        _assert_rigid(transform)
    s = out["steps_ab"]
    torch.testing.assert_close(out["transforms"][-1], s[2] @ s[1] @ s[0], atol=1e-5, rtol=0)
    losses = model.loss(out, gt)
    assert set(losses) == {"loss", "loss/pose", "loss/feature_alignment", "loss/cycle"}
    torch.testing.assert_close(losses["loss"], losses["loss/pose"] + losses["loss/feature_alignment"] + losses["loss/cycle"])
    model.eval()
    with torch.no_grad():
        _assert_rigid(model(src, ref)["transforms"][-1])
        det = _small(deterministic_eval=True).eval()
        torch.testing.assert_close(det(src, ref)["transforms"][-1], det(src, ref)["transforms"][-1])


def test_keypoints_are_the_largest_feature_norms():
    model = _small()
    points = torch.randn(2, 64, 3)
    feat = torch.randn(2, 64, 16)
    kp, kf = model.keypoints(points, feat)
    assert kp.shape == (2, 48, 3) and kf.shape == (2, 48, 16)
    assert kf.norm(dim=-1).min() >= feat.norm(dim=-1).sort(dim=1, descending=True).values[:, 47].min() - 1e-6
    kp_all, _ = _small().keypoints(points[:, :40], feat[:, :40])  # fewer points than keypoints: all of them
    assert kp_all.shape == (2, 40, 3)
    with pytest.raises(ValueError):
        PRNet(sampler="sinkhorn")


@pytest.mark.parametrize("sampler", ["gumbel_softmax", "softmax"])
def test_a_few_training_steps_lower_the_loss(sampler):
    torch.manual_seed(1)
    model = _small(sampler=sampler)
    src, ref, gt = _batch(b=4, seed=1)
    # PRNet draws Gumbel noise: compare losses over fixed seeds
    before, after = seeded_losses_before_after(model, (src, ref, gt), steps=6, lr=1e-3)
    assert after < 0.8 * before


def test_config_composes_instantiates_and_reloads_from_a_checkpoint(tmp_path):
    cfg = compose_model_config("prnet", 1.0)
    small = compose_model_config("prnet", 0.125, ["model.network.num_keypoints=48", "model.network.k=8"])
    module = instantiate(cfg)
    assert isinstance(module, RegistrationModule) and module.network_target == "baselines.learned.prnet.PRNet"
    assert module.hparams["lr"] == 1e-3 and module.hparams["weight_decay"] == 1e-4 and module.network.num_iters == 3
    module.configure_optimizers()
    module = instantiate(small).eval()
    loaded = reload_via_checkpoint(module, tmp_path / "prnet.ckpt")
    src, ref, _ = _batch(b=2)
    with torch.no_grad():
        torch.manual_seed(5)
        expected = module(src, ref)
        torch.manual_seed(5)
        torch.testing.assert_close(loaded(src, ref), expected)


def test_the_layer_norm_is_the_codes_unless_a_checkpoint_was_trained_with_pytorchs():
    from baselines.learned.common.correspondence import AuthorsLayerNorm

    kinds = lambda net: {type(m) for m in net.modules() if isinstance(m, torch.nn.LayerNorm)}  # noqa: E731
    assert kinds(PRNet(width=0.0625)) == {AuthorsLayerNorm}
    assert kinds(PRNet(width=0.0625, layer_norm="torch")) == {torch.nn.LayerNorm}
    with pytest.raises(ValueError, match="layer_norm must be one of"):
        PRNet(width=0.0625, layer_norm="batch")
    shipped = torch.load(SHIPPED_DIR / "prnet_real_airplane_ts_prnet.ckpt", map_location="cpu", weights_only=False)
    assert shipped["hyper_parameters"]["network"]["layer_norm"] == "torch"  # evaluated as it was trained
