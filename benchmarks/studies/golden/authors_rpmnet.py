"""yewzijian/RPMNet's RPM-Net with the weights of an RPMNet of ours: the golden reference (``authors.rpmnet``).

The authors' ``src/models/rpmnet.py`` (``RPMNetEarlyFusion``) is imported from a checkout outside the repository
(never copied into it); its arguments are those of ``src/arguments.py`` that our network's settings name
(:func:`authors_args`). Its ``ParameterPredictionNet`` has literal channel counts (``src/models/feature_nets.py``:
4-64-64-64-128-1024, 1024-512-256, 2 out): :func:`build` makes it at the checkpoint's width as ours scales them
(``scaled(c, width, 16)``, the 4 inputs and 2 outputs fixed); the feature network takes ``--feat_dim``, our
(scaled) feature width. The weight map is layer for layer: the authors' ``nn.Sequential`` and our MLPs number
their (linear, norm, ReLU) modules alike, and our last linear ``weights_net.out`` is their ``postpool.6``.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import types
from argparse import Namespace
from collections.abc import Iterator
from pathlib import Path

import torch
from torch import Tensor, nn

from src.utils.errors import ConfigError

REPO = "yewzijian/RPMNet"
#: ParameterPredictionNet's channel counts that are not widths: xyz + the cloud flag in, β and α out.
FIXED_CHANNELS = (2, 4)
#: Our parameter network's channels are multiples of its GroupNorm's 16 groups (baselines/learned/rpmnet.py).
PARAMETER_MULTIPLE = 16
#: Top-level packages of the authors' src/ that a name of the same spelling elsewhere must not shadow.
PACKAGES = ("models", "common")


@contextlib.contextmanager
def _authors_packages(src: Path) -> Iterator[None]:
    """``src`` first on the import path and its ``models``/``common`` free to import, for as long as the
    authors' modules import; whatever those names were before is restored afterwards."""
    saved = {k: v for k, v in sys.modules.items() if k.split(".")[0] in PACKAGES}
    for key in saved:
        del sys.modules[key]
    sys.path.insert(0, str(src))
    try:
        yield
    finally:
        sys.path.remove(str(src))
        for key in [k for k in sys.modules if k.split(".")[0] in PACKAGES]:
            del sys.modules[key]
        sys.modules.update(saved)


def load_authors(checkout: Path) -> types.SimpleNamespace:
    """The authors' ``models.rpmnet`` and ``models.feature_nets`` modules from ``checkout`` (its ``src/``)."""
    src = checkout / "src"
    if not (src / "models" / "rpmnet.py").is_file() or not (src / "models" / "feature_nets.py").is_file():
        raise ConfigError(f"--authors {checkout}: no src/models/rpmnet.py (a checkout of {REPO} is needed)")
    with _authors_packages(src):
        try:
            rpmnet = importlib.import_module("models.rpmnet")
            feature_nets = importlib.import_module("models.feature_nets")
        except ImportError as exc:
            raise ConfigError(f"the authors' code needs {exc.name}") from exc
    return types.SimpleNamespace(rpmnet=rpmnet, feature_nets=feature_nets)


def authors_args(settings: dict, feat_dim: int) -> Namespace:
    """The authors' model arguments (``src/arguments.py:38-49``) from our network's settings: ``--radius``,
    ``--num_neighbors``, ``--features``, ``--feat_dim`` (our feature width), ``--no_slack``, ``--num_sk_iter``,
    ``--num_reg_iter`` (evaluation iterations, ``src/eval.py:157``)."""
    return Namespace(radius=settings["radius"], num_neighbors=settings["num_neighbors"], features=list(settings["features"]),
                     feat_dim=feat_dim, no_slack=not settings["slack"], num_sk_iter=settings["num_sk_iter"],
                     num_reg_iter=settings["num_iters"])


