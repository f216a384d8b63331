"""OMNet's fast passes compute the plain dataflow's outputs (tests/helpers/omnet_reference.py) within float tolerance:
training (outputs, gradients, BatchNorm running statistics), batched evaluation and CPU inference (folded
BatchNorm, kept points only, chunks), for both fusion maskings, shared and per-iteration weights and the ablations.

The comparisons run in float64: a small untrained network iterated four times amplifies rounding (in float32
the plain dataflow itself is ~1e-4 from its float64 result after one training-mode iteration on 3 clouds, ~1
after four), so float32 would test the conditioning, not the math. In float64 the same amplification leaves ~1e-9
to 2e-8 between the two on a given machine (the order of the BLAS sums differs between CPUs: 1.7e-8 absolute,
2.8e-6 relative on the topk configuration here): the tolerance sits well above that and far below what a wrong
mask, pool or fold gives (O(0.1) and more)."""

import copy

import pytest
import torch

from src.models.omnet import OMNet, OMNetIteration
from tests.helpers.omnet_reference import _iteration, reference_forward
from tests.helpers.registration_helpers import partial_pair_batch

TOL = dict(rtol=1e-5, atol=1e-6)
CONFIGS = {
    "official": {},
    "every_layer": dict(fusion_masking="every_layer"),
    "shared": dict(share_weights=True),
    "shared_every_layer": dict(share_weights=True, fusion_masking="every_layer"),
    "topk": dict(mask_mode="topk", topk=30),
    "B": dict(mask_module=False, mask_loss=False, fusion=False, connection=False),
    "B+M+ML": dict(fusion=False, connection=False),
    "B+M+ML+F": dict(connection=False),
    "no_connection_no_fusion": dict(fusion=False),
    "no_mask_module": dict(mask_module=False, mask_loss=False, connection=False),
}


def _model(seed: int = 0, **flags) -> OMNet:
    """A small float64 OMNet with random BatchNorm affines and running statistics (so folding is not trivial)."""
    torch.manual_seed(seed)
    model = OMNet(width=0.0625, **flags).double()
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, torch.nn.BatchNorm1d):
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
    return model


def _split_masks(model: OMNet, src: torch.Tensor, ref: torch.Tensor) -> None:
    """Put each mask head's decision boundary in the widest gap between the middle half of its points' logit
    differences (block by block, each measured in a pass of a copy in the model's mode, after the earlier blocks
    are set), so that the masks of iterations 3 and 4 keep some points and drop others."""
    if not model.mask_module:
        return
    for k, block in enumerate(model.iterations):
        probe, seen = copy.deepcopy(model), []
        probe.iterations[k].mask_logits.register_forward_hook(lambda _m, _i, out: seen.append(out.detach().reshape(-1, 2)))
        with torch.no_grad():
            probe(src, ref)
        difference = torch.cat(seen).diff(dim=1).flatten().sort().values
        middle = difference[len(difference) // 4 : 3 * len(difference) // 4]
        widest = middle.diff().argmax()  # no point near the boundary, where rounding would decide
        with torch.no_grad():
            block.mask_logits.bias[1] -= (middle[widest] + middle[widest + 1]) / 2


def _batch(b: int, n: int) -> tuple[torch.Tensor, ...]:
    return tuple(t.double() for t in partial_pair_batch(b=b, n=n))


def _flat(outputs: dict) -> list[torch.Tensor]:
    tensors = []
    for key in ("transforms", "quats", "translations", "mask_logits", "mask_labels", "masks"):
        for item in outputs[key]:
            tensors += list(item) if isinstance(item, tuple) else [item]
    return tensors


def _assert_outputs_close(got: dict, want: dict) -> None:
    got, want = _flat(got), _flat(want)
    assert len(got) == len(want)
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, **TOL)


def _masks_are_partial(outputs: dict) -> bool:
    """Some cloud of the masked iterations keeps some points and drops others."""
    masks = torch.stack([m for pair in outputs["masks"][2:] for m in pair])
    return bool(((masks > 0).any(-1) & (masks == 0).any(-1)).any())


