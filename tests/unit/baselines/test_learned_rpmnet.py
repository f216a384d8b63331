"""RPMNet: normals estimated from the received points or given with them (sign conventions), 2 training /
5 test iterations, loss, training, config and checkpoint."""


import pytest
import torch
import torch.nn.functional as F
from hydra.utils import instantiate

from baselines.learned.common.correspondence import estimate_normals
from baselines.learned.rpmnet import RPMNet
from src.compose import compose_model_config
from src.config import register_resolvers
from src.utils.errors import ConfigError, PointCloudError
from src.models.module import RegistrationModule
from tests.helpers.registration_helpers import assert_reloads_the_same
from tests.helpers.registration_helpers import assert_rigid as _assert_rigid
from tests.helpers.registration_helpers import train_losses
from tests.helpers.registration_helpers import exact_pair_batch as _batch

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


def test_it_trains_under_bf16_autocast_with_the_moved_cloud_in_float32():
    """The moved source and its normals stay float32 (mixed bf16 and float32 geometry would stop the step)."""
    torch.manual_seed(0)
    model = _small()
    src, ref, gt = _batch()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(src, ref, gt)
        loss = model.loss(out, gt)["loss"]
    loss.backward()
    assert torch.isfinite(loss) and len(out["transforms"]) == 2
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_its_model_config_keeps_the_annealing_parameters_in_float32():
    module = instantiate(compose_model_config("rpmnet", 0.125))
    assert module.hparams["fp32_modules"] == ["weights_net"]
    src, ref, _ = _batch()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        beta, alpha = module.network.weights_net(src, ref)
    assert beta.dtype == alpha.dtype == torch.float32


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


def _spy_normals(model: RPMNet) -> list[torch.Tensor]:
    """The normals of every feature-extraction call, in call order (reference first, then the source
    once per iteration)."""
    seen: list[torch.Tensor] = []
    model.feat_extractor.register_forward_pre_hook(lambda _, args: seen.append(args[1].clone()))
    return seen


def _random_normals(*clouds: torch.Tensor) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    return [F.normalize(torch.randn(c.shape, generator=g), dim=-1) for c in clouds]


def test_estimated_normals_are_unit_and_signed_away_from_the_centroid_given_ones_ignored():
    torch.manual_seed(0)
    model = _small().eval()
    src, ref, _ = _batch(b=2)
    seen = _spy_normals(model)
    with torch.no_grad():
        plain = model(src, ref)["transforms"][-1]
        ignored = model(src, ref, normals_src=-src, normals_ref=-ref)["transforms"][-1]
    torch.testing.assert_close(ignored, plain, rtol=0, atol=0)
    for normals, points in ((seen[0], ref), (seen[1], src)):
        torch.testing.assert_close(normals.norm(dim=-1), torch.ones(points.shape[:2]))
        assert ((normals * (points - points.mean(1, keepdim=True))).sum(-1) >= 0).all()


def test_given_normals_feed_the_point_pair_features_as_given_and_rotate_with_the_source():
    torch.manual_seed(0)
    model = _small(normals="given").eval()
    src, ref, _ = _batch(b=2)
    normals_src, normals_ref = _random_normals(src, ref)  # half of them point inwards: the sign is kept
    seen = _spy_normals(model)
    with torch.no_grad():
        out = model(src, ref, normals_src=normals_src, normals_ref=normals_ref)
        flipped = model(src, ref, normals_src=-normals_src, normals_ref=-normals_ref)["transforms"][-1]
    assert len(seen) == 2 * (1 + 5)
    torch.testing.assert_close(seen[0], normals_ref, rtol=0, atol=0)
    torch.testing.assert_close(seen[1], normals_src, rtol=0, atol=0)
    for i, transform in enumerate(out["transforms"][:-1]):  # iteration i+1 sees the source moved by estimate i
        torch.testing.assert_close(seen[i + 2], normals_src @ transform[:, :3, :3].transpose(1, 2).float())
    assert not torch.allclose(flipped, out["transforms"][-1], atol=1e-4)  # the PPF angles depend on the sign


def test_given_normals_equal_to_the_estimate_reproduce_the_estimating_network():
    torch.manual_seed(0)
    estimating = _small().eval()
    given = _small(normals="given").eval()
    given.load_state_dict(estimating.state_dict())
    src, ref, _ = _batch(b=2)
    with torch.no_grad():
        expected = estimating(src, ref)["transforms"][-1]
        got = given(src, ref, normals_src=estimate_normals(src, 10), normals_ref=estimate_normals(ref, 10))
    torch.testing.assert_close(got["transforms"][-1], expected, rtol=0, atol=0)


def test_given_normals_are_required_and_checked():
    model = _small(normals="given")
    src, ref, gt = _batch()
    assert model.uses_normals and not _small().uses_normals
    with pytest.raises(ConfigError, match="normals=given but got no normals_src"):
        model(src, ref, gt)
    with pytest.raises(PointCloudError, match="normals_ref has shape"):
        model(src, ref, gt, normals_src=src, normals_ref=ref[:, :10])
    with pytest.raises(ConfigError, match="model.network.normals must be one of"):
        RPMNet(normals="oriented")


def test_a_few_training_steps_with_given_normals_lower_the_loss():
    torch.manual_seed(0)
    model = _small(normals="given")
    src, ref, gt = _batch(b=4)
    normals_ref = estimate_normals(ref, 10)
    normals_src = normals_ref @ gt[:, :3, :3]  # src = gt⁻¹·ref: its normals rotated back by Rᵀ
    losses = train_losses(model, (src, ref, gt), steps=6, normals_src=normals_src, normals_ref=normals_ref)
    assert losses[-1] < losses[0]


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
    assert module.network.normals == "estimated"  # the OMNet paper's protocol by default
    assert instantiate(compose_model_config("rpmnet", 0.125, ["model.network.normals=given"])).network.uses_normals
    module.configure_optimizers()
    module = instantiate(small).eval()
    assert_reloads_the_same(module, tmp_path / "rpmnet.ckpt", *_batch(b=2)[:2])
