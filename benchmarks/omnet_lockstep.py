"""OMNet's authors' code and ours trained side by side on the same pairs (issue 21 §5's diagnosis).

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
    OMP_NUM_THREADS=1 python -m benchmarks.omnet_lockstep --authors <checkout of hxwork/OMNet_Pytorch> \\
        --out RUN [--steps 1086] [--schedule-steps 1086] [--width 0.25] [--lr 1e-4] [--val-every 109]

Resumable: ``state.pt`` in ``--out`` every ``--val-every`` steps; ``curves.csv`` (step, net, training
loss, validation Error(R)/Error(t)). ``--mask-ce batch`` (the default) gives ours the port's mask
cross-entropy reduction (``nn.CrossEntropyLoss(weight=...)`` over all points, ``loss/loss.py``), so
that the two losses are the same function.
"""

from __future__ import annotations

import argparse
import csv
import importlib
import importlib.util
import json
import sys
import time
import types
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from src.errors import ConfigError, exit_code_of
from src.models.base import MIN_CHANNELS, scaled

#: The port's channel counts that are not widths: the points' xyz in, the mask's two classes and the pose's 7 out.
FIXED_CHANNELS = (2, 3, 7)
PROTOCOL = ["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "model=omnet",
            "recipe=omnet_official", "data.num_workers=0", "data.persistent_workers=false", "data.pin_memory=false",
            "data.eval_batch_size=50"]


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
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # the port's .cuda() calls, on the CPU
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
    source, target = ours.state_dict(), theirs.state_dict()
    mapped = {}
    for name_ours, name_theirs in (p for i in range(iterations) for p in _layer_names(i)):
        for key in [k[len(name_theirs) + 1:] for k in target if k.startswith(name_theirs + ".")]:
            want = target[f"{name_theirs}.{key}"]
            have = source.get(f"{name_ours}.{key}")
            value = torch.zeros_like(want) if have is None and key == "bias" else have
            if value is None or value.numel() != want.numel():
                raise ConfigError(f"{name_theirs}.{key} {tuple(want.shape)} has no counterpart in ours ({name_ours}.{key})")
            mapped[f"{name_theirs}.{key}"] = value.reshape(want.shape).clone()
    missing = set(target) - set(mapped)
    if missing:
        raise ConfigError(f"port parameters not mapped: {sorted(missing)[:5]}")
    theirs.load_state_dict(mapped)


def pose_of(transform: Tensor) -> Tensor:
    """(B,7) quaternion (w ≥ 0) and translation of (B,4,4) transforms: the port's ``pose_gt``."""
    from src.geometry.quaternion import matrix_to_quat, quat_canonical

    return torch.cat((quat_canonical(matrix_to_quat(transform[:, :3, :3])), transform[:, :3, 3]), dim=1)


def _as_4x4(transform: Tensor) -> Tensor:
    bottom = transform.new_tensor([0.0, 0.0, 0.0, 1.0]).expand(transform.shape[0], 1, 4)
    return transform if transform.shape[1] == 4 else torch.cat((transform, bottom), dim=1)


class Pair:
    """Ours and theirs behind one interface: ``transform(batch)`` and ``loss(batch)``."""

    def __init__(self, ours: nn.Module, theirs: nn.Module, compute_loss: Callable, loss_params: Any) -> None:
        self.nets = {"ours": ours, "authors": theirs}
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


def validate(pair: Pair, name: str, loader) -> dict[str, float]:
    """Mean Error(R) (degrees) and Error(t) of one network over the validation pairs (eval mode)."""
    from src.metrics import pair_errors

    net = pair.nets[name]
    net.eval()
    rot, trans = [], []
    with torch.no_grad():
        for batch in loader:
            _, transform = pair.outputs(name, batch)
            errors = pair_errors(transform, batch["transform_gt"], "zyx")
            rot.append(errors["rot_deg"])
            trans.append(errors["trans_norm"])
    net.train()
    return {"val_rot_deg": torch.cat(rot).mean().item(), "val_trans": torch.cat(trans).mean().item()}


