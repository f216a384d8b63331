"""Shared correspondence blocks: Sinkhorn, Gumbel-softmax, normals, ball query / PPF, encoders, SVD head."""

import math

import pytest
import torch

from baselines.learned.common.correspondence import (
    DGCNN,
    AttentionPointer,
    AuthorsLayerNorm,
    EdgeConv,
    edge_features,
    edge_linear,
    ball_query,
    estimate_normals,
    gumbel_softmax,
    matching_logits,
    ppf_features,
    sinkhorn,
    soft_correspondence_svd,
)
from baselines.learned.common.layers import MLP, GroupNormLast
from src.models.base import MIN_CHANNELS, scaled
from src.geometry import euler_to_matrix, se3_apply, se3_from_rt


def _rigid(b, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return se3_from_rt(euler_to_matrix(torch.rand(b, 3, generator=g, dtype=dtype) * 3, "zyx"),
                       torch.rand(b, 3, generator=g, dtype=dtype) - 0.5)


def test_sinkhorn_with_slack_rows_and_columns_sum_to_one_with_their_slack():
    torch.manual_seed(0)
    log_alpha = torch.randn(3, 7, 5, dtype=torch.float64) * 2
    padded = sinkhorn(log_alpha, n_iters=200, slack=True, return_padded=True).exp()
    assert padded.shape == (3, 8, 6)
    torch.testing.assert_close(padded[:, :-1, :].sum(dim=2), torch.ones(3, 7, dtype=torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(padded[:, :, :-1].sum(dim=1), torch.ones(3, 5, dtype=torch.float64), atol=1e-6, rtol=0)
    # a few iterations: real columns exactly normalised (with slack), real rows and columns <= 1
    few = sinkhorn(log_alpha, n_iters=5, slack=True, return_padded=True).exp()
    torch.testing.assert_close(few[:, :, :-1].sum(dim=1), torch.ones(3, 5, dtype=torch.float64))
    perm = sinkhorn(log_alpha, n_iters=5, slack=True).exp()
    assert perm.shape == (3, 7, 5)
    assert (perm.sum(dim=1) <= 1 + 1e-9).all() and (perm.sum(dim=2) <= 1 + 1e-6).all()


def test_sinkhorn_without_slack_is_doubly_stochastic_and_slack_absorbs_outliers():
    torch.manual_seed(1)
    perm = sinkhorn(torch.randn(2, 6, 6, dtype=torch.float64), n_iters=300, slack=False).exp()
    ones = torch.ones(2, 6, dtype=torch.float64)
    torch.testing.assert_close(perm.sum(dim=1), ones, atol=1e-6, rtol=0)
    torch.testing.assert_close(perm.sum(dim=2), ones, atol=1e-6, rtol=0)
    # a source point with very low affinity to everything goes (mostly) to the slack column
    log_alpha = torch.zeros(1, 4, 4, dtype=torch.float64)
    log_alpha[0, 0] = -20
    perm = sinkhorn(log_alpha, n_iters=50).exp()
    assert perm[0, 0].sum() < 1e-6 and perm[0, 1:].sum(dim=1).min() > 0.5


def test_gumbel_softmax_shapes_normalisation_and_straight_through_gradient():
    torch.manual_seed(0)
    logits = torch.randn(2, 5, 7, requires_grad=True)
    tau = torch.tensor([0.5, 2.0]).view(2, 1, 1)
    hard = gumbel_softmax(logits, tau, hard=True)
    assert hard.shape == (2, 5, 7)
    torch.testing.assert_close(hard.sum(dim=-1), torch.ones(2, 5))
    assert set(hard.detach().unique().tolist()) <= {0.0, 1.0}
    (hard * torch.randn(2, 5, 7)).sum().backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0  # gradient of the soft sample
    soft = gumbel_softmax(logits.detach(), 1.0, hard=False)
    torch.testing.assert_close(soft.sum(dim=-1), torch.ones(2, 5))
    assert (soft > 0).all()
    a = gumbel_softmax(logits.detach(), 1.0, generator=torch.Generator().manual_seed(3))
    b = gumbel_softmax(logits.detach(), 1.0, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(a, b)
    # the hard sample follows softmax(logits): a dominant logit is (almost) always picked
    peaked = torch.zeros(1, 200, 4)
    peaked[..., 2] = 8.0
    assert (gumbel_softmax(peaked, 1.0).argmax(-1) == 2).float().mean() > 0.95


def test_normals_are_orthogonal_to_a_plane_and_signed_away_from_the_centroid():
    torch.manual_seed(0)
    plane = torch.cat((torch.rand(2, 100, 2) * 2 - 1, torch.zeros(2, 100, 1)), dim=-1)
    transform = _rigid(2)
    moved = se3_apply(transform, plane)
    normals = estimate_normals(moved, k=10)
    assert normals.shape == (2, 100, 3)
    torch.testing.assert_close(normals.norm(dim=-1), torch.ones(2, 100))
    in_plane = moved[:, 1:] - moved[:, :1]  # vectors lying in the plane
    assert (in_plane * normals[:, 1:]).sum(-1).abs().max() < 1e-4
    # a sphere: outward normals, and they rotate with the cloud
    sphere = torch.nn.functional.normalize(torch.randn(1, 400, 3), dim=-1)
    n_sphere = estimate_normals(sphere, k=12)
    assert ((n_sphere * sphere).sum(-1) > 0.95).all()
    rot = transform[:1, :3, :3]
    torch.testing.assert_close(estimate_normals(sphere @ rot.transpose(1, 2) + 3.0, k=12), n_sphere @ rot.transpose(1, 2),
                               atol=1e-4, rtol=0)
    with pytest.raises(ValueError):
        estimate_normals(sphere, orientation="up")


def test_ball_query_excludes_the_point_and_pads_with_it():
    pts = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [5.0, 0, 0]]])
    idx = ball_query(pts, radius=0.15, num_neighbors=3)
    assert idx.shape == (1, 4, 3)
    assert idx[0, 0].tolist() == [1, 0, 0] and idx[0, 1].tolist() == [0, 2, 1] and idx[0, 3].tolist() == [3, 3, 3]
    assert ball_query(pts, radius=10.0, num_neighbors=6)[0, 0].tolist() == [1, 2, 3, 0, 0, 0]


def test_ppf_features_are_rigid_invariant_and_zero_on_padding():
    torch.manual_seed(0)
    pts = torch.randn(2, 40, 3, dtype=torch.float64) * 0.3
    normals = estimate_normals(pts, k=8)
    feats = ppf_features(pts, normals, radius=0.3, num_neighbors=8)
    assert feats["ppf"].shape == (2, 40, 8, 4) and feats["dxyz"].shape == (2, 40, 8, 3) and feats["xyz"].shape == (2, 40, 8, 3)
    transform = _rigid(2, torch.float64)
    moved = ppf_features(se3_apply(transform, pts), normals @ transform[:, :3, :3].transpose(1, 2), 0.3, 8)
    torch.testing.assert_close(moved["ppf"], feats["ppf"])
    padded = feats["dxyz"].norm(dim=-1) == 0
    assert feats["ppf"][padded].abs().max() < 1e-9
    angles = feats["ppf"][..., :3]
    assert (angles >= 0).all() and (angles <= math.pi).all()


def test_soft_correspondence_svd_recovers_a_transform_from_a_permutation():
    torch.manual_seed(0)
    src = torch.randn(2, 30, 3, dtype=torch.float64)
    perm = torch.stack([torch.eye(30, dtype=torch.float64)[torch.randperm(30)] for _ in range(2)])
    transform = _rigid(2, torch.float64)
    ref = perm.transpose(1, 2) @ se3_apply(transform, src)  # ref shuffled; perm maps src i -> ref
    estimate, corr = soft_correspondence_svd(src, ref, perm)
    torch.testing.assert_close(estimate, transform)
    torch.testing.assert_close(corr, se3_apply(transform, src))
    # halved rows with row normalisation give the same points
    estimate, _ = soft_correspondence_svd(src, ref, perm * 0.5, weights=torch.ones(2, 30, dtype=torch.float64), normalize_rows=True)
    torch.testing.assert_close(estimate, transform, atol=1e-4, rtol=0)  # row sums + eps
    feat = torch.randn(2, 30, 16)
    torch.testing.assert_close(matching_logits(feat, feat), feat @ feat.transpose(1, 2) / 4.0)


@pytest.mark.parametrize("dynamic", [False, True])
def test_dgcnn_and_pointer_shapes_and_gradients(dynamic):
    torch.manual_seed(0)
    pts = torch.randn(2, 50, 3)
    dgcnn = DGCNN((8, 8, 16, 16), emb_dims=32, k=6, dynamic=dynamic, negative_slope=0.2 if dynamic else 0.0)
    feat = dgcnn(pts)
    assert feat.shape == (2, 50, 32)
    pointer = AttentionPointer(32, n_blocks=1, n_heads=4, ff_dims=64)
    a, b = pointer(feat, dgcnn(pts[:, :40]))
    assert a.shape == (2, 50, 32) and b.shape == (2, 40, 32)
    (a.sum() + b.sum()).backward()
    assert all(p.grad is not None for p in dgcnn.parameters()) and all(p.grad is not None for p in pointer.parameters())
    # permuting the points permutes the features
    perm = torch.randperm(50)
    torch.testing.assert_close(dgcnn.eval()(pts[:, perm]), dgcnn(pts)[:, perm], atol=1e-5, rtol=0)


def test_the_authors_layer_norm_divides_by_the_unbiased_std_plus_eps_and_keeps_the_state_dict():
    """DCP/PRNet's LayerNorm (PRNet model.py:159-169): (x - mean) / (std + eps), std unbiased; nn.LayerNorm's
    biased variance gives sqrt(n / (n - 1)) times it."""
    x = torch.randn(2, 5, 8, dtype=torch.float64) * 3 + 1
    theirs, torchs = AuthorsLayerNorm(8, eps=0.0).double(), torch.nn.LayerNorm(8, eps=0.0).double()
    torch.testing.assert_close(theirs(x).std(-1), torch.ones(2, 5, dtype=torch.float64))
    torch.testing.assert_close(torchs(x), theirs(x) * math.sqrt(8 / 7))
    with_eps = AuthorsLayerNorm(8, eps=0.5).double()
    torch.testing.assert_close(with_eps(x), (x - x.mean(-1, keepdim=True)) / (x.std(-1, keepdim=True) + 0.5))
    assert list(theirs.state_dict()) == list(torchs.state_dict())  # checkpoints of either load into the other
    pointer = AttentionPointer(8, n_heads=2, ff_dims=16, layer_norm="authors")
    norms = [m for m in pointer.modules() if isinstance(m, torch.nn.LayerNorm)]
    assert len(norms) == 7 and all(isinstance(m, AuthorsLayerNorm) for m in norms)


def test_mlp_group_norm_paths_agree_and_edgeconv_modes():
    torch.manual_seed(0)
    mlp = MLP([5, 16, 16, 8], norm="group", groups=[8, 4, 8], last_activation=False, bias=True)
    x = torch.randn(2, 10, 6, 5)
    reference = x
    for layer in mlp.layers:
        reference = layer(reference)  # channel-last GroupNormLast path
    torch.testing.assert_close(mlp(x), reference, atol=1e-5, rtol=0)
    gn = GroupNormLast(4, 8)
    y = torch.randn(3, 7, 8)
    torch.testing.assert_close(gn(y), torch.nn.functional.group_norm(y.transpose(1, 2), 4).transpose(1, 2))
    idx = torch.arange(7).view(1, 7, 1).expand(3, 7, 2)  # every point its own neighbour
    out = EdgeConv([8, 4], mode="diff", norm="none", last_activation=False)(y, idx)
    assert out.shape == (3, 7, 4)
    assert scaled(512, 0.25, 4) == 128 and scaled(96, 0.0625, 8) == 8 and scaled(64, 1.0) == 64
    assert scaled(64, 0.0625) == 4 and scaled(64, 0.0625, minimum=MIN_CHANNELS) == 8 == MIN_CHANNELS
    with pytest.raises(ValueError):
        MLP([3, 4], norm="layer")


@pytest.mark.parametrize("mode", ["concat", "diff"])
def test_edge_linear_equals_the_linear_map_of_the_edge_features(mode):
    torch.manual_seed(0)
    x = torch.randn(2, 30, 5, dtype=torch.float64)
    idx = torch.randint(0, 30, (2, 30, 4))
    linear = torch.nn.Linear(10 if mode == "concat" else 5, 7).double()
    torch.testing.assert_close(edge_linear(x, idx, linear, mode), linear(edge_features(x, idx, mode)))
    edges = edge_features(x, idx, mode)
    assert edges.shape == (2, 30, 4, 10 if mode == "concat" else 5)
    torch.testing.assert_close(edges[..., :5], x[torch.arange(2).view(2, 1, 1), idx] - (0 if mode == "concat" else x.unsqueeze(2)))
