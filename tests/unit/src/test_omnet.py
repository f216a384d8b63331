"""OMNet: output structure, rigid poses, masks schedule, labels, ablation flags, one step lowers the loss."""

import pytest
import torch

from src.geometry import euler_to_matrix, se3_apply, se3_from_rt
from src.models.omnet import OMNet
from tests.helpers.registration_helpers import train_losses

torch.manual_seed(0)


def _batch(b=4, n=96):
    ref = torch.randn(b, n, 3) * torch.tensor([0.6, 0.4, 0.2])
    angles = torch.rand(b, 3) * 0.6
    gt = se3_from_rt(euler_to_matrix(angles, "zyx"), torch.rand(b, 3) - 0.5)
    src = se3_apply(torch.linalg.inv(gt), ref)  # src maps onto ref under gt
    return src, ref, gt


def _small(**kwargs):
    return OMNet(width=0.0625, **kwargs)


def test_outputs_per_iteration_and_rigid_transforms():
    model = _small().eval()
    src, ref, gt = _batch()
    out = model(src, ref, gt)
    assert len(out["transforms"]) == 4 and len(out["mask_logits"]) == 4 and len(out["mask_labels"]) == 4
    final = out["transforms"][-1]
    assert final.shape == (4, 4, 4)
    rot = final[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(rot), torch.ones(4), atol=1e-5, rtol=0)
    assert out["mask_logits"][0][0].shape == (4, 96, 2)


def test_masks_all_ones_for_two_iterations_then_hard():
    model = _small().eval()
    src, ref, gt = _batch()
    masks = model(src, ref, gt)["masks"]
    for i in (0, 1):
        assert torch.all(masks[i][0] == 1) and torch.all(masks[i][1] == 1)
    for i in (2, 3):
        assert set(masks[i][0].unique().tolist()) <= {0.0, 1.0}


def test_topk_masks_keep_k_points():
    model = _small(mask_mode="topk", topk=10).eval()
    src, ref, gt = _batch()
    masks = model(src, ref, gt)["masks"]
    assert torch.all(masks[2][0].sum(dim=1) == 10)


def test_overlap_labels_by_hand():
    model = _small()
    src = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]]])
    ref = torch.tensor([[[0.05, 0, 0], [1.2, 0, 0]]])
    ones_s, ones_r = torch.ones(1, 3), torch.ones(1, 2)
    lab_s, lab_r = model.overlap_labels(src, ref, torch.eye(4)[None], ones_s, ones_r)
    assert lab_s.tolist() == [[1, 0, 0]] and lab_r.tolist() == [[1, 0]]
    # a masked-out source point never matches
    lab_s, lab_r = model.overlap_labels(src, ref, torch.eye(4)[None], torch.tensor([[0.0, 1, 1]]), ones_r)
    assert lab_s.tolist() == [[0, 0, 0]] and lab_r.tolist() == [[0, 0]]


@pytest.mark.parametrize(
    "flags",
    [
        dict(mask_module=False, mask_loss=False, fusion=False, connection=False),  # B
        dict(mask_loss=False, fusion=False, connection=False),  # B+M
        dict(fusion=False, connection=False),  # B+M+ML
        dict(connection=False),  # B+M+ML+F
        dict(share_weights=True),
        dict(trans_loss="l2", num_iters=2),
    ],
)
def test_ablation_variants_run_and_train(flags):
    model = _small(**flags)
    src, ref, gt = _batch()
    losses = model.loss(model(src, ref, gt), gt)
    losses["loss"].backward()
    assert torch.isfinite(losses["loss"])
    if not model.mask_loss_enabled:
        assert losses["loss/mask"].item() == 0.0
    else:
        assert losses["loss/mask"].item() > 0.0


def test_shared_weights_have_a_quarter_of_the_parameters():
    per_iter = sum(p.numel() for p in _small().parameters())
    shared = sum(p.numel() for p in _small(share_weights=True).parameters())
    assert per_iter == 4 * shared


def test_training_steps_lower_the_loss_on_a_tiny_batch():
    torch.manual_seed(1)
    model = _small()
    losses = train_losses(model, _batch(b=8, n=64), steps=15)
    assert losses[-1] < 0.7 * losses[0]


def test_invalid_options_are_rejected():
    with pytest.raises(ValueError, match="mask_mode"):
        OMNet(mask_mode="soft")
    with pytest.raises(ValueError, match="trans_loss"):
        OMNet(trans_loss="l3")


def test_poses_stay_float32_and_rigid_under_bf16_autocast():
    model = _small().eval()
    src, ref, gt = _batch()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(src, ref, gt)
        losses = model.loss(out, gt)
    final = out["transforms"][-1]
    assert final.dtype == torch.float32 and torch.isfinite(losses["loss"])
    rot = final[:, :3, :3]
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3).expand(4, 3, 3), atol=1e-5, rtol=0)