def _batches(datamodule, epoch: int, done: int) -> Iterator[dict[str, Tensor]]:
    """Training batches from (epoch, batches done) on, epoch after epoch, as ``src.train`` draws them."""
    loader = datamodule.train_dataloader()
    sampler = datamodule._train_sampler
    sampler.resume_at(epoch, done * datamodule.batch_size)
    while True:
        yield from loader
        epoch += 1
        sampler.set_epoch(epoch)


def lockstep(args: argparse.Namespace) -> Path:
    """Train both networks ``args.steps`` steps; write ``curves.csv`` and ``summary.json`` in ``args.out``."""
    import hydra

    from src.compose import compose_conf

    torch.set_num_threads(1)
    cfg = compose_conf([*PROTOCOL, f"model_scale={args.width}", f"data.batch_size={args.batch}",
                        f"model.network.mask_ce_reduction={args.mask_ce}", f"seed={args.seed}"])
    authors = load_authors(args.authors, args.width)
    torch.manual_seed(args.seed)
    ours = hydra.utils.instantiate(cfg.model.network)
    theirs = authors.OMNet(types.SimpleNamespace(titer=ours.num_iters, overlap_dist=ours.overlap_dist))
    copy_weights(ours, theirs, ours.num_iters)
    loss_params = types.SimpleNamespace(loss_type="omnet", loss_alpha1=ours.rot_loss_weight, loss_alpha2=ours.trans_loss_weight)
    pair = Pair(ours.train(), theirs.train(), authors.compute_loss, loss_params)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    milestones = [round(f * (args.schedule_steps or args.steps)) for f in args.milestones]
    optimizers = {n: torch.optim.Adam(net.parameters(), lr=args.lr) for n, net in pair.nets.items()}
    schedulers = {n: torch.optim.lr_scheduler.MultiStepLR(o, milestones, 0.1) for n, o in optimizers.items()}
    args.out.mkdir(parents=True, exist_ok=True)
    state_file, curves = args.out / "state.pt", args.out / "curves.csv"
    cpu, step_count = {"ours": 0.0, "authors": 0.0}, 0
    if state_file.is_file():
        state = torch.load(state_file, weights_only=False)
        for n in pair.nets:
            pair.nets[n].load_state_dict(state["nets"][n])
            optimizers[n].load_state_dict(state["optimizers"][n])
            schedulers[n].load_state_dict(state["schedulers"][n])
        step_count, cpu = state["step"], state["cpu_s"]
        torch.set_rng_state(state["rng"])
    else:
        check_same_start(pair, next(_batches(datamodule, 0, 0)), args.out)
        curves.write_text("step,net,cpu_s,train_loss,val_rot_deg,val_trans\n")
    batches_per_epoch = len(datamodule.train_dataloader())
    batches = _batches(datamodule, step_count // batches_per_epoch, step_count % batches_per_epoch)
    running = {n: [] for n in pair.nets}
    val_loader = datamodule.val_dataloader()
    (args.out / "command.txt").write_text(" ".join(sys.argv) + "\n")
    while step_count < args.steps:
        batch = next(batches)
        for n, net in pair.nets.items():
            start = time.process_time()
            loss, _ = pair.outputs(n, batch)
            optimizers[n].zero_grad(set_to_none=True)
            loss.backward()
            optimizers[n].step()
            schedulers[n].step()
            cpu[n] += time.process_time() - start
            running[n].append(loss.item())
        step_count += 1
        if step_count % args.val_every == 0 or step_count == args.steps:
            with curves.open("a", newline="") as f:
                for n in pair.nets:
                    val = validate(pair, n, val_loader)
                    row = [step_count, n, f"{cpu[n]:.1f}", f"{sum(running[n]) / len(running[n]):.5f}",
                           f"{val['val_rot_deg']:.3f}", f"{val['val_trans']:.4f}"]
                    csv.writer(f).writerow(row)
                    print(f"step {step_count}/{args.steps}: " + ",".join(map(str, row)), flush=True)
                    running[n] = []
            torch.save({"nets": {n: m.state_dict() for n, m in pair.nets.items()},
                        "optimizers": {n: o.state_dict() for n, o in optimizers.items()},
                        "schedulers": {n: s.state_dict() for n, s in schedulers.items()},
                        "step": step_count, "cpu_s": cpu, "rng": torch.get_rng_state()}, state_file.with_suffix(".tmp"))
            state_file.with_suffix(".tmp").replace(state_file)
    return curves


def check_same_start(pair: Pair, batch: dict[str, Tensor], out: Path) -> None:
    """One forward pass of copies of both (train mode) in float64: the same poses, or a ConfigError.

    In float32 the two differ by ~1e-4 after the first iteration, and the untrained network amplifies
    that ~100-fold per iteration (a random pose moves the next input; near-tied mask logits flip), so
    the same math is checked where rounding does not hide it. The port casts with ``.float()``: for
    this check only, that cast keeps float64 (and tensors are made in float64)."""
    import copy

    float_cast, default_dtype = torch.Tensor.float, torch.get_default_dtype()
    torch.Tensor.float = lambda self, *args, **kwargs: self.double()
    torch.set_default_dtype(torch.float64)  # the port's loss builds its class weights with torch.tensor
    try:
        twins = Pair(copy.deepcopy(pair.nets["ours"]).double(), copy.deepcopy(pair.nets["authors"]).double(),
                     pair._compute_loss, pair._loss_params)
        double = {k: v.double() if v.is_floating_point() else v for k, v in batch.items()}
        with torch.no_grad():
            (loss_ours, ours), (loss_theirs, theirs) = twins.outputs("ours", double), twins.outputs("authors", double)
    finally:
        torch.Tensor.float = float_cast
        torch.set_default_dtype(default_dtype)
    diff = {"max_abs_transform_diff_float64": (ours - theirs).abs().max().item(),
            "loss_ours": loss_ours.item(), "loss_authors": loss_theirs.item()}
    (out / "start_check.json").write_text(json.dumps(diff, indent=2))
    print(f"same start: {diff}", flush=True)
    if diff["max_abs_transform_diff_float64"] > 1e-6 or abs(diff["loss_ours"] - diff["loss_authors"]) > 1e-6:
        raise ConfigError(f"ours and the port differ at the start ({diff}): the weight mapping is wrong")


def plot(curves: Path, out: Path) -> Path:
    """Validation Error(R) and Error(t) against steps, ours and the authors' code, from ``curves.csv``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    frame = pd.read_csv(curves)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for net, group in frame.groupby("net", sort=False):
        label = {"ours": "ours (src.models.omnet)", "authors": "authors' code (hxwork/OMNet_Pytorch)"}.get(net, net)
        for ax, column in zip(axes, ("val_rot_deg", "val_trans")):
            ax.plot(group["step"], group[column], marker="o", markersize=3, label=label)
    for ax, name in zip(axes, ("validation Error(R) [deg]", "validation Error(t)")):
        ax.set(xlabel="training step (same batches, same start)", ylabel=name)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("OMNet, ours and the authors' code in lockstep (real airplanes, TS, PRNet manner, clean)", fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.omnet_lockstep", description=__doc__.split("\n\n")[0])
    parser.add_argument("--authors", type=Path, required=True, help="a checkout of hxwork/OMNet_Pytorch")
    parser.add_argument("--out", type=Path, required=True, help="run folder (outside the repository)")
    parser.add_argument("--steps", type=int, default=1086, help="steps (default: the 1-CPU-hour budget run's)")
    parser.add_argument("--width", type=float, default=0.25)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--milestones", type=float, nargs="*", default=[0.7, 0.9], help="×0.1 at these fractions")
    parser.add_argument("--schedule-steps", type=int, default=None,
                        help="the run whose schedule the milestones follow (default --steps): train its first --steps")
    parser.add_argument("--val-every", type=int, default=109)
    parser.add_argument("--mask-ce", choices=("batch", "per_cloud"), default="batch")
    parser.add_argument("--seed", type=int, default=1234, help="default: conf/config.yaml's, as src.train")
    parser.add_argument("--plot", type=Path, default=None, help="only draw --out's curves.csv into this PNG")
    args = parser.parse_args(argv)
    if args.plot is not None:
        return exit_code_of(lambda: print(f"wrote {plot(args.out / 'curves.csv', args.plot)}"))
    return exit_code_of(lambda: print(f"wrote {lockstep(args)}"))


if __name__ == "__main__":
    sys.exit(main())
