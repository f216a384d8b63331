"""OMNet's authors' code and ours side by side on the same pairs: ``benchmarks.studies.lockstep.harness``'s ``omnet`` adapter.

The authors' PyTorch port (``hxwork/OMNet_Pytorch``: ``model/net.py``, ``model/module.py``,
``loss/loss.py``; the MegEngine original does not install on this Python) is read from a checkout
outside the repository and never copied. Three edits are made in memory, never in the files:
``Tensor.cuda`` returns the tensor itself (the port calls ``.cuda()`` on every mask), the channel
counts of its layers are scaled by ``--width`` exactly as ``model_scale`` scales ours, and where
``pytorch3d`` is not installed an empty module stands for it (``common/so3.py`` imports it for
its metrics, which are not called here).
Both networks start from the same weights (ours copied into theirs; the port's conv and linear
biases are zero, and stay zero: train-mode BatchNorm cancels them), see the same batches in the
same order, and each has its own Adam and the same step schedule. Before training, one forward
pass on the first batch checks that the two give the same poses. Every ``--val-every`` steps both
are evaluated on the experiment's validation pairs.

    pip install transforms3d coloredlogs       # what the port imports (not a dependency of the package)
    OMP_NUM_THREADS=1 python -m benchmarks.studies.lockstep.omnet --authors <checkout of hxwork/OMNet_Pytorch> \\
        --out RUN [--steps 1086] [--schedule-steps 1086] [--width 0.25] [--lr 1e-4] [--val-every 109]

Resumable: ``state.pt`` in ``--out`` every ``--val-every`` steps; ``curves.csv`` (step, net, training
loss, validation Error(R)/Error(t)). ``--mask-ce batch`` (the default) gives ours the port's mask
cross-entropy reduction (``nn.CrossEntropyLoss(weight=...)`` over all points, ``loss/loss.py``), so
that the two losses are the same function.
"""

from __future__ import annotations

import argparse
import copy
import importlib
import importlib.util
import sys
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from benchmarks.studies.lockstep.harness import Pair, as_double, copy_mapped, cuda_on_cpu, float64_mode, write_check
from src.utils.errors import ConfigError
from src.models.base import MIN_CHANNELS, scaled

AUTHORS_REPO = "hxwork/OMNet_Pytorch"
#: The port's channel counts that are not widths: the points' xyz in, the mask's two classes and the pose's 7 out.
FIXED_CHANNELS = (2, 3, 7)
PROTOCOL = ["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "model=omnet",
            "recipe=omnet_official"]
DEFAULTS = {"steps": 1086, "width": 0.25, "batch": 16, "lr": 1e-4, "weight_decay": 0.0, "milestones": [0.7, 0.9],
            "val_every": 109}
LABELS = {"ours": "ours (src.models.omnet)", "authors": "authors' code (hxwork/OMNet_Pytorch)"}
TITLE = "OMNet, ours and the authors' code in lockstep (real airplanes, TS, PRNet manner, clean)"


def scaled_nn(width: float) -> types.SimpleNamespace:
    """``torch.nn`` with Conv1d, Linear and BatchNorm1d built at ``width`` times their channels."""
    def w(c: int) -> int:
        return c if c in FIXED_CHANNELS else scaled(c, width, minimum=MIN_CHANNELS)

    namespace = types.SimpleNamespace(**{k: getattr(nn, k) for k in dir(nn) if not k.startswith("_")})
    namespace.Conv1d = lambda c_in, c_out, *a, **k: nn.Conv1d(w(c_in), w(c_out), *a, **k)
    namespace.Linear = lambda c_in, c_out, *a, **k: nn.Linear(w(c_in), w(c_out), *a, **k)
    namespace.BatchNorm1d = lambda c, *a, **k: nn.BatchNorm1d(w(c), *a, **k)
    return namespace


def load_authors(checkout: Path, width: float) -> types.SimpleNamespace:
    """The port's ``OMNet`` class and ``compute_loss`` on the CPU, its layers at ``width``."""
    if not (checkout / "model" / "net.py").is_file():
        raise ConfigError(f"--authors {checkout}: no model/net.py (a checkout of hxwork/OMNet_Pytorch is needed)")
    cuda_on_cpu()
    if importlib.util.find_spec("pytorch3d") is None:  # common/so3.py's import, used by its metrics only (not called)
        sys.modules["pytorch3d"] = types.ModuleType("pytorch3d")
        sys.modules["pytorch3d"].transforms = None
    sys.path.insert(0, str(checkout))
    try:
        module = importlib.import_module("model.module")
        module.nn = scaled_nn(width)
        net = importlib.import_module("model.net")
        loss = importlib.import_module("loss.loss")
    except ImportError as exc:
        raise ConfigError(f"the authors' code needs {exc.name}: pip install transforms3d coloredlogs") from exc
    finally:
        sys.path.remove(str(checkout))
    return types.SimpleNamespace(OMNet=net.OMNet, compute_loss=loss.compute_loss)


