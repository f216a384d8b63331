"""Shared global-feature blocks (exp map, LK Jacobian and loop, FMR decoder/Chamfer, DeepGMR GMM and
RRI), and the Hydra configs + checkpoints of PointNetLK, FMR and DeepGMR."""


import pytest
import torch
from hydra.utils import instantiate
from scipy.spatial.transform import Rotation

from baselines.learned.common.encoders import PointNetEncoder
from baselines.learned.common.global_feature import (
    FeatureMetricDecoder,
    chamfer_loss,
    eval_mode,
    gmm_params,
    gmm_posterior,
    gmm_register,
    inverse_compositional_lk,
    lk_jacobian,
    lk_register,
    rri_features,
    se3_exp,
    skew,
)
from baselines.learned.common.procrustes import weighted_procrustes
from src.compose import compose_model_config
from src.config import register_resolvers
from src.geometry import euler_to_matrix, se3_apply, se3_from_rt, se3_inverse
from src.models.module import RegistrationModule
from tests.helpers.registration_helpers import assert_reloads_the_same

register_resolvers()


def _twist_matrix(twist):
    top = torch.cat((skew(twist[:, :3]), twist[:, 3:, None]), dim=-1)
    return torch.cat((top, torch.zeros_like(top[:, :1])), dim=1)


def test_exp_map_matches_matrix_exp_and_scipy():
    torch.manual_seed(0)
    twist = torch.randn(64, 6, dtype=torch.float64)
    twist[:8, :3] *= 1e-5  # tiny angles (series branch)
    twist[8:16, :3] *= 0.04  # just below / above the series threshold
    twist[16, :3] = 0.0
    twist[17, :3] = torch.tensor([0.0, 0.0, 3.14159])  # near π
    g = se3_exp(twist)
    torch.testing.assert_close(g, torch.linalg.matrix_exp(_twist_matrix(twist)), atol=1e-12, rtol=0)
    torch.testing.assert_close(g[:, :3, :3], torch.from_numpy(Rotation.from_rotvec(twist[:, :3].numpy()).as_matrix()),
                               atol=1e-12, rtol=0)
    g32 = se3_exp(twist.float())  # float32 stays accurate, including the series branch
    torch.testing.assert_close(g32, g.float(), atol=2e-6, rtol=0)
    assert se3_exp(torch.zeros(2, 3, 6)).shape == (2, 3, 4, 4)


def test_exp_map_gradients_including_at_zero():
    twist = torch.cat((torch.zeros(1, 6), torch.randn(3, 6) * 0.05, torch.randn(3, 6)), 0).double().requires_grad_()
    assert torch.autograd.gradcheck(se3_exp, (twist,))
    # d exp(ξ)/dξ_k at 0 is the k-th generator
    jac = torch.autograd.functional.jacobian(lambda x: se3_exp(x), torch.zeros(6, dtype=torch.float64))
    torch.testing.assert_close(jac.permute(2, 0, 1), _twist_matrix(torch.eye(6, dtype=torch.float64)))


def _toy_feature(weight):
    return lambda points: torch.tanh(points @ weight).mean(dim=1)  # smooth, permutation invariant


def test_finite_difference_jacobian_matches_autograd():
    torch.manual_seed(0)
    points = torch.randn(2, 40, 3, dtype=torch.float64)
    feature = _toy_feature(torch.randn(3, 7, dtype=torch.float64))
    exact = torch.stack([
        torch.autograd.functional.jacobian(lambda xi: feature(se3_apply(se3_exp(xi)[None], points[b:b + 1]))[0],
                                           torch.zeros(6, dtype=torch.float64))
        for b in range(2)
    ])  # (B, K, 6)
    fine = lk_jacobian(feature, points, torch.full((6,), 1e-6, dtype=torch.float64))
    torch.testing.assert_close(fine, exact, atol=1e-5, rtol=0)
    coarse = lk_jacobian(feature, points, torch.full((1, 6), 1e-2, dtype=torch.float64))  # PointNetLK's step
    assert (coarse - exact).abs().max() < 2e-2 * exact.abs().max()


def _pair(b=3, n=128, angle=0.5, seed=0):
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(b, n, 3, generator=g) * torch.tensor([0.6, 0.4, 0.2]) + 0.3
    gt = se3_from_rt(euler_to_matrix(torch.rand(b, 3, generator=g) * angle, "zyx"), torch.rand(b, 3, generator=g) - 0.5)
    return se3_apply(se3_inverse(gt), ref), ref, gt


