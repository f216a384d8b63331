"""XiaoshuiHuang/fmr's FMR with the weights of an FMR of ours: the golden reference (``authors.fmr``).

Their ``model.py`` is imported from a checkout outside the repository (never copied into it), with their
``se_math`` package bare (its ``__init__`` also imports the mesh tools: plyfile, Open3D, matplotlib; the model
needs ``se_math.se3`` and ``se_math.invmat`` only). The network is their test's (``FMRTest.create_model``,
model.py:428-435): ``SolveRegistration(PointNet(dim_k), Decoder(), isTest=True)``; the test never calls the decoder
(model.py:221), which keeps the weights it is built with. Their PointNet writes its channels as literals
(model.py:68-70): a width other than 1.0 is refused.

Weight map: their encoder's Conv1d/BatchNorm1d and our encoder's Linear/BatchNorm, in order (their ``h1``, ``h2``
number (conv, norm, ReLU) as our MLP does (linear, norm, ReLU)); their convolutions' biases, which ours has not
(BatchNorm follows), zero; their learned Jacobian step ``dt`` (model.py:128-130) our ``delta``.

The estimate is their test's (``FMRTest.evaluate``, model.py:437-463): eval mode, no gradients,
``estimate_t(template=ref, source=src, maxiter=10)`` (model.py:425, 451) with its default ``xtol`` 1e-7
(model.py:140), one pair at a time (their test loader's ``batch_size=1``, evaluate.py:95; the convergence test
takes the batch's largest step, model.py:262-263), and its ``g``: source → reference in the uncentred frames
(model.py:174-184).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from src.utils.errors import ConfigError

REPO = "XiaoshuiHuang/fmr"
#: Their test's IC iterations (``FMRTest.max_iter``, model.py:425) and convergence threshold (model.py:140).
MAX_ITER, XTOL = 10, 1e-7


def load_authors(checkout: Path):
    """Their ``model`` module from ``checkout`` (its ``se_math`` package without its ``__init__``)."""
    from tests.helpers.make_published_fixtures import load_module, package

    if not (checkout / "model.py").is_file() or not (checkout / "se_math" / "se3.py").is_file():
        raise ConfigError(f"--authors {checkout}: no model.py/se_math/se3.py (a checkout of {REPO} is needed)")
    package("se_math", checkout / "se_math")
    return load_module("fmr_authors_model", checkout / "model.py")


def layer_pairs(ours: nn.Module, theirs: nn.Module) -> list[tuple[str, str]]:
    """(our module, their module) names of the encoders' layers with weights, in order."""
    def layers(module: nn.Module, kinds: tuple[type, ...]) -> list[str]:
        return [f"encoder.{name}" for name, m in module.encoder.named_modules() if isinstance(m, kinds)]

    our_layers = layers(ours, (nn.Linear, nn.BatchNorm1d))
    their_layers = layers(theirs, (nn.Conv1d, nn.BatchNorm1d))
    if len(our_layers) != len(their_layers):
        raise ConfigError(f"our encoder has {len(our_layers)} layers with weights, theirs {len(their_layers)}")
    return list(zip(our_layers, their_layers))


def authors_network(checkout: Path, ours: nn.Module, network: dict) -> nn.Module:
    """Their test's network with the weights of ``ours`` (an FMR built from ``network``, the checkpoint's
    ``model.network``), in eval mode and the dtype of ``ours``."""
    from benchmarks.studies.lockstep.harness import copy_mapped

    if network["width"] != 1.0:
        raise ConfigError(f"FMR width {network['width']}: their PointNet's channels are literals (model.py:68-70)")
    model = load_authors(checkout)
    theirs = model.SolveRegistration(model.PointNet(dim_k=network["dim_k"]), model.Decoder(), isTest=True)
    constants = [k for k in theirs.state_dict() if k == "dt" or k.startswith("decoder.")]
    copy_mapped(ours, theirs, layer_pairs(ours, theirs), zero_missing_bias=True, constants=constants)
    with torch.no_grad():
        theirs.dt.copy_(ours.delta)
    return theirs.to(next(ours.parameters()).dtype).eval()


def pose(theirs: nn.Module, src: Tensor, ref: Tensor) -> np.ndarray:
    """Their test's estimates (B, 4, 4) float64 for (B, N, 3) clouds, one pair at a time."""
    out = []
    for b in range(len(src)):
        theirs.estimate_t(ref[b:b + 1], src[b:b + 1], MAX_ITER, XTOL)
        out.append(theirs.g.double().numpy())
    return np.concatenate(out)
