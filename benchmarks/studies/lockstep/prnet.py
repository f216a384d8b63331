"""PRNet's authors' code (WangYueFt/prnet) and ours side by side on the same pairs: ``benchmarks.studies.lockstep.harness``'s ``prnet``.

Their ``model.py``/``util.py`` are loaded from a checkout outside the repository, never copied or edited. In memory
only: ``Tensor.cuda`` returns the tensor itself; their module's ``torch`` is torch with ``device('cuda')``
(model.py:58) the CPU and its float32 literals (model.py:460-462, :611-615, :652-656) in the default dtype (float32 in
training, float64 in the start check); their ``Logger`` (model.py:508, :576: it opens ``checkpoints/<exp_name>/log``)
does nothing; ``h5py``, ``tqdm``, ``sklearn.metrics`` (model.py:8, :13, :17; their epoch loops' only) are stubbed where
they do not import. Their training loss is their ``_train_one_batch`` (model.py:606-646) with an optimiser that does
nothing and its ``backward`` (:643) caught, so the harness steps both alike; their validation is ``_test_one_batch``
(:648-685, which samples Gumbel noise as ours does: model.py:441 in every mode).

Recipe for both nets (main.py): Adam lr 1e-3 (main.py:107), weight decay 1e-4 (main.py:37), ×0.1 at epochs 30/60/80
of 100 (main.py:39-43) with the scheduler stepped before each epoch (main.py:48): the 0-based epochs 29, 59, 79 are
the first at the lower rate, fractions 0.29/0.59/0.79 of the run; batch 36 (main.py:99). The network: main.py's
defaults (:79-:97, :117-:119; :data:`AUTHORS_ARGS`), DGCNN k = 20 (model.py:53, called without k at :299-311).
Width 1.0 only (their channels are literals, model.py:286-295, :389-398). A float32 step at width 1.0 holds ~1 GB
(ours) and ~1.7 GB (theirs, which builds the (B, 2C, N, k) edge features, model.py:73) per pair of 768 points:
batch 36 wants ~60 GB of memory; ``--batch`` runs a smaller one.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.lockstep.harness --method prnet --authors <checkout of WangYueFt/prnet> --out RUN \\
        [--steps 142] [--batch 36] [--val-every 14] [--val-pairs 200]

Each net draws its own Gumbel noise, in training and validation (theirs ``F.gumbel_softmax``, model.py:441, on
keypoints in ``topk(sorted=False)`` order, :487-488; ours ``torch.rand`` on keypoints by decreasing feature norm):
the same distribution, not the same draws, so the curves are compared statistically, not bit for bit. The start
check (``start_check.json``, float64, the first batch's first two pairs) makes both draw the same noise; see
:func:`check_same_start`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import sys
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from baselines.learned.common.correspondence import gumbel_softmax
from benchmarks.studies.lockstep.harness import Pair, as_double, check_start, copy_mapped, float64_mode, load_authors_model, se3
from src.utils.errors import ConfigError

AUTHORS_REPO = "WangYueFt/prnet"
PROTOCOL = ["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "model=prnet"]
#: 142 steps of batch 36: our 1-CPU-hour budget run of PRNet (cpu_budget_runs/prnet/plan.json, there at width
#: 0.0625); validation every 14 steps: ten along the run, as the IDAM lockstep's.
DEFAULTS = {"steps": 142, "width": 1.0, "batch": 36, "lr": 1e-3, "weight_decay": 1e-4, "milestones": [0.29, 0.59, 0.79],
            "val_every": 14}
LABELS = {"ours": "ours (baselines.learned.prnet)", "authors": "authors' code (WangYueFt/prnet)"}
TITLE = "PRNet, ours and the authors' code in lockstep (real airplanes, TS, PRNet manner, clean)"
#: Our network's settings → (their flag, main.py's default): --n_emb_dims (main.py:79), --n_blocks (:81),
#: --n_heads (:83), --n_iters (:85), --discount_factor (:87), --n_ff_dims (:89), --n_keypoints (:91),
#: --temp_factor (:93), --cat_sampler (:95), --dropout (:97), --cycle_consistency_loss (:117),
#: --feature_alignment_loss (:119). Theirs is built from ours; the lockstep refuses other values.
AUTHORS_ARGS = {"emb_dims": ("n_emb_dims", 512), "n_blocks": ("n_blocks", 1), "n_heads": ("n_heads", 4),
                "num_iters": ("n_iters", 3), "discount": ("discount_factor", 0.9), "ff_dims": ("n_ff_dims", 1024),
                "num_keypoints": ("n_keypoints", 512), "temp_factor": ("temp_factor", 100.0),
                "sampler": ("cat_sampler", "gumbel_softmax"), "dropout": ("dropout", 0.0),
                "cycle_weight": ("cycle_consistency_loss", 0.1),
                "feature_alignment_weight": ("feature_alignment_loss", 0.1)}
#: Their hard-coded constants (model.py:53 k=20; :441 a Gumbel sample in eval too) and ours that must match them.
FIXED = {"k": 20, "deterministic_eval": False}
#: Their modules (main.py:70-78 defaults) and what ACPNet stores unused (model.py:507: n_subsampled_points, only
#: compared with n_keypoints at :532; None: their KeyPointNet always, the clouds need ≥ n_keypoints points).
MODULES = {"emb_nn": "dgcnn", "attention": "transformer", "head": "svd", "n_subsampled_points": None, "model_path": "",
           "exp_name": "lockstep"}
#: Imported by model.py (:8, :13, :17), used by their epoch loops only: stubbed where they do not import.
UNUSED_IMPORTS = ("h5py", "tqdm", "sklearn", "sklearn.metrics")
#: Their parameters that ours lacks: SVDHead's reflection matrix and its unused temperature (model.py:419-421).
CONSTANTS = ("acpnet.head.reflect", "acpnet.head.temperature")
#: The start check's pairs (of the first batch): in float64 at width 1.0 on 768 points a pass of their code holds
#: ~3.5 GB a pair (their (B, 2C, N, k) edge features, model.py:73), so the check is bounded whatever ``--batch``;
#: two, the fewest their TemperatureNet's train-mode BatchNorm accepts (model.py:390).
CHECK_PAIRS = 2


class _View(types.ModuleType):
    """``module`` with a few functions replaced, for the authors' module's global of that name only."""

    def __init__(self, module: types.ModuleType, **replaced: Callable) -> None:
        super().__init__(module.__name__)
        self._module = module
        self.__dict__.update(replaced)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._module, name)


def _default_dtype(make: Callable) -> Callable:
    """``make`` (torch.eye, torch.zeros) with dtype=float32 meaning the default dtype."""
    return lambda *a, dtype=None, **k: make(*a, dtype=None if dtype is torch.float32 else dtype, **k)


def _from_numpy(array: Any) -> Tensor:
    tensor = torch.from_numpy(array)
    return tensor.to(torch.get_default_dtype()) if tensor.is_floating_point() else tensor


def cpu_torch() -> _View:
    """torch for their model.py: ``torch.device('cuda')`` the CPU, float32 literals in the default dtype."""
    return _View(torch, device=lambda *a, **k: torch.device("cpu"), eye=_default_dtype(torch.eye),
                 zeros=_default_dtype(torch.zeros), from_numpy=_from_numpy)


class _NoLogger:
    """Their Logger (model.py:831-870) writing nothing."""

    def __init__(self, args: Any) -> None:
        pass


def load_authors(checkout: Path) -> types.ModuleType:
    """Their ``model`` module (PRNet and its parts) from ``checkout``, on the CPU."""
    model = load_authors_model(checkout, AUTHORS_REPO, "prnet", UNUSED_IMPORTS)
    if not all(hasattr(model, name) for name in ("PRNet", "ACPNet", "KeyPointNet", "get_graph_feature")):
        raise ConfigError(f"--authors {checkout}: its model.py is not PRNet's (a checkout of {AUTHORS_REPO} is needed)")
    model.torch, model.Logger = cpu_torch(), _NoLogger
    return model


def authors_args(network: dict[str, Any]) -> types.SimpleNamespace:
    """Their ``args`` (main.py's flags) carrying our network's settings."""
    return types.SimpleNamespace(**{flag: network[ours] for ours, (flag, _) in AUTHORS_ARGS.items()}, **MODULES)


def _attention(ours: str, theirs: str) -> list[tuple[str, str]]:
    """Our attention's q, k, v, out ↔ their MultiHeadedAttention's linears 0-3 (model.py:222, :234-245)."""
    return [(f"{ours}.{name}", f"{theirs}.linears.{j}") for j, name in enumerate(("q", "k", "v", "out"))]


def layer_names(n_blocks: int) -> list[tuple[str, str]]:
    """(ours, theirs) Linear/BatchNorm module names (model.py:286-295, :366-372, :389-398)."""
    pairs = []
    for i in range(5):  # DGCNN: four edge convolutions, then the fusion of their concatenation
        ours = f"embedding.layers.{i}.mlp.layers" if i < 4 else "embedding.fuse.layers"
        pairs += [(f"{ours}.0", f"acpnet.emb_nn.conv{i + 1}"), (f"{ours}.1", f"acpnet.emb_nn.bn{i + 1}")]
    model = "acpnet.attention.model"
    for b in range(n_blocks):
        pairs += _attention(f"pointer.encoder.{b}.self_attn", f"{model}.encoder.layers.{b}.self_attn")
        pairs += _attention(f"pointer.decoder.{b}.self_attn", f"{model}.decoder.layers.{b}.self_attn")
        pairs += _attention(f"pointer.decoder.{b}.cross_attn", f"{model}.decoder.layers.{b}.src_attn")
        for part in ("encoder", "decoder"):
            pairs += [(f"pointer.{part}.{b}.ff.w1", f"{model}.{part}.layers.{b}.feed_forward.w_1"),
                      (f"pointer.{part}.{b}.ff.w2", f"{model}.{part}.layers.{b}.feed_forward.w_2")]
    return pairs + [(f"temperature_net.layers.{j}", f"acpnet.temp_net.nn.{j}") for j in (0, 1, 3, 4, 6, 7, 9)]


def layer_norm_names(n_blocks: int) -> list[tuple[str, str]]:
    """(ours, theirs) LayerNorm names: ours weight/bias, theirs a_2/b_2 (model.py:137, :151, :159-179)."""
    model = "acpnet.attention.model"
    pairs = [("pointer.encoder_norm", f"{model}.encoder.norm"), ("pointer.decoder_norm", f"{model}.decoder.norm")]
    for b in range(n_blocks):
        pairs += [(f"pointer.{part}.{b}.norms.{j}", f"{model}.{part}.layers.{b}.sublayer.{j}.norm")
                  for part, count in (("encoder", 2), ("decoder", 3)) for j in range(count)]
    return pairs


def copy_weights(ours: nn.Module, theirs: nn.Module, n_blocks: int) -> dict[str, str]:
    """Ours into theirs, exactly (their convolutions' biases are off where a BatchNorm follows, as ours).

    Returns their key → our key of every copied tensor."""
    norms = {f"{t}.{their}": f"{o}.{our}" for o, t in layer_norm_names(n_blocks)
             for our, their in (("weight", "a_2"), ("bias", "b_2"))}
    mapped = copy_mapped(ours, theirs, layer_names(n_blocks), zero_missing_bias=False, constants=[*CONSTANTS, *norms])
    with torch.no_grad():
        for their_key, our_key in norms.items():
            theirs.get_parameter(their_key).copy_(ours.get_parameter(our_key))
    return {**mapped, **norms}


#: The optimiser their ``_train_one_batch`` is handed (model.py:607, :644): the harness steps the net itself.
_NO_OPTIMISER = types.SimpleNamespace(zero_grad=lambda: None, step=lambda: None)


@contextlib.contextmanager
def _caught_backward() -> Iterator[list[Tensor]]:
    """``Tensor.backward`` keeping the tensor instead (their ``total_loss.backward()``, model.py:643)."""
    backward, caught = torch.Tensor.backward, []
    torch.Tensor.backward = lambda self, *args, **kwargs: caught.append(self)
    try:
        yield caught
    finally:
        torch.Tensor.backward = backward


class PRNetPair(Pair):
    """Ours ((B,N,3), 4×4 ground truth) and theirs ((B,3,N), R_ab (B,3,3), t_ab (B,3)); ``authors``: their module."""

    def __init__(self, ours: nn.Module, theirs: nn.Module, authors: types.ModuleType) -> None:
        super().__init__(ours, theirs)
        self.authors = authors

    def outputs(self, name: str, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        src, ref, gt = batch["points_src"], batch["points_ref"], batch["transform_gt"]
        net = self.nets[name]
        if name == "ours":
            out = net(src, ref, gt)
            return net.loss(out, gt)["loss"], out["transforms"][-1]
        inputs = (src.transpose(1, 2).contiguous(), ref.transpose(1, 2).contiguous(), gt[:, :3, :3], gt[:, :3, 3])
        if net.training:
            with _caught_backward() as caught:
                *_, rot, trans = net._train_one_batch(*inputs, _NO_OPTIMISER)
            return caught[0], se3(rot, trans)
        loss, *_, rot, trans = net._test_one_batch(*inputs)
        return torch.as_tensor(loss, dtype=src.dtype), se3(rot, trans)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """No options of its own."""


def overrides(args: argparse.Namespace) -> list[str]:
    return []


def make_pair(authors: types.ModuleType, network: dict[str, Any]) -> PRNetPair:
    """Ours ``PRNet(**network)`` and theirs with the same settings and our weights, both in train mode."""
    from baselines.learned.prnet import PRNet

    ours = PRNet(**network)
    theirs = authors.PRNet(authors_args(network))
    copy_weights(ours, theirs, network["n_blocks"])
    return PRNetPair(ours.train(), theirs.train(), authors)


def build(args: argparse.Namespace, cfg) -> PRNetPair:
    """Ours from ``cfg`` (main.py's defaults required), theirs PRNet(args) with our weights; both in train mode."""
    from omegaconf import OmegaConf

    if args.width != 1.0:
        raise ConfigError(f"--width {args.width}: the PRNet lockstep supports width 1.0 only (their channels are "
                          "fixed)")
    network = {k: v for k, v in OmegaConf.to_container(cfg.model.network, resolve=True).items() if k != "_target_"}
    wanted = {**{k: v for k, (_, v) in AUTHORS_ARGS.items()}, **FIXED}
    wrong = {k: network.get(k) for k, v in wanted.items() if network.get(k) != v}
    if wrong:
        raise ConfigError(f"model.network {wrong}: the lockstep runs the authors' settings {wanted}")
    return make_pair(load_authors(args.authors), network)


@contextlib.contextmanager
def _same_noise(authors: types.ModuleType) -> Iterator[Callable[[], None]]:
    """Both drawing the same Gumbel noise: our sampler in both (theirs is ``F.gumbel_softmax``, model.py:441), from
    one generator that the yielded ``reseed()`` restarts, their keypoints sorted as ours (:487-488 ``sorted=False``)."""
    import baselines.learned.prnet as prnet

    generator = torch.Generator()
    sample = functools.partial(gumbel_softmax, generator=generator)
    sampler, functional = prnet.gumbel_softmax, authors.F
    prnet.gumbel_softmax, authors.F = sample, _View(F, gumbel_softmax=sample)
    authors.torch.topk = lambda *a, **k: torch.topk(*a, **{**k, "sorted": True})
    try:
        yield lambda: generator.manual_seed(0)
    finally:
        prnet.gumbel_softmax, authors.F = sampler, functional
        del authors.torch.topk


#: Ours's deviation from theirs, removable in the start check by :func:`_ours_as_theirs` (their LayerNorm,
#: model.py:159-169, is ours: ``baselines.learned.common.correspondence.AuthorsLayerNorm``).
DEVIATIONS = ("svd_weights",)


@contextlib.contextmanager
def _ours_as_theirs(net: nn.Module, deviations: tuple[str, ...] = DEVIATIONS) -> Iterator[None]:
    """``net`` (a copy of ours) computing ``deviations`` as theirs: ``svd_weights`` their uniform SVD weights 1/K
    (their means, model.py:448-468; ours 1/(K + 1e-5), the ε of ``soft_correspondence_svd``)."""
    import baselines.learned.prnet as prnet

    solve = prnet.soft_correspondence_svd
    if "svd_weights" in deviations:
        prnet.soft_correspondence_svd = functools.partial(solve, eps=0.0)
    try:
        yield
    finally:
        prnet.soft_correspondence_svd = solve


def _max_diff(a: Tensor, b: Tensor) -> float:
    return (a - b).abs().max().item()


def _twins(pair: PRNetPair, train: bool) -> PRNetPair:
    """float64 copies of both, in train or eval mode."""
    ours, theirs = copy.deepcopy(pair.nets["ours"]).double(), copy.deepcopy(pair.nets["authors"]).double()
    return PRNetPair(ours.train(train), theirs.train(train), pair.authors)


def _record(module: nn.Module, into: list) -> None:
    module.register_forward_hook(lambda _m, _i, output: into.append(output))


def _eval_pass(pair: PRNetPair, batch: dict[str, Tensor]) -> dict[str, float]:
    """Eval mode, the same noise, ours as theirs: embeddings and pointer (iteration 1), each iteration's X→Y and
    Y→X steps and feature disparity, the final pose."""
    twins = _twins(pair, train=False)
    ours, theirs = twins.nets["ours"], twins.nets["authors"]
    seen: dict[str, list] = {k: [] for k in ("emb_o", "ptr_o", "emb_t", "ptr_t", "step_t")}
    _record(ours.embedding, seen["emb_o"])
    _record(ours.pointer, seen["ptr_o"])
    _record(theirs.acpnet.emb_nn, seen["emb_t"])
    _record(theirs.acpnet.attention, seen["ptr_t"])
    _record(theirs.acpnet, seen["step_t"])  # (R_ab, t_ab, R_ba, t_ba, disparity) per iteration (model.py:541)
    with torch.no_grad(), _same_noise(pair.authors) as reseed, _ours_as_theirs(ours):
        reseed()
        out = ours(batch["points_src"], batch["points_ref"])
        reseed()
        _, transform_theirs = twins.outputs("authors", batch)
    result = {"embedding": max(_max_diff(o, t.transpose(1, 2)) for o, t in zip(seen["emb_o"][:2], seen["emb_t"][:2])),
              "pointer": max(_max_diff(o, t.transpose(1, 2)) for o, t in zip(seen["ptr_o"][0], seen["ptr_t"][0]))}
    for i, (rot_ab, t_ab, rot_ba, t_ba, disparity) in enumerate(seen["step_t"]):
        result[f"step_ab_iter{i + 1}"] = _max_diff(out["steps_ab"][i], se3(rot_ab, t_ab))
        result[f"step_ba_iter{i + 1}"] = _max_diff(out["steps_ba"][i], se3(rot_ba, t_ba))
        result[f"disparity_iter{i + 1}"] = _max_diff(out["disparities"][i], disparity)
    result["transform"] = _max_diff(out["transforms"][-1], transform_theirs)
    return result


def _key_map(pair: PRNetPair) -> dict[str, str]:
    """Their parameter names → ours (the mapping :func:`copy_weights` uses, on a throwaway copy of theirs)."""
    return copy_weights(pair.nets["ours"], copy.deepcopy(pair.nets["authors"]), len(pair.nets["ours"].pointer.encoder))


def _train_pass(pair: PRNetPair, batch: dict[str, Tensor], same_noise: bool = True,
                as_theirs: tuple[str, ...] = DEVIATIONS) -> dict[str, float]:
    """Train mode: losses, every gradient, the final pose. ``same_noise``: :func:`_same_noise`, else each its own
    sampler after the same seed (as the lockstep trains); ``as_theirs``: the deviations that :func:`_ours_as_theirs`
    removes."""
    twins = _twins(pair, train=True)
    noise = _same_noise(pair.authors) if same_noise else contextlib.nullcontext(lambda: torch.manual_seed(0))
    with torch.random.fork_rng(), noise as reseed, _ours_as_theirs(twins.nets["ours"], as_theirs):
        reseed()
        loss_ours, transform_ours = twins.outputs("ours", batch)
        loss_ours.backward()  # before their forward: one graph alive at a time
        reseed()
        loss_theirs, transform_theirs = twins.outputs("authors", batch)
        loss_theirs.backward()
    params_ours = dict(twins.nets["ours"].named_parameters())
    params_theirs = dict(twins.nets["authors"].named_parameters())
    pairs = [(params_ours[o].grad, params_theirs[t].grad.reshape(params_ours[o].shape))
             for t, o in _key_map(pair).items() if o in params_ours and params_ours[o].grad is not None]
    gradient = max(_max_diff(a, b) for a, b in pairs)
    return {"loss_ours": loss_ours.item(), "loss_authors": loss_theirs.item(),
            "loss_rel": abs(loss_ours.item() - loss_theirs.item()) / abs(loss_theirs.item()),
            "gradient": gradient, "gradient_rel": gradient / max(b.abs().max().item() for _, b in pairs),
            "transform": _max_diff(transform_ours, transform_theirs)}


def check_same_start(pair: PRNetPair, batch: dict[str, Tensor], out: Path) -> None:
    """Copies of both in float64 on the first batch's first :data:`CHECK_PAIRS` pairs, max |ours − theirs|.

    ``eval`` and ``train``: both draw the same Gumbel noise (our sampler in both from one reseeded generator,
    their keypoints sorted as ours) and ours computes its deviation as theirs (their exact uniform SVD weights): the
    same function, checked — ``eval`` embeddings, pointer, per-iteration steps and disparities, pose; ``train`` loss,
    every gradient, pose. ``train_our_svd_weights``: the same with ours's deviation kept (its size). ``train_own_noise``: each its own sampler after the same
    seed, as the lockstep trains: their draws fall elsewhere (``exponential_`` vs ``rand``, unsorted keypoints), so
    this one differs.
    Required (else ConfigError): ``eval`` iteration 1 ≤ 1e-8; ``train`` loss and gradients ≤ 1e-6 relative."""
    with float64_mode():
        double = as_double({k: v[:CHECK_PAIRS] if torch.is_tensor(v) else v for k, v in batch.items()})
        result = {"eval": _eval_pass(pair, double),
                  "train": _train_pass(pair, double),
                  "train_our_svd_weights": _train_pass(pair, double, as_theirs=()),
                  "train_own_noise": _train_pass(pair, double, same_noise=False)}
    iteration1 = ("embedding", "pointer", "step_ab_iter1", "step_ba_iter1", "disparity_iter1")
    eval_diff = max(result["eval"][k] for k in iteration1)
    train_diff = max(result["train"]["loss_rel"], result["train"]["gradient_rel"])
    check_start(out, result, eval_diff, train_diff)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.studies.lockstep.prnet ...``: ``python -m benchmarks.studies.lockstep.harness --method prnet ...``."""
    from benchmarks.studies.lockstep.harness import main as shared_main

    return shared_main(argv, method="prnet", prog="python -m benchmarks.studies.lockstep.prnet")


if __name__ == "__main__":
    sys.exit(main())
