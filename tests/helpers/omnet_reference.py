"""OMNet's forward pass written plainly, as before the speed work: every iteration encodes both clouds, masks
are applied everywhere (all-ones ones included), the pooled parts are concatenated per point, BatchNorm runs
unfolded, and the overlap labels are recomputed from scratch. It reads the parameters (and updates the running
statistics) of a ``src.models.omnet.OMNet``; the equivalence tests compare that network's own passes with it."""

import torch

from src.geometry import quat_multiply, quat_normalize, quat_to_matrix, se3_apply, se3_from_rt


def _layer(layer, x):
    b, n, _ = x.shape
    return torch.relu(layer.norm(layer.linear(x).reshape(b * n, -1))).reshape(b, n, -1)


def _masked_max(features, mask):
    return (features * mask.unsqueeze(-1)).amax(dim=1)


def _encode(block, points, mask):
    x, local = points, points
    for k, layer in enumerate(block.encoder):
        x = _layer(layer, x)
        if k == 1:
            local = x
    return local, x, _masked_max(x, mask)


def _fuse_and_decode(block, local, own, other, mask):
    m = mask.unsqueeze(-1)
    every_layer = block.fusion_masking == "every_layer"
    n = local.shape[1]
    x = torch.cat((local if every_layer else local * m, own.unsqueeze(1).expand(-1, n, -1), other.unsqueeze(1).expand(-1, n, -1)), dim=-1)
    for k, layer in enumerate(block.fusion):
        x = _layer(layer, x * m if every_layer and k > 0 else x)
    x = x * m
    inter, logits = [], None
    if block.mask_module:
        h = x
        for layer in block.decoder:
            h = _layer(layer, h)
            inter.append(h * m)
        logits = block.mask_logits(h)
    return x, inter, logits


def _iteration(block, src, ref, mask_src, mask_ref):
    local_s, feat_s, glob_s = _encode(block, src, mask_src)
    local_r, feat_r, glob_r = _encode(block, ref, mask_ref)
    pooled, logits = [], []
    for local, feat, own, other, mask in ((local_s, feat_s, glob_s, glob_r, mask_src), (local_r, feat_r, glob_r, glob_s, mask_ref)):
        fused, inter, lg = (None, [], None)
        if block.fusion is not None:
            fused, inter, lg = _fuse_and_decode(block, local, own, other, mask)
        parts = [fused if block.fusion_enabled else feat * mask.unsqueeze(-1)]
        if block.connection:
            parts += inter
        pooled.append(_masked_max(torch.cat(parts, dim=-1), mask))
        logits.append(lg)
    out = block.regressor(torch.cat(pooled, dim=-1))
    return quat_normalize(out[:, :4]), out[:, 4:], logits[0], logits[1]


def _labels(model, src, ref, gt, mask_src, mask_ref):
    with torch.no_grad():
        dist = torch.cdist(se3_apply(gt, src), ref) + 1e6 * (1 - mask_src).unsqueeze(2) + 1e6 * (1 - mask_ref).unsqueeze(1)
        return (dist.amin(2) < model.overlap_dist).long(), (dist.amin(1) < model.overlap_dist).long()


def reference_forward(model, src, ref, gt=None):
    """``model(src, ref, gt)``'s outputs, computed the plain way with the model's modules."""
    b = src.shape[0]
    mask_src, mask_ref = src.new_ones(b, src.shape[1]), ref.new_ones(b, ref.shape[1])
    quat, trans = src.new_tensor([1.0, 0, 0, 0]).expand(b, 4), src.new_zeros(b, 3)
    out = {"transforms": [], "quats": [], "translations": [], "mask_logits": [], "mask_labels": [], "masks": []}
    for i in range(model.num_iters):
        moved = se3_apply(se3_from_rt(quat_to_matrix(quat), trans).detach(), src)
        d_quat, d_trans, logits_src, logits_ref = _iteration(model.block(i), moved, ref, mask_src, mask_ref)
        d_quat, quat_prev, trans_prev = quat_normalize(d_quat), quat.detach(), trans.detach()
        quat = quat_multiply(d_quat, quat_prev)
        trans = (quat_to_matrix(d_quat) @ trans_prev.unsqueeze(-1)).squeeze(-1) + d_trans
        out["transforms"].append(se3_from_rt(quat_to_matrix(quat), trans))
        out["quats"].append(quat)
        out["translations"].append(trans)
        out["masks"].append((mask_src, mask_ref))
        if model.mask_module:
            out["mask_logits"].append((logits_src, logits_ref))
            if gt is not None:
                out["mask_labels"].append(_labels(model, src, ref, gt, mask_src, mask_ref))
            if i + 1 >= model.mask_start_iter:
                mask_src, mask_ref = model.next_mask(logits_src.detach()), model.next_mask(logits_ref.detach())
    return out