@pytest.mark.parametrize("name", CONFIGS)
def test_training_pass_equals_the_plain_dataflow(name):
    """Outputs, every parameter's gradient and the BatchNorm running statistics after a training step."""
    model = _model(**CONFIGS[name]).train()
    src, ref, gt = _batch(b=8, n=40)  # batch statistics of a few clouds would amplify the rounding
    _split_masks(model, src, ref)
    reference = copy.deepcopy(model)
    got, want = model(src, ref, gt), reference_forward(reference, src, ref, gt)
    _assert_outputs_close(got, want)
    if model.mask_module:
        assert _masks_are_partial(want)
    model.loss(got, gt)["loss"].backward()
    reference.loss(want, gt)["loss"].backward()
    scale = max(q.grad.norm() for q in reference.parameters())
    for (name_, p), q in zip(model.named_parameters(), reference.parameters()):
        assert (p.grad - q.grad).norm() <= 1e-6 * q.grad.norm() + 1e-9 * scale, name_
    for (name_, b), c in zip(model.named_buffers(), reference.buffers()):
        torch.testing.assert_close(b, c, **TOL, msg=name_)


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("autograd", [False, True], ids=["inference", "batched"])
def test_evaluation_equals_the_plain_dataflow(name, autograd, monkeypatch):
    """Without autograd on the CPU: the folded, kept-points-only, chunked pass; with autograd: the batched pass."""
    model = _model(**CONFIGS[name]).eval()
    for block in model.iterations:
        block.chunk_rows = 16  # several chunks per cloud (40 points)
    src, ref, gt = _batch(b=3, n=40)
    _split_masks(model, src, ref)
    with torch.no_grad():
        want = reference_forward(model, src, ref, gt)
    inferred = []
    infer = OMNetIteration._infer
    monkeypatch.setattr(OMNetIteration, "_infer", lambda self, *args: inferred.append(1) or infer(self, *args))
    with torch.set_grad_enabled(autograd):
        got = model(src, ref, gt)
    assert len(inferred) == (0 if autograd else model.num_iters)
    _assert_outputs_close(got, want)
    if model.mask_module:
        assert _masks_are_partial(want)


@pytest.mark.parametrize("masking", ["official", "every_layer"])
@pytest.mark.parametrize("train", [True, False])
def test_one_iteration_with_given_masks_including_an_empty_one(masking, train):
    """Masks drawn at random, one cloud with no kept point and one with all: each pass of one iteration."""
    block = _model(fusion_masking=masking).iterations[0].train(train)
    block.chunk_rows = 8
    src, ref, _ = _batch(b=3, n=30)
    mask_src, mask_ref = (torch.rand(3, 30) > 0.4).double(), (torch.rand(3, 30) > 0.6).double()
    mask_src[0], mask_ref[1] = 0.0, 1.0
    want = _iteration(copy.deepcopy(block), src, ref, mask_src, mask_ref)
    passes = [torch.enable_grad] + ([] if train else [torch.no_grad, torch.inference_mode])
    for autograd in passes:
        with autograd():
            got = block(src, ref, mask_src, mask_ref)
        for g, w in zip(got, want):
            torch.testing.assert_close(g, w, **TOL)


def test_all_ones_masks_given_as_none_change_nothing():
    block = _model().iterations[0].train()
    src, ref, _ = _batch(b=2, n=30)
    ones = torch.ones(2, 30, dtype=torch.float64)
    for got, want in zip(block(src, ref, None, None), copy.deepcopy(block)(src, ref, ones, ones)):
        torch.testing.assert_close(got, want, **TOL)


def test_folded_weights_follow_loaded_weights_and_training():
    """The folded weights are cached, and recomputed after load_state_dict, an optimiser step, or training-mode
    passes that move the running statistics."""
    model, other = _model(seed=0).eval(), _model(seed=1).eval()
    src, ref, gt = _batch(b=2, n=40)

    def check():
        with torch.inference_mode():
            got = model(src, ref, gt)
        with torch.no_grad():
            _assert_outputs_close(got, reference_forward(model, src, ref, gt))

    check()
    layer = model.iterations[0].encoder[0]
    assert layer.folded()[0] is layer.folded()[0]  # cached
    model.load_state_dict(other.state_dict())
    check()
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    model.train()
    model.loss(model(src, ref, gt), gt)["loss"].backward()
    optimizer.step()
    model.eval()
    check()
    with torch.no_grad():
        model.train()(src, ref)  # running statistics only
    model.eval()
    check()


def test_inference_after_inference_mode_still_trains():
    """Folded weights made under inference_mode are no inference tensors: later autograd passes work."""
    model = _model().eval()
    src, ref, gt = _batch(b=2, n=30)
    with torch.inference_mode():
        model(src, ref)
    with torch.no_grad():
        model(src, ref)
    model.train()
    model.loss(model(src, ref, gt), gt)["loss"].backward()
    assert all(p.grad is not None for p in model.parameters() if p.requires_grad)