@pytest.mark.parametrize("train", [True, False])
def test_fusion_layer_with_global_features_equals_the_concatenated_input(train):
    """The first fusion layer computes the broadcast global part once per cloud: same function."""
    from src.models.omnet import PointwiseLayer

    torch.manual_seed(0)
    layer = PointwiseLayer(8 + 2 * 16, 12).train(train)
    if not train:
        layer.norm.running_mean.uniform_(-1, 1)
        layer.norm.running_var.uniform_(0.5, 2)
    local, glob = torch.randn(3, 50, 8), torch.randn(3, 32)
    concatenated = torch.cat((local, glob.unsqueeze(1).expand(-1, 50, -1)), dim=-1)
    torch.testing.assert_close(layer.forward_with_global(local, glob), layer(concatenated), rtol=1e-5, atol=1e-5)


def _official_fusion(block, local, own, other, mask):
    """The official dataflow (model/module.py): Encoder masks the 64-d local feature, Fusion runs its three
    layers unmasked and masks only the output; the decoder runs on that output, its features masked."""
    m = mask.unsqueeze(-1)
    n = local.shape[1]
    x = torch.cat((local * m, own.unsqueeze(1).expand(-1, n, -1), other.unsqueeze(1).expand(-1, n, -1)), dim=-1)
    for layer in block.fusion:
        x = layer(x)
    x = x * m
    h, inter = x, []
    for layer in block.decoder:
        h = layer(h)
        inter.append(h * m)
    return x, inter, block.mask_logits(h)


@pytest.mark.parametrize("masking", ["official", "every_layer"])
def test_fusion_masking_follows_the_official_code_by_default(masking):
    """Per-point layers give the kept points the same values either way in eval mode; the two differ through
    the training-mode BatchNorm statistics, which include the masked-out points' features."""
    torch.manual_seed(1)
    block = _small(fusion_masking=masking).iterations[0].train()
    b, n = 2, 40
    local, own, other = torch.randn(b, n, 8), torch.randn(b, 64), torch.randn(b, 64)
    mask = (torch.rand(b, n) > 0.4).float()
    got = block.fuse_and_decode(local, own, other, mask)
    want = _official_fusion(block, local, own, other, mask)
    close = all(torch.allclose(g, w, atol=1e-5) for g, w in zip([got[0], *got[1], got[2]], [want[0], *want[1], want[2]]))
    assert close == (masking == "official")


def test_unknown_fusion_masking_is_refused():
    with pytest.raises(ValueError, match="fusion_masking"):
        OMNet(fusion_masking="some")


def _hand_weighted_ce(logits, labels, weights, per_cloud):
    """Class-weighted cross-entropy written out point by point, with plain Python floats."""
    import math

    clouds = []
    total_wn, total_w = 0.0, 0.0
    for b in range(labels.shape[0]):
        wn, w = 0.0, 0.0
        for n in range(labels.shape[1]):
            l0, l1 = float(logits[b, n, 0]), float(logits[b, n, 1])
            label = int(labels[b, n])
            nll = math.log(math.exp(l0) + math.exp(l1)) - (l1 if label else l0)
            wn += weights[label] * nll
            w += weights[label]
        clouds.append(wn / w)
        total_wn, total_w = total_wn + wn, total_w + w
    return sum(clouds) / len(clouds) if per_cloud else total_wn / total_w


def test_mask_cross_entropy_is_normalised_per_cloud_as_the_official_code():
    """Clouds with different overlap ratios: the official per-cloud reduction differs from the batch one."""
    from src.models.omnet import weighted_mask_cross_entropy

    g = torch.Generator().manual_seed(3)
    logits = torch.randn(3, 7, 2, generator=g, dtype=torch.float64)
    labels = torch.tensor([[1] * 6 + [0], [1, 0, 0, 0, 0, 0, 0], [1, 1, 1, 0, 0, 0, 0]])
    weights = torch.tensor([0.7, 0.3], dtype=torch.float64)
    per_cloud = weighted_mask_cross_entropy(logits, labels, weights, "per_cloud")
    batch = weighted_mask_cross_entropy(logits, labels, weights, "batch")
    assert per_cloud.item() == pytest.approx(_hand_weighted_ce(logits, labels, [0.7, 0.3], True), rel=1e-12)
    assert batch.item() == pytest.approx(_hand_weighted_ce(logits, labels, [0.7, 0.3], False), rel=1e-12)
    assert abs(per_cloud.item() - batch.item()) > 1e-3


def test_omnet_loss_uses_the_configured_mask_reduction():
    src, ref, gt = _batch()
    ref = ref.clone()
    for b in range(ref.shape[0]):  # a different overlap ratio per cloud: the last 10·b points far away
        ref[b, ref.shape[1] - 10 * b:] += 5.0
    losses = {}
    for reduction in ("per_cloud", "batch"):
        torch.manual_seed(0)
        model = _small(mask_ce_reduction=reduction).eval()
        losses[reduction] = model.loss(model(src, ref, gt), gt)["loss/mask"].item()
    assert OMNet().mask_ce_reduction == "per_cloud"
    assert losses["per_cloud"] != pytest.approx(losses["batch"], rel=1e-6)
    with pytest.raises(ValueError, match="mask_ce_reduction"):
        OMNet(mask_ce_reduction="sum")