def test_lk_recovers_a_transform_between_copies_with_a_random_pointnet():
    torch.manual_seed(0)
    encoder = PointNetEncoder((3, 32, 64, 256))
    src, ref, gt = _pair()
    with torch.no_grad():
        encoder(ref)  # some BatchNorm statistics
        with eval_mode(encoder):
            result = lk_register(lambda p: encoder(p)[1], src, ref, torch.full((6,), 1e-2), max_iter=20)
    assert encoder.training  # restored
    assert len(result.transforms) == 20 and result.jacobian.shape == (3, 256, 6)
    torch.testing.assert_close(result.transforms[-1], gt, atol=1e-3, rtol=0)


def test_lk_runs_in_float32_under_bf16_autocast():
    torch.manual_seed(0)
    encoder = PointNetEncoder((3, 32, 64, 256)).eval()
    src, ref, _ = _pair(b=2)
    with torch.no_grad():
        plain = lk_register(lambda p: encoder(p)[1], src, ref, torch.full((6,), 1e-2), max_iter=5)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert (torch.randn(2, 3) @ torch.randn(3, 3)).dtype == torch.bfloat16  # autocast is on
            mixed = lk_register(lambda p: encoder(p)[1], src, ref, torch.full((6,), 1e-2), max_iter=5)
            loss = chamfer_loss(src.bfloat16(), ref.bfloat16())
    assert mixed.transforms[-1].dtype == torch.float32 and loss.dtype == torch.float32
    torch.testing.assert_close(mixed.transforms[-1], plain.transforms[-1])


def test_lk_stops_early_and_pads_the_series():
    feature = _toy_feature(torch.randn(3, 8))
    pts = torch.randn(2, 50, 3)
    result = inverse_compositional_lk(feature, pts, pts.clone(), torch.full((6,), 1e-2), max_iter=5, xtol=1e-3)
    assert result.iterations == 0 and len(result.transforms) == 5
    torch.testing.assert_close(result.transforms[-1], torch.eye(4).expand(2, 4, 4))
    with pytest.raises(ValueError, match="max_iter"):
        inverse_compositional_lk(feature, pts, pts, torch.full((6,), 1e-2), max_iter=0)


def test_decoder_and_chamfer():
    decoder = FeatureMetricDecoder(64, num_points=30)
    out = decoder(torch.randn(4, 64))
    assert out.shape == (4, 30, 3) and out.abs().max() <= 1
    a = torch.randn(2, 20, 3)
    assert chamfer_loss(a, a[:, torch.randperm(20)]).item() == pytest.approx(0.0, abs=1e-5)
    b = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0]]])
    c = torch.tensor([[[0.0, 0, 0]]])
    assert chamfer_loss(b, c).item() == pytest.approx(0.5 + 0.0)  # (0 + 1)/2 one way, 0 the other


def test_gmm_posterior_and_parameters():
    torch.manual_seed(0)
    gamma = gmm_posterior(torch.randn(2, 50, 6))
    torch.testing.assert_close(gamma.sum(-1), torch.ones(2, 50))
    pts = torch.randn(2, 50, 3)
    pi, mu, sigma2 = gmm_params(gamma, pts)
    torch.testing.assert_close(pi.sum(-1), torch.ones(2))
    for j in range(6):
        w = gamma[..., j:j + 1]
        mean = (w * pts).sum(1) / w.sum(1)
        torch.testing.assert_close(mu[:, j], mean)
        variance = (w[..., 0] * ((pts - mean[:, None]) ** 2).sum(-1)).sum(1) / w.sum((1, 2))
        torch.testing.assert_close(sigma2[:, j], variance)


@pytest.mark.parametrize("exact", [False, True])
def test_gmm_register_recovers_the_transform_between_mixtures(exact):
    torch.manual_seed(0)
    mu_s = torch.randn(3, 16, 3, dtype=torch.float64)
    pi = torch.softmax(torch.randn(3, 16, dtype=torch.float64), -1)
    sigma2 = torch.rand(3, 16, dtype=torch.float64) + 0.1
    f64 = dict(dtype=torch.float64)
    gt = se3_from_rt(euler_to_matrix(torch.rand(3, 3, **f64) * 3, "xyz"), torch.randn(3, 3, **f64))
    transform = gmm_register(pi, mu_s, se3_apply(gt, mu_s), sigma2, exact=exact)
    torch.testing.assert_close(transform, gt, atol=1e-5, rtol=0)  # weighted_procrustes has eps = 1e-6
    rot = transform[:, :3, :3]
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(3, dtype=torch.float64))


