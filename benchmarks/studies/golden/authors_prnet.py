"""WangYueFt/prnet's PRNet on the golden pairs, with the shipped PRNet checkpoint's weights and our Gumbel noise.

Their ``model.py`` is loaded and mapped as in :mod:`benchmarks.studies.lockstep.prnet` (CPU, float64 literals, our
weights copied layer by layer), with two more in-memory edits:

* width: their DGCNN and TemperatureNet write their channel counts as literals (model.py:286-295, :389-398); the
  two are rebuilt with those literals scaled as ours scales them (``src.models.base.scaled``), the transformer and
  the embedding size come from their ``args`` (main.py's flags) at our scaled sizes;
* noise: their evaluation samples Gumbel noise too (``F.gumbel_softmax``, model.py:441, in every mode: there is no
  noiseless path with their ``gumbel_softmax`` sampler). Both codes take the same draws: their ``F.gumbel_softmax``
  is our sampler (:func:`baselines.learned.common.correspondence.gumbel_softmax`: ``softmax((logits + g) / τ)``,
  hard straight-through, the formula of ``F.gumbel_softmax``; g = −log(−log u), u ~ U(0, 1) from torch's global
  generator), seeded with :data:`NOISE_SEED` before each batch of 8 pairs (``authors.BATCH``, ``ours.BATCH``) as the
  framework's registrator seeds each call (``baselines/learned/adapter.py``); their keypoints come in
  ``topk(sorted=True)`` order (model.py:487-488 ``sorted=False``: an order the noise rows follow), as ours.

The estimate is their ``predict`` (model.py:592-604), the pose of their test loop (``_test_one_batch``, :648-685).
"""

from __future__ import annotations

import contextlib
import types
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

#: The seed of the Gumbel noise before each batch, in their code and (the registrator's ``seed``,
#: ``benchmarks.studies.golden.ours``) in ours.
NOISE_SEED = 0
#: Their channel literals in DGCNN and TemperatureNet (model.py:286-295, :389-398) that are widths (6, the
#: edge features' xyz pair, and 1, the temperature, are not).
LITERALS = (64, 128, 256, 512)


def _width_nn(width: float) -> types.SimpleNamespace:
    """``torch.nn`` with Conv2d, BatchNorm2d, Linear and BatchNorm1d built at ``width`` times the :data:`LITERALS`
    (other channel counts, their ``n_emb_dims`` argument among them, as given)."""
    from src.models.base import scaled

    def w(c: int) -> int:
        return scaled(c, width) if c in LITERALS else c

    namespace = types.SimpleNamespace(**{k: getattr(nn, k) for k in dir(nn) if not k.startswith("_")})
    namespace.Conv2d = lambda c_in, c_out, *a, **k: nn.Conv2d(w(c_in), w(c_out), *a, **k)
    namespace.Linear = lambda c_in, c_out, *a, **k: nn.Linear(w(c_in), w(c_out), *a, **k)
    namespace.BatchNorm2d = lambda c, *a, **k: nn.BatchNorm2d(w(c), *a, **k)
    namespace.BatchNorm1d = lambda c, *a, **k: nn.BatchNorm1d(w(c), *a, **k)
    return namespace


def build_authors(model: types.ModuleType, network: dict) -> nn.Module:
    """Their ``PRNet(args)`` with our ``network`` settings at its ``width``: ``args`` carry our scaled embedding
    and feed-forward sizes; DGCNN and TemperatureNet rebuilt with their literals scaled (:func:`_width_nn`)."""
    from benchmarks.studies.lockstep.prnet import FIXED, authors_args
    from src.models.base import scaled
    from src.utils.errors import ConfigError

    wrong = {k: network.get(k) for k, v in FIXED.items() if network.get(k) != v}
    if wrong:
        raise ConfigError(f"PRNet {wrong}: their code has {FIXED} (model.py:53, :441)")
    width = network["width"]
    args = authors_args(network)
    args.n_emb_dims = scaled(network["emb_dims"], width, network["n_heads"])
    args.n_ff_dims = scaled(network["ff_dims"], width)
    if width != 1.0 and args.n_emb_dims in LITERALS:
        raise ConfigError(f"width {width}: the embedding size {args.n_emb_dims} is one of their literals {LITERALS}, "
                          "which are scaled")
    theirs = model.PRNet(args)
    if width != 1.0:
        torch_nn, model.nn = model.nn, _width_nn(width)
        try:
            theirs.acpnet.emb_nn = model.DGCNN(n_emb_dims=args.n_emb_dims)
            theirs.acpnet.temp_net = model.TemperatureNet(args)
        finally:
            model.nn = torch_nn
    return theirs


@contextlib.contextmanager
def our_noise(model: types.ModuleType) -> Iterator[None]:
    """Their ``F.gumbel_softmax`` our sampler (global generator), their keypoints in ``topk(sorted=True)`` order."""
    from baselines.learned.common.correspondence import gumbel_softmax
    from benchmarks.studies.lockstep.prnet import _View

    functional, model.F = model.F, _View(F, gumbel_softmax=gumbel_softmax)
    model.torch.topk = lambda *a, **k: torch.topk(*a, **{**k, "sorted": True})
    try:
        yield
    finally:
        model.F = functional
        del model.torch.topk


def authors_network(checkout: Path, ours: nn.Module, network: dict, dtype: torch.dtype) -> tuple[types.ModuleType, nn.Module]:
    """Their ``model`` module and their PRNet (:func:`build_authors`) with ``ours``'s weights, eval mode, ``dtype``."""
    from benchmarks.studies.lockstep.prnet import copy_weights, load_authors

    model = load_authors(checkout)
    theirs = build_authors(model, network)
    copy_weights(ours, theirs, network["n_blocks"])
    return model, theirs.to(dtype).eval()


def pose(theirs: nn.Module, src: Tensor, ref: Tensor) -> np.ndarray:
    """Their ``predict`` (model.py:592-604: the pose of their test loop's ``_test_one_batch``, :648-685, without
    its loss) on (B, N, 3) clouds after ``torch.manual_seed(NOISE_SEED)``: (B, 4, 4) float64."""
    from benchmarks.studies.lockstep.harness import se3

    torch.manual_seed(NOISE_SEED)
    rotation, translation = theirs.predict(src.transpose(1, 2).contiguous(), ref.transpose(1, 2).contiguous(),
                                           n_iters=theirs.num_iters)
    return se3(rotation, translation).double().numpy()


@contextlib.contextmanager
def same_noise(model: types.ModuleType, dtype: torch.dtype) -> Iterator[None]:
    """:func:`our_noise`, the global generator restored afterwards; in float64 their float32 literals and
    ``.float()`` casts keep float64."""
    from benchmarks.studies.lockstep.harness import float64_mode

    with torch.random.fork_rng(), our_noise(model), float64_mode() if dtype == torch.float64 else contextlib.nullcontext():
        yield
