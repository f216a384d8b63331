"""DCP-v2: rigid one-shot estimate, loss terms, a few steps lower the loss, config and checkpoint."""


import torch
from hydra.utils import instantiate

from baselines.learned.dcp import DCP
from src.compose import compose_model_config
from src.config import register_resolvers
from src.models.module import RegistrationModule
from tests.helpers.registration_helpers import assert_reloads_the_same
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import train_losses
from tests.helpers.registration_helpers import exact_pair_batch as _batch

register_resolvers()


def test_forward_gives_one_rigid_transform_and_the_papers_loss():
    torch.manual_seed(0)
    model = DCP(width=0.125)
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 1
    _assert_rigid(out["transforms"][0])
    losses = model.loss(out, gt)
    assert set(losses) == {"loss", "loss/rot", "loss/trans"}
    torch.testing.assert_close(losses["loss"], losses["loss/rot"] + losses["loss/trans"])
    # a perfect estimate has zero loss
    assert model.loss({"transforms": [gt]}, gt)["loss"] < 1e-10
    cyc = DCP(width=0.125, cycle=True)
    out = cyc(src, ref, gt)
    _assert_rigid(out["transform_ba"])
    assert "loss/cycle" in cyc.loss(out, gt)
    assert DCP(width=0.125, pointer=False)(src, ref)["transforms"][0].shape == (3, 4, 4)


def test_a_few_training_steps_lower_the_loss():
    torch.manual_seed(0)
    model = DCP(width=0.125)
    src, ref, gt = _batch(b=4)
    losses = train_losses(model, (src, ref, gt), steps=8)
    assert losses[-1] < losses[0]


def test_config_composes_instantiates_and_reloads_from_a_checkpoint(tmp_path):
    cfg, small = compose_model_config("dcp", 1.0), compose_model_config("dcp", 0.125)
    module = instantiate(cfg)
    assert isinstance(module, RegistrationModule) and module.network_target == "baselines.learned.dcp.DCP"
    assert module.hparams["lr"] == 1e-3 and module.hparams["weight_decay"] == 1e-4
    assert sum(p.numel() for p in module.network.parameters()) > 5_000_000
    module.configure_optimizers()
    module = instantiate(small).eval()
    assert_reloads_the_same(module, tmp_path / "dcp.ckpt", *_batch(b=2)[:2])


def test_dcp_v1_doubles_the_embeddings_as_the_official_identity_pointer():
    # DCP-v1's Identity pointer returns its inputs, which are then added to them: Φ = 2F (model.py 460-463)
    torch.manual_seed(0)
    model = DCP(width=0.125, pointer=False).eval()
    src, ref, _ = _batch(b=2)
    with torch.no_grad():
        feat_src, feat_ref = model.embedding(src), model.embedding(ref)
        torch.testing.assert_close(model(src, ref)["transforms"][0], model.head(2 * feat_src, 2 * feat_ref, src, ref))
        assert not torch.allclose(model.head(feat_src, feat_ref, src, ref), model.head(2 * feat_src, 2 * feat_ref, src, ref))
    cfg = compose_model_config("dcp_v1", 1.0)
    assert cfg.network.pointer is False and cfg.lr == compose_model_config("dcp", 1.0).lr
    assert instantiate(cfg).network.pointer is None