def test_official_gmm_register_is_weighted_procrustes_when_variances_are_equal():
    torch.manual_seed(1)
    mu_s, mu_t = torch.randn(2, 8, 3, dtype=torch.float64), torch.randn(2, 8, 3, dtype=torch.float64)
    pi = torch.softmax(torch.randn(2, 8, dtype=torch.float64), -1)
    sigma2 = torch.full((2, 8), 0.3, dtype=torch.float64)
    torch.testing.assert_close(gmm_register(pi, mu_s, mu_t, sigma2), weighted_procrustes(mu_s, mu_t, pi),
                               atol=1e-5, rtol=0)


@pytest.mark.parametrize("projection", ["authors", "exact"])
def test_rri_features_are_rotation_and_translation_invariant(projection):
    torch.manual_seed(0)
    pts = torch.randn(2, 60, 3, dtype=torch.float64)
    feats = rri_features(pts, k=6, projection=projection)
    assert feats.shape == (2, 60, 24) and torch.isfinite(feats).all()
    moved = se3_apply(se3_from_rt(euler_to_matrix(torch.rand(2, 3, dtype=torch.float64) * 6, "zyx"),
                                  torch.randn(2, 3, dtype=torch.float64)), pts)
    torch.testing.assert_close(rri_features(moved, k=6, projection=projection), feats, atol=1e-9, rtol=0)
    r, theta, phi = feats[..., 0::4], feats[..., 2::4], feats[..., 3::4]
    torch.testing.assert_close(r, pts.sub(pts.mean(1, keepdim=True)).norm(dim=-1, keepdim=True).expand_as(r))
    assert (theta >= 0).all() and (theta <= torch.pi).all() and (phi >= 0).all() and (phi < 2 * torch.pi).all()
    # a mirror image is not a rotation: φ changes orientation
    assert not torch.allclose(rri_features(pts * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), k=6,
                                           projection=projection), feats)


def test_rri_projections_differ_in_phi_only():
    torch.manual_seed(0)
    pts = torch.randn(1, 60, 3, dtype=torch.float64)
    authors, exact = (rri_features(pts, k=6, projection=p).reshape(1, 60, 6, 4) for p in ("authors", "exact"))
    torch.testing.assert_close(authors[..., :3], exact[..., :3], atol=0, rtol=0)  # ‖p‖, ‖q‖, θ
    assert not torch.allclose(authors[..., 3], exact[..., 3])  # q − (p̂·q̂)p leaves the plane ⊥ p: φ's cosine moves
    with pytest.raises(ValueError, match="projection must be one of"):
        rri_features(pts, k=6, projection="plane")


# --- configs and checkpoints -------------------------------------------------------------------

NETWORKS = {
    "pointnetlk": "baselines.learned.pointnetlk.PointNetLK",
    "fmr": "baselines.learned.fmr.FMR",
    "deepgmr": "baselines.learned.deepgmr.DeepGMR",
}


@pytest.mark.parametrize("name", sorted(NETWORKS))
def test_config_composes_and_instantiates_the_module(name):
    cfg = compose_model_config(name, 1.0)
    module = instantiate(cfg)
    assert isinstance(module, RegistrationModule) and module.network_target == NETWORKS[name]
    assert module.hparams["network"]["width"] == 1.0 and module.hparams["euler_seq"] == "zyx"
    module.configure_optimizers()
    smoke = compose_model_config(name, 0.25, ["trainer=smoke", "+exp=unseen_shapes"])
    assert smoke.network.width == 0.25


@pytest.mark.parametrize("name", sorted(NETWORKS))
def test_load_from_checkpoint_rebuilds_the_network(name, tmp_path):
    cfg = compose_model_config(name, 0.125)
    module = instantiate(cfg).eval()
    loaded = assert_reloads_the_same(module, tmp_path / "model.ckpt", *_pair(b=2, n=64)[:2])
    assert loaded.network_target == NETWORKS[name]
