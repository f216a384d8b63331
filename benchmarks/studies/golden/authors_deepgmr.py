"""wentaoyuan/deepgmr's DeepGMR with the weights of a DeepGMR of ours: the golden reference (``authors.deepgmr``).

Their ``model.py`` and ``data.py`` are loaded from a checkout outside the repository (never copied into it), on the
CPU (``.cuda()`` a no-op), with stubs for what the evaluation does not use (``visu_util``'s plots, model.py:10;
``pycuda``, data.py:10-11, their CUDA RRI). Their ``PointNet`` writes its channel counts as literals
(model.py:123-132: 64, 128, 256, 512 and ``2 * d_model``): :func:`build` makes it at the checkpoint's width as ours
scales them (``scaled(c, width, minimum=MIN_CHANNELS)``), the 4k RRI inputs and the J outputs as given. The weight
map is layer for layer: their ``Conv1dBNReLU`` (conv, BatchNorm, ReLU) is our MLP's (linear, norm, ReLU) triple,
their last convolution our ``logits``.

Their network takes the RRI features from its input (model.py:160-164); their data loader computes them in NumPy
from the centred points (``get_rri(pcd - pcd.mean(axis=0), k)``, data.py:110-111; ``get_rri``, data.py:22-43, as
their CPU path does): :func:`authors_estimate` computes them so from the same points, in float64.
"""

from __future__ import annotations

import types
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from src.utils.errors import ConfigError

REPO = "wentaoyuan/deepgmr"
#: Imports of their model.py and data.py that their evaluation on the CPU does not use.
UNUSED_IMPORTS = ("visu_util", "pycuda", "pycuda.compiler", "pycuda.autoinit")


def load_authors(checkout: Path) -> types.SimpleNamespace:
    """Their ``model`` and ``data`` modules from ``checkout``, on the CPU."""
    from benchmarks.studies.lockstep.harness import _load_file, _stubbed, cuda_on_cpu

    if not (checkout / "model.py").is_file() or not (checkout / "data.py").is_file():
        raise ConfigError(f"--authors {checkout}: no model.py/data.py (a checkout of {REPO} is needed)")
    cuda_on_cpu()  # model.py:46-47: U.cuda(), V.cuda()
    try:
        with _stubbed(UNUSED_IMPORTS):
            return types.SimpleNamespace(model=_load_file("deepgmr_authors_model", checkout / "model.py"),
                                         data=_load_file("deepgmr_authors_data", checkout / "data.py"))
    except ImportError as exc:
        raise ConfigError(f"the authors' code needs {exc.name}") from exc


def _scaled_nn(width: float, literals: tuple[int, ...]) -> types.SimpleNamespace:
    """``torch.nn`` with Conv1d and BatchNorm1d built at ``width`` times the ``literals`` (other counts as given)."""
    from src.models.base import MIN_CHANNELS, scaled

    def w(c: int) -> int:
        return scaled(c, width, minimum=MIN_CHANNELS) if c in literals else c

    namespace = types.SimpleNamespace(**{k: getattr(nn, k) for k in dir(nn) if not k.startswith("_")})
    namespace.Conv1d = lambda c_in, c_out, *a, **k: nn.Conv1d(w(c_in), w(c_out), *a, **k)
    namespace.BatchNorm1d = lambda c, *a, **k: nn.BatchNorm1d(w(c), *a, **k)
    return namespace


def build(model: types.ModuleType, settings: dict) -> nn.Module:
    """Their ``DeepGMR(args)`` (test.py's flags: ``--use_rri``, ``--k``, ``--d_model``, ``--n_clusters``, no T-net)
    for our network's ``settings`` (the checkpoint's ``model.network``), its PointNet at ``settings["width"]``."""
    from src.models.base import MIN_CHANNELS, scaled

    if not settings["use_rri"] or settings["exact_procrustes"]:
        raise ConfigError(f"DeepGMR use_rri={settings['use_rri']}, exact_procrustes={settings['exact_procrustes']}: "
                          "the golden reference is their code's RRI network and gmm_register (model.py:34-54)")
    d_model, width = settings["d_model"], settings["width"]
    literals = (64, 128, 256, 512, d_model, 2 * d_model)
    fixed = (4 * settings["k"], settings["n_clusters"])
    if set(fixed) & set(literals) or scaled(2 * d_model, width, minimum=MIN_CHANNELS) != 2 * scaled(d_model, width, minimum=MIN_CHANNELS):
        raise ConfigError(f"DeepGMR {settings}: their channel literals cannot be told apart at this width")
    args = Namespace(use_tnet=False, use_rri=True, k=settings["k"], d_model=d_model, n_clusters=settings["n_clusters"])
    torch_nn, model.nn = model.nn, _scaled_nn(width, literals)
    try:
        return model.DeepGMR(args)
    finally:
        model.nn = torch_nn


def layer_pairs(theirs: nn.Module) -> list[tuple[str, str]]:
    """(our module, their module) names of every layer with weights: their ``backbone.{encoder,decoder}.i.j``
    is our ``backbone.{encoder,decoder}.layers.(3i + j)``, their last convolution ``backbone.decoder.3`` our
    ``backbone.logits``."""
    pairs = []
    for name, module in theirs.named_modules():
        if not isinstance(module, (nn.Conv1d, nn.BatchNorm1d)):
            continue
        _, stack, *index = name.split(".")
        ours = "backbone.logits" if len(index) == 1 else f"backbone.{stack}.layers.{3 * int(index[0]) + int(index[1])}"
        pairs.append((ours, name))
    return pairs


def authors_network(checkout: Path, ours: nn.Module, settings: dict) -> tuple[types.SimpleNamespace, nn.Module]:
    """Their modules and their DeepGMR with the weights of ``ours`` (built from ``settings``), in eval mode and
    the dtype of ``ours``."""
    from benchmarks.studies.lockstep.harness import copy_mapped

    authors = load_authors(checkout)
    theirs = build(authors.model, settings)
    copy_mapped(ours, theirs, layer_pairs(theirs), zero_missing_bias=False)
    return authors, theirs.to(next(ours.parameters()).dtype).eval()


def authors_estimate(authors: types.SimpleNamespace, theirs: nn.Module, k: int, src: Tensor, ref: Tensor) -> Tensor:
    """(B, 4, 4): their ``T_12`` (model.py:176, the pose test.py reports) of ``forward(pts1, pts2, T_gt)`` on
    (B, N, 3 + 4k) points and their RRI features, ``pts1`` the source; ``T_gt`` enters their loss and errors only
    (model.py:178-187), the identity here. The features: their ``get_rri`` of each centred cloud (data.py:110-111)
    in float64, then the points' dtype."""
    def with_rri(points: Tensor) -> Tensor:
        clouds = points.double().numpy()
        rri = np.stack([authors.data.get_rri(cloud - cloud.mean(axis=0), k) for cloud in clouds])
        return torch.cat((points, torch.from_numpy(rri).to(points.dtype)), dim=-1)

    theirs(with_rri(src), with_rri(ref), torch.eye(4, dtype=src.dtype).expand(len(src), 4, 4))
    return theirs.T_12