def _layer_names(i: int) -> list[tuple[str, str]]:
    """(ours, theirs) module names of iteration ``i``, layer by layer: (linear, norm) pairs and the two heads."""
    pairs = []
    for ours, theirs, count in (("encoder", "encoder", 5), ("fusion", "fusion", 3), ("decoder", "decoder", 3)):
        for k in range(count):
            pairs += [(f"iterations.{i}.{ours}.{k}.linear", f"{theirs}.{i}.conv_block{k + 1}.0"),
                      (f"iterations.{i}.{ours}.{k}.norm", f"{theirs}.{i}.conv_block{k + 1}.1")]
    pairs.append((f"iterations.{i}.mask_logits", f"decoder.{i}.conv_block4.0"))
    for k in range(4):
        pairs += [(f"iterations.{i}.regressor.{k}.0", f"regression.{i}.fc_block{k + 1}.0"),
                  (f"iterations.{i}.regressor.{k}.1", f"regression.{i}.fc_block{k + 1}.1")]
    pairs.append((f"iterations.{i}.regressor.4", f"regression.{i}.final_fc.0"))
    return pairs


def copy_weights(ours: nn.Module, theirs: nn.Module, iterations: int) -> None:
    """Our weights into the port (k=1 convolutions take the linear weights; biases we lack are zero)."""
    copy_mapped(ours, theirs, [p for i in range(iterations) for p in _layer_names(i)], zero_missing_bias=True)


def pose_of(transform: Tensor) -> Tensor:
    """(B,7) quaternion (w ≥ 0) and translation of (B,4,4) transforms: the port's ``pose_gt``."""
    from src.geometry.quaternion import matrix_to_quat, quat_canonical

    return torch.cat((quat_canonical(matrix_to_quat(transform[:, :3, :3])), transform[:, :3, 3]), dim=1)


def _as_4x4(transform: Tensor) -> Tensor:
    bottom = transform.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(transform.shape[0], 1, 4)
    return transform if transform.shape[1] == 4 else torch.cat((transform, bottom), dim=1)


class OMNetPair(Pair):
    """Ours and the port: ``outputs(name, batch)`` → (loss, predicted (B,4,4) transform)."""

    def __init__(self, ours: nn.Module, theirs: nn.Module, compute_loss: Callable, loss_params: Any) -> None:
        super().__init__(ours, theirs)
        self._compute_loss, self._loss_params = compute_loss, loss_params

    def _authors_inputs(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        return {"points_src": batch["points_src"], "points_ref": batch["points_ref"],
                "transform_gt": batch["transform_gt"][:, :3, :], "pose_gt": pose_of(batch["transform_gt"])}

    def outputs(self, name: str, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """(loss, predicted (B,4,4) transform) of one network on a batch."""
        if name == "ours":
            net = self.nets["ours"]
            out = net(batch["points_src"], batch["points_ref"], batch["transform_gt"])
            return net.loss(out, batch["transform_gt"])["loss"], out["transforms"][-1]
        endpoints = self.nets["authors"](self._authors_inputs(batch))
        return self._compute_loss(endpoints, self._loss_params)["total"], _as_4x4(endpoints["transform_pair"][1])


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mask-ce", choices=("batch", "per_cloud"), default="batch")


def overrides(args: argparse.Namespace) -> list[str]:
    return [f"model.network.mask_ce_reduction={args.mask_ce}"]


def build(args: argparse.Namespace, cfg) -> OMNetPair:
    """Ours from ``cfg``; the port at ``args.width`` with our weights; both in train mode."""
    import hydra

    authors = load_authors(args.authors, args.width)
    ours = hydra.utils.instantiate(cfg.model.network)
    theirs = authors.OMNet(types.SimpleNamespace(titer=ours.num_iters, overlap_dist=ours.overlap_dist))
    copy_weights(ours, theirs, ours.num_iters)
    loss_params = types.SimpleNamespace(loss_type="omnet", loss_alpha1=ours.rot_loss_weight, loss_alpha2=ours.trans_loss_weight)
    return OMNetPair(ours.train(), theirs.train(), authors.compute_loss, loss_params)


def check_same_start(pair: OMNetPair, batch: dict[str, Tensor], out: Path) -> None:
    """One forward pass of copies of both (train mode) in float64: the same poses, or a ConfigError.

    In float32 the two differ by ~1e-4 after the first iteration, and the untrained network amplifies
    that ~100-fold per iteration (a random pose moves the next input; near-tied mask logits flip), so
    the same math is checked where rounding does not hide it. The port casts with ``.float()``: for
    this check only, that cast keeps float64 (and tensors are made in float64: the port's loss builds
    its class weights with torch.tensor)."""
    with float64_mode():
        twins = OMNetPair(copy.deepcopy(pair.nets["ours"]).double(), copy.deepcopy(pair.nets["authors"]).double(),
                          pair._compute_loss, pair._loss_params)
        double = as_double(batch)
        with torch.no_grad():
            (loss_ours, ours), (loss_theirs, theirs) = twins.outputs("ours", double), twins.outputs("authors", double)
    diff = {"max_abs_transform_diff_float64": (ours - theirs).abs().max().item(),
            "loss_ours": loss_ours.item(), "loss_authors": loss_theirs.item()}
    write_check(out, diff)
    if diff["max_abs_transform_diff_float64"] > 1e-6 or abs(diff["loss_ours"] - diff["loss_authors"]) > 1e-6:
        raise ConfigError(f"ours and the port differ at the start ({diff}): the weight mapping is wrong")


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.studies.lockstep.omnet ...``: ``python -m benchmarks.studies.lockstep.harness --method omnet ...``."""
    from benchmarks.studies.lockstep.harness import main as shared_main

    return shared_main(argv, method="omnet", prog="python -m benchmarks.studies.lockstep.omnet")


if __name__ == "__main__":
    sys.exit(main())
