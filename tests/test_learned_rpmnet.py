"""RPMNet: normals from the received points, 2 training / 5 test iterations, loss, training, config and checkpoint."""


import pytest
import torch
from hydra.utils import instantiate

from baselines.learned.adapter import compose_model_config
from baselines.learned.rpmnet import RPMNet
from src.config import register_resolvers
from src.models.module import RegistrationModule
from registration_helpers import reload_via_checkpoint
from registration_helpers import assert_rigid as _assert_rigid
from registration_helpers import train_losses
from registration_helpers import exact_pair_batch as _batch

register_resolvers()


def _small(**kwargs):
    return RPMNet(width=0.125, num_neighbors=16, normals_k=10, **kwargs)


def test_two_iterations_while_training_five_at_evaluation_all_rigid():
    torch.manual_seed(0)
    model = _small()
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 2 and len(out["row_sums"]) == 2
    for transform in out["transforms"]:
        _assert_rigid(transform)
    assert (out["row_sums"][0] <= 1 + 1e-5).all() and (out["col_sums"][0] <= 1 + 1e-5).all()
    assert (out["betas"][0] > 0).all() and (out["alphas"][0] > 0).all()
    losses = model.loss(out, gt)
    assert set(losses) == {"loss", "loss/points", "loss/inlier"}
    torch.testing.assert_close(losses["loss"], losses["loss/points"] + losses["loss/inlier"])
    model.eval()
    with torch.no_grad():
        out = model(src, ref, gt)
    assert len(out["transforms"]) == 5
    _assert_rigid(out["transforms"][-1])


def test_loss_is_zero_pointwise_for_the_ground_truth_and_discounts_early_iterations():
    model = _small()
    src, _, gt = _batch()
    ones = torch.ones(3, 64)
    perfect = {"transforms": [gt, gt], "row_sums": [ones, ones], "col_sums": [ones, ones], "points_src": src}
    assert model.loss(perfect, gt)["loss"] < 1e-6
    off = torch.eye(4).expand(3, 4, 4)
    first_bad = model.loss({**perfect, "transforms": [off, gt]}, gt)["loss/points"]
    last_bad = model.loss({**perfect, "transforms": [gt, off]}, gt)["loss/points"]
    torch.testing.assert_close(first_bad, 0.5 * last_bad)
    with pytest.raises(ValueError):
        RPMNet(loss_type="huber")


def test_the_network_needs_no_normals_and_is_invariant_to_point_order():
    torch.manual_seed(0)
    model = RPMNet(width=0.125, num_neighbors=64, normals_k=10).eval()  # every ball neighbour kept
    src, ref, _ = _batch(b=2)
    perm = torch.randperm(64)
    with torch.no_grad():
        a = model(src, ref)["transforms"][-1]
        b = model(src[:, perm], ref[:, torch.randperm(64)])["transforms"][-1]
    torch.testing.assert_close(a, b, atol=1e-4, rtol=0)


def test_a_few_training_steps_lower_the_loss():
    torch.manual_seed(0)
    model = _small()
    src, ref, gt = _batch(b=4)
    losses = train_losses(model, (src, ref, gt), steps=6)
    assert losses[-1] < losses[0]


def test_config_composes_instantiates_and_reloads_from_a_checkpoint(tmp_path):
    cfg = compose_model_config("rpmnet", 1.0, ["partial=rpmnet"])
    small = compose_model_config("rpmnet", 0.125, ["model.network.num_neighbors=16"])
    module = instantiate(cfg)
    assert isinstance(module, RegistrationModule) and module.network_target == "baselines.learned.rpmnet.RPMNet"
    assert module.hparams["lr"] == 1e-4 and module.hparams["weight_decay"] == 0 and module.hparams["euler_seq"] == "xyz"
    assert module.network.feat_extractor.features == ("xyz", "dxyz", "ppf")
    module.configure_optimizers()
    module = instantiate(small).eval()
    loaded = reload_via_checkpoint(module, tmp_path / "rpmnet.ckpt")
    src, ref, _ = _batch(b=2)
    with torch.no_grad():
        torch.testing.assert_close(loaded(src, ref), module(src, ref))