def _scaled_nn(width: float) -> types.SimpleNamespace:
    """``torch.nn`` with Conv1d, Linear and GroupNorm built at ``width`` times their channels (as ours)."""
    from src.models.base import scaled

    def w(c: int) -> int:
        return int(c) if c in FIXED_CHANNELS else scaled(int(c), width, PARAMETER_MULTIPLE)

    namespace = types.SimpleNamespace(**{k: getattr(nn, k) for k in dir(nn) if not k.startswith("_")})
    namespace.Conv1d = lambda c_in, c_out, *a, **k: nn.Conv1d(w(c_in), w(c_out), *a, **k)
    namespace.Linear = lambda c_in, c_out, *a, **k: nn.Linear(w(c_in), w(c_out), *a, **k)
    namespace.GroupNorm = lambda groups, c, *a, **k: nn.GroupNorm(groups, w(c), *a, **k)
    return namespace


def build(authors: types.SimpleNamespace, settings: dict, feat_dim: int) -> nn.Module:
    """The authors' ``RPMNetEarlyFusion`` (``src/models/rpmnet.py:218-226``) for our settings, its
    ``ParameterPredictionNet(weights_dim=[0])`` made again at ``settings["width"]``."""
    theirs = authors.rpmnet.RPMNetEarlyFusion(authors_args(settings, feat_dim))
    module_nn = authors.feature_nets.nn
    authors.feature_nets.nn = _scaled_nn(settings["width"])
    try:
        theirs.weights_net = authors.feature_nets.ParameterPredictionNet(weights_dim=[0])
    finally:
        authors.feature_nets.nn = module_nn
    return theirs


def layer_pairs(theirs: nn.Module) -> list[tuple[str, str]]:
    """(our module, their module) names of every layer with weights."""
    pairs = []
    for name, module in theirs.named_modules():
        if not isinstance(module, (nn.Conv1d, nn.Conv2d, nn.Linear, nn.GroupNorm)):
            continue
        net, stack, index = name.split(".")
        ours = f"{net}.out" if (net, stack, index) == ("weights_net", "postpool", "6") else f"{net}.{stack}.layers.{index}"
        pairs.append((ours, name))
    return pairs


def copy_weights(ours: nn.Module, theirs: nn.Module) -> None:
    """Our weights into theirs (every parameter of both mapped; linear (out, in) → conv (out, in, 1[, 1]))."""
    from benchmarks.studies.lockstep.harness import copy_mapped

    copy_mapped(ours, theirs, layer_pairs(theirs), zero_missing_bias=False)


def authors_network(checkout: Path, ours: nn.Module, settings: dict) -> nn.Module:
    """The authors' RPM-Net from ``checkout`` with the weights of ``ours`` (an RPMNet built from ``settings``, the
    checkpoint's ``model.network``), in eval mode and the dtype of ``ours``."""
    theirs = build(load_authors(checkout), settings, ours.feat_extractor.postpool.layers[-1].out_features)
    copy_weights(ours, theirs)
    return theirs.to(next(ours.parameters()).dtype).eval()


def authors_estimate(theirs: nn.Module, ours: nn.Module, src: Tensor, ref: Tensor, num_iters: int) -> Tensor:
    """(B, 4, 4): the authors' ``forward(data, num_reg_iter)`` (``src/eval.py:157``) on (B, N, 6) points and
    normals, its last iteration's transform (the one ``src/eval.py:199, 229-233`` reports). The normals are
    those ``ours`` estimates from the points it receives (``normals: estimated``); the authors' code reads
    them from its input (``src/models/rpmnet.py:177-178``) and estimates none."""
    from baselines.learned.common.correspondence import estimate_normals
    from benchmarks.studies.lockstep.harness import se3

    def with_normals(points: Tensor) -> Tensor:
        return torch.cat((points, estimate_normals(points, ours.normals_k, ours.normal_orientation)), dim=-1)

    transforms, _ = theirs({"points_src": with_normals(src), "points_ref": with_normals(ref)}, num_iters)
    return se3(transforms[-1][:, :3, :3], transforms[-1][:, :3, 3])

