"""IDAM's authors' code (jiahaowork/idam) and ours side by side on the same pairs: ``benchmarks.studies.lockstep.harness``'s ``idam`` adapter.

Their ``model.py``/``util.py`` are loaded from a checkout outside the repository, never copied or edited; in memory
only, ``Tensor.cuda`` returns the tensor itself and, where ``open3d.open3d.geometry`` (model.py:14, used by the FPFH
embedding only) does not import, a stub stands for it. Recipe for both nets (main.py): Adam lr 1e-4, weight decay 1e-3
(main.py:105), ×0.1 at epoch 30 of 40 (MultiStepLR([30]), main.py:106, --epochs 40 main.py:138: 75 %), batch 16
(main.py:134); IDAM(GNN(64), emb_dims=64, num_iter=3) (main.py:128, :132, :175). Width 1.0 only.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.lockstep.harness --method idam --authors <checkout of jiahaowork/idam> --out RUN \\
        [--steps 1410] [--schedule-steps 1410] [--val-every 141] [--val-pairs 200]

The start check (``start_check.json``) is float64 on the first batch; see :func:`check_same_start`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import sys
import types
from collections.abc import Iterator
from pathlib import Path

import torch
from torch import Tensor, nn

from benchmarks.studies.lockstep.harness import Pair, as_double, check_start, copy_mapped, float64_mode, load_authors_model, se3
from src.utils.errors import ConfigError

AUTHORS_REPO = "jiahaowork/idam"
PROTOCOL = ["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "model=idam"]
#: 1410 steps / validation every 141: our 1-CPU-hour budget run of IDAM (width 1.0, batch 16).
DEFAULTS = {"steps": 1410, "width": 1.0, "batch": 16, "lr": 1e-4, "weight_decay": 1e-3, "milestones": [0.75],
            "val_every": 141}
LABELS = {"ours": "ours (baselines.learned.idam)", "authors": "authors' code (jiahaowork/idam)"}
TITLE = "IDAM, ours and the authors' code in lockstep (real airplanes, TS, PRNet manner, clean)"
#: Their hard-coded constants (model.py:120 knn k=12, :214 N // 6, :198 0.05) and ours that must match them.
FIXED = {"k": 12, "keep_divisor": 6, "match_dist": 0.05}


def load_authors(checkout: Path) -> types.ModuleType:
    """Their ``model`` module (IDAM, GNN, SVDHead, batch_choice) from ``checkout``, on the CPU (open3d's old
    ``open3d.open3d.geometry``, for an FPFH embedding the lockstep does not use, stubbed where it does not import)."""
    return load_authors_model(checkout, AUTHORS_REPO, "idam", ("open3d.open3d", "open3d.open3d.geometry"))


def _block(ours: str, theirs: str, layers: int) -> list[tuple[str, str]]:
    """An MLP of ours (Linear, BN, ReLU per layer, the last a plain Linear) ↔ their Conv{1,2}DBlock."""
    pairs = []
    for k in range(layers - 1):
        pairs += [(f"{ours}.layers.{3 * k}", f"{theirs}.conv.{k}.conv"), (f"{ours}.layers.{3 * k + 1}", f"{theirs}.conv.{k}.bn")]
    return pairs + [(f"{ours}.layers.{3 * (layers - 1)}", f"{theirs}.conv.{layers - 1}")]


def layer_names(num_iters: int) -> list[tuple[str, str]]:
    """(ours, theirs) module names, layer by layer (model.py:52-128, :177-180)."""
    pairs = []
    for j in range(5):  # GNN: propogate1..5, each Conv2DBlock((c, 64, 64)) then Conv1DBlock((64, 64))
        pairs += _block(f"embedding.edges.{j}.mlp", f"emb_nn.propogate{j + 1}.conv2d", 2)
        pairs.append((f"embedding.points.{j}", f"emb_nn.propogate{j + 1}.conv1d.conv.0"))
    pairs += _block("significance", "significance_fc", 3)
    for i in range(num_iters):
        pairs += _block(f"sim_features.{i}", f"sim_mat_conv1.{i}", 2)
        pairs += _block(f"sim_scores.{i}", f"sim_mat_conv2.{i}", 2)
        pairs += _block(f"weight_logits.{i}", f"weight_fc.{i}", 2)
    return pairs


def copy_weights(ours: nn.Module, theirs: nn.Module) -> dict[str, str]:
    """Ours into theirs, exactly: biases where both have them (none where a BN follows, in both)."""
    return copy_mapped(ours, theirs, layer_names(ours.num_iters), zero_missing_bias=False, constants=["head.reflect"])


class IDAMPair(Pair):
    """Ours ((B,N,3), 4×4 ground truth) and theirs ((B,3,N), R (B,3,3), t (B,3); no ground truth in eval).

    ``authors``: their ``model`` module; ``shared_selection``: in training, their random point
    selection (util.py:43 ``batch_choice``) replaced by our draw on the same batch (ours runs first)."""

    def __init__(self, ours: nn.Module, theirs: nn.Module, authors: types.ModuleType | None = None,
                 shared_selection: bool = False) -> None:
        super().__init__(ours, theirs)
        self.authors, self.shared_selection, self._chosen = authors, shared_selection, None

    def outputs(self, name: str, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        src, ref, gt = batch["points_src"], batch["points_ref"], batch["transform_gt"]
        net = self.nets[name]
        if name == "ours":
            with self._recording(net):
                out = net(src, ref, gt)
            return net.loss(out, gt)["loss"], out["transforms"][-1]
        if net.training:
            with self._forcing():
                rot, trans, loss = net(src.transpose(1, 2), ref.transpose(1, 2), gt[:, :3, :3], gt[:, :3, 3])
        else:  # model.py:188: ground truth refused outside training; their loss is 0 then
            rot, trans, loss = net(src.transpose(1, 2), ref.transpose(1, 2))
        return torch.as_tensor(loss, dtype=src.dtype), se3(rot, trans)

    @contextlib.contextmanager
    def _recording(self, net: nn.Module) -> Iterator[None]:
        """Our training selection's source indices kept in ``_chosen`` (when shared)."""
        if not (self.shared_selection and net.training):
            yield
            return
        select = net._training_selection
        net._training_selection = lambda *a: (lambda r: setattr(self, "_chosen", r[0]) or r)(select(*a))
        try:
            yield
        finally:
            del net._training_selection

    @contextlib.contextmanager
    def _forcing(self) -> Iterator[None]:
        """Their ``batch_choice`` returning our positives, then our negatives (when shared)."""
        if not self.shared_selection:
            yield
            return
        if self._chosen is None:
            raise RuntimeError("shared selection: ours must run first on the batch")
        idx, choice = self._chosen.numpy(), self.authors.batch_choice
        picks = iter((idx[:, :idx.shape[1] // 2], idx[:, idx.shape[1] // 2:]))
        self.authors.batch_choice = lambda data, k, p=None, replace=False: next(picks)
        try:
            yield
        finally:
            self.authors.batch_choice, self._chosen = choice, None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--shared-selection", action="store_true",
                        help="their training-time point selection replaced by ours (default: each its own draw)")


def overrides(args: argparse.Namespace) -> list[str]:
    return []


def build(args: argparse.Namespace, cfg) -> IDAMPair:
    """Ours from ``cfg``; theirs IDAM(GNN(64), emb_dims=64, num_iter=3) with our weights; both in train mode."""
    import hydra

    if args.width != 1.0:
        raise ConfigError(f"--width {args.width}: the IDAM lockstep supports width 1.0 only (their channels are fixed)")
    net_cfg = cfg.model.network
    wrong = {k: net_cfg[k] for k, v in FIXED.items() if net_cfg[k] != v}
    if wrong:
        raise ConfigError(f"model.network {wrong}: the authors' code has {FIXED} built in")
    authors = load_authors(args.authors)
    ours = hydra.utils.instantiate(net_cfg)
    theirs = authors.IDAM(authors.GNN(net_cfg.emb_dims), types.SimpleNamespace(emb_dims=net_cfg.emb_dims, num_iter=ours.num_iters))
    copy_weights(ours, theirs)
    return IDAMPair(ours.train(), theirs.train(), authors, getattr(args, "shared_selection", False))


def _procrustes_head(src: Tensor, src_corr: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """Their SVDHead's interface ((B,3,K) points) with our weighted Procrustes (weighted centroids)."""
    from baselines.learned.common.procrustes import weighted_procrustes

    transform = weighted_procrustes(src.transpose(1, 2), src_corr.transpose(1, 2), weights)
    return transform[:, :3, :3], transform[:, :3, 3]


def _record(module: nn.Module, into: list) -> None:
    module.register_forward_hook(lambda _m, _i, output: into.append(output))


def _max_diff(a: Tensor, b: Tensor) -> float:
    return (a - b).abs().max().item()


def _nudged(batch: dict[str, Tensor], size: float = 1e-15) -> dict[str, Tensor]:
    """The batch with its source points moved by ±``size`` (the control: how much rounding alone moves things)."""
    generator = torch.Generator().manual_seed(0)
    noise = torch.randint(0, 2, batch["points_src"].shape, generator=generator).to(batch["points_src"]) * 2 - 1
    return {**batch, "points_src": batch["points_src"] + size * noise}


def _per_iteration(out_a: dict, out_b: dict) -> dict[str, float]:
    """Max differences of two of our outputs (or ours and theirs recast), iteration by iteration."""
    result = {}
    for i in range(len(out_a["similarities"])):
        result[f"similarity_iter{i + 1}"] = _max_diff(out_a["similarities"][i], out_b["similarities"][i])
        result[f"weight_logits_iter{i + 1}"] = _max_diff(out_a["weight_logits"][i], out_b["weight_logits"][i])
    result["transform"] = _max_diff(out_a["transforms"][-1], out_b["transforms"][-1])
    return result


def _eval_pass(pair: IDAMPair, batch: dict[str, Tensor], our_head: bool) -> dict[str, float]:
    """Eval mode (top-k selection): embeddings, significance, per-iteration similarity and weights, poses."""
    ours, theirs = copy.deepcopy(pair.nets["ours"]).double().eval(), copy.deepcopy(pair.nets["authors"]).double().eval()
    seen: dict[str, list] = {k: [] for k in ("emb_o", "sig_o", "emb_t", "sig_t", "sim_t", "w_t")}
    _record(ours.embedding, seen["emb_o"])
    _record(ours.significance, seen["sig_o"])
    _record(theirs.emb_nn, seen["emb_t"])
    _record(theirs.significance_fc, seen["sig_t"])
    for i in range(ours.num_iters):
        _record(theirs.sim_mat_conv2[i], seen["sim_t"])
        _record(theirs.weight_fc[i], seen["w_t"])
    if our_head:
        theirs.head.forward = _procrustes_head
    with torch.no_grad():
        out = ours(batch["points_src"], batch["points_ref"])
        _, transform_theirs = IDAMPair(ours, theirs).outputs("authors", batch)
    emb_t = [seen["emb_t"][1], seen["emb_t"][0]]  # theirs embeds tgt first (model.py:207-208)
    result = {
        "embedding": max(_max_diff(o, t.transpose(1, 2)) for o, t in zip(seen["emb_o"][:2], emb_t)),
        "significance": max(_max_diff(o.squeeze(-1), t.squeeze(1)) for o, t in zip(seen["sig_o"][:2], seen["sig_t"])),
    }
    result.update(_per_iteration(out, {"similarities": [s.squeeze(1).clamp(-20, 20) for s in seen["sim_t"]],
                                       "weight_logits": [w.squeeze(1) for w in seen["w_t"]],
                                       "transforms": [transform_theirs]}))
    if our_head:  # the control: ours against ours with the source points moved by 1e-15
        with torch.no_grad():
            nudged = ours(*(_nudged(batch)[k] for k in ("points_src", "points_ref")))
        result["control_ours_vs_ours_nudged_1e-15"] = _per_iteration(out, nudged)
    return result


def _train_pass(pair: IDAMPair, batch: dict[str, Tensor], our_head: bool, iterations: int | None = None) -> dict[str, float]:
    """Train mode, their selection forced to ours (``batch_choice`` returns our indices): losses and gradients.

    ``iterations``: the copies run only that many of their iterations (``num_iters`` / ``num_iter``)."""
    ours, theirs = copy.deepcopy(pair.nets["ours"]).double().train(), copy.deepcopy(pair.nets["authors"]).double().train()
    if iterations is not None:
        ours.num_iters = theirs.num_iter = iterations
    if our_head:
        theirs.head.forward = _procrustes_head
    twins = IDAMPair(ours, theirs, pair.authors, shared_selection=True)
    loss_ours, transform_ours = twins.outputs("ours", batch)
    loss_theirs, transform_theirs = twins.outputs("authors", batch)
    loss_ours.backward()
    loss_theirs.backward()
    params_ours, params_theirs = dict(ours.named_parameters()), dict(theirs.named_parameters())
    pairs = [(params_ours[o].grad, params_theirs[t].grad.reshape(params_ours[o].shape))
             for t, o in _key_map(pair).items() if o in params_ours and params_ours[o].grad is not None]
    gradient = max(_max_diff(a, b) for a, b in pairs)
    scale = max(b.abs().max().item() for _, b in pairs)
    return {"loss_ours": loss_ours.item(), "loss_authors": loss_theirs.item(),
            "loss_rel": abs(loss_ours.item() - loss_theirs.item()) / abs(loss_theirs.item()),
            "gradient": gradient, "gradient_rel": gradient / scale,
            "transform": _max_diff(transform_ours, transform_theirs)}


@contextlib.contextmanager
def _concatenated_first_layers() -> Iterator[None]:
    """Ours computing the edge and similarity first layers on the concatenated inputs, as theirs does
    (``linear(x_j − x_i)``, ``linear([f_i, g_j, e_ij])``): the same function, summed in another order."""
    import baselines.learned.common.correspondence as correspondence
    import baselines.learned.idam as idam

    edge, first = correspondence.edge_linear, idam.similarity_first_layer
    correspondence.edge_linear = lambda x, idx, linear, mode: linear(correspondence.gather_neighbours(x, idx) - x.unsqueeze(2))
    idam.similarity_first_layer = lambda linear, fs, fr, geometry: linear(torch.cat(
        (fs.unsqueeze(2).expand(-1, -1, fr.shape[1], -1), fr.unsqueeze(1).expand(-1, fs.shape[1], -1, -1), geometry), dim=-1))
    try:
        yield
    finally:
        correspondence.edge_linear, idam.similarity_first_layer = edge, first


def _train_control(pair: IDAMPair, batch: dict[str, Tensor], nudge: bool) -> dict[str, float]:
    """Ours against ours, the same random selection: loss and gradients. ``nudge``: the source points
    moved by 1e-15; else the second run sums the first layers in their order (``_concatenated_first_layers``)."""
    runs = []
    for k, b in enumerate((batch, _nudged(batch) if nudge else batch)):
        net = copy.deepcopy(pair.nets["ours"]).double().train()
        with torch.random.fork_rng(), (_concatenated_first_layers() if k and not nudge else contextlib.nullcontext()):
            torch.manual_seed(0)
            loss = net.loss(net(b["points_src"], b["points_ref"], b["transform_gt"]), b["transform_gt"])["loss"]
        loss.backward()
        runs.append((loss.item(), [p.grad for p in net.parameters() if p.grad is not None]))
    (loss_a, grads_a), (loss_b, grads_b) = runs
    gradient = max(_max_diff(a, b) for a, b in zip(grads_a, grads_b))
    return {"loss_rel": abs(loss_a - loss_b) / abs(loss_a), "gradient": gradient,
            "gradient_rel": gradient / max(g.abs().max().item() for g in grads_a)}


def _key_map(pair: IDAMPair) -> dict[str, str]:
    """Their parameter names → ours (the mapping :func:`copy_weights` uses, on a throwaway copy of theirs)."""
    return copy_weights(pair.nets["ours"], copy.deepcopy(pair.nets["authors"]))


def check_same_start(pair: IDAMPair, batch: dict[str, Tensor], out: Path) -> None:
    """Copies of both in float64 on the first batch, max |ours − theirs| of what is deterministic.

    ``eval``: top-k selection; embeddings, significance scores, per-iteration similarity matrices and
    weight logits, the final pose. From the first Procrustes on the two differ by the documented
    deviation (ours centres on the weighted centroids, theirs on the uniform means, model.py:139-140);
    ``eval_our_procrustes`` repeats it with their SVDHead replaced by ours. ``train``: their random
    selection (util.py:43 batch_choice) forced to our draw, their head ours: loss and every gradient
    (the same training step); ``train_iteration1_only``: the same with one iteration;
    ``train_their_procrustes``: with their head. The untrained network's later iterations amplify
    rounding (near-degenerate covariances, also in training): the ``control`` entries give ours
    against ours with the source moved by 1e-15, and with the first layers summed in their order.
    Required (else ConfigError): iteration 1 in eval ≤ 1e-8; training losses and gradients ≤ 1e-6
    relative (exact to ~1e-15 on synthetic pairs; ~1e-9 on the first real batch, not located)."""
    with float64_mode():
        double = as_double(batch)
        result = {"eval": _eval_pass(pair, double, our_head=False),
                  "eval_our_procrustes": _eval_pass(pair, double, our_head=True),
                  "train_iteration1_only": _train_pass(pair, double, our_head=True, iterations=1),
                  "train": _train_pass(pair, double, our_head=True),
                  "train_control_ours_vs_ours_nudged_1e-15": _train_control(pair, double, nudge=True),
                  "train_control_ours_vs_ours_summed_as_theirs": _train_control(pair, double, nudge=False),
                  "train_their_procrustes": _train_pass(pair, double, our_head=False)}
    eval_diff = max(result["eval"][k] for k in ("embedding", "significance", "similarity_iter1", "weight_logits_iter1"))
    train_diff = max(result[k][rel] for k in ("train_iteration1_only", "train") for rel in ("loss_rel", "gradient_rel"))
    check_start(out, result, eval_diff, train_diff)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.studies.lockstep.idam ...``: ``python -m benchmarks.studies.lockstep.harness --method idam ...``."""
    from benchmarks.studies.lockstep.harness import main as shared_main

    return shared_main(argv, method="idam", prog="python -m benchmarks.studies.lockstep.idam")


if __name__ == "__main__":
    sys.exit(main())
