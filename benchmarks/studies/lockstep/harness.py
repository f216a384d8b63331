"""The authors' code and ours trained side by side on the same pairs (a harness to tell our bugs from the method's).

Both networks start from the same weights (ours copied into theirs), see the same batches in the
same order, each with its own Adam and the same step schedule; before training, a float64 check on
the first batch shows what of the two forward passes is the same function. Every ``--val-every``
steps both are evaluated (eval mode) on the experiment's validation pairs. The per-method part (the
authors' code loaded from a checkout outside the repository, the weight mapping, the two forward
calls, the start check) is an adapter module: ``benchmarks.studies.lockstep.omnet``, ``benchmarks.studies.lockstep.idam``,
``benchmarks.studies.lockstep.prnet``.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.lockstep.harness --method omnet|idam|prnet --authors CHECKOUT --out RUN [--steps N]

Resumable (``state.pt`` every ``--val-every`` steps); ``curves.csv``, ``start_check.json``; ``--plot PNG``.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import importlib
import importlib.util
import json
import sys
import time
import types
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from src.utils.errors import ConfigError, exit_code_of

METHODS = ("omnet", "idam", "prnet")
#: What the protocol of every adapter adds: single-process data, validation in batches of 50.
DATA = ["data.num_workers=0", "data.persistent_workers=false", "data.pin_memory=false", "data.eval_batch_size=50"]


def adapter(method: str) -> types.ModuleType:
    """The adapter module of ``method`` (``benchmarks.studies.lockstep.<method>``)."""
    if method not in METHODS:
        raise ConfigError(f"--method {method!r}: one of {METHODS}")
    return importlib.import_module(f"benchmarks.studies.lockstep.{method}")


class Pair:
    """Ours and theirs behind one interface: ``outputs(name, batch)`` → (loss, predicted (B,4,4) transform)."""

    def __init__(self, ours: nn.Module, theirs: nn.Module) -> None:
        self.nets = {"ours": ours, "authors": theirs}

    def outputs(self, name: str, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        raise NotImplementedError


def copy_mapped(ours: nn.Module, theirs: nn.Module, pairs: Sequence[tuple[str, str]], *,
                zero_missing_bias: bool, constants: Sequence[str] = ()) -> dict[str, str]:
    """Our weights into theirs, module pair by module pair (Linear (out, in) → Conv (out, in, 1[, 1])).

    ``zero_missing_bias``: a bias of theirs that ours lacks is set to zero (else refused); a key of
    ours without counterpart in theirs is refused. ``constants``: keys of theirs that stay as built.
    Returns their key → our key of every copied tensor."""
    source, target = ours.state_dict(), theirs.state_dict()
    mapped, used = {}, {}
    for name_ours, name_theirs in pairs:
        for key in [k[len(name_theirs) + 1:] for k in target if k.startswith(name_theirs + ".")]:
            want = target[f"{name_theirs}.{key}"]
            have = source.get(f"{name_ours}.{key}")
            if have is not None:
                used[f"{name_ours}.{key}"] = f"{name_theirs}.{key}"
            elif key == "bias" and zero_missing_bias:
                have = torch.zeros_like(want)
            if have is None or have.numel() != want.numel():
                raise ConfigError(f"{name_theirs}.{key} {tuple(want.shape)} has no counterpart in ours ({name_ours}.{key})")
            mapped[f"{name_theirs}.{key}"] = have.reshape(want.shape).clone()
        extra = [k for k in source if k.startswith(name_ours + ".") and k not in used]
        if extra and not zero_missing_bias:
            raise ConfigError(f"ours has {extra} where {name_theirs} has none")
    mapped.update({k: target[k] for k in constants})
    missing = set(target) - set(mapped)
    if missing:
        raise ConfigError(f"the authors' parameters not mapped: {sorted(missing)[:5]}")
    theirs.load_state_dict(mapped)
    return {theirs_key: ours_key for ours_key, theirs_key in used.items()}


def cuda_on_cpu() -> None:
    """``Tensor.cuda`` returning the tensor itself: the authors' ``.cuda()`` calls, on the CPU (this process only)."""
    torch.Tensor.cuda = lambda self, *args, **kwargs: self


def _load_file(name: str, path: Path) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    with warnings.catch_warnings():  # e.g. PRNet's model.py:583 ``is not ''``
        warnings.simplefilter("ignore", SyntaxWarning)
        spec.loader.exec_module(module)
    return module


def _unavailable(*args: Any, **kwargs: Any) -> Any:
    raise NotImplementedError("a stub for an import of the authors' code that the lockstep does not use")


def _stub_getattr(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    return _unavailable


@contextlib.contextmanager
def _stubbed(names: Sequence[str]) -> Iterator[None]:
    """Empty modules (every attribute a function that refuses to run) for those of ``names`` that do not import,
    for as long as the authors' model.py imports."""
    added = []
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError:
            sys.modules[name] = types.ModuleType(name)
            sys.modules[name].__getattr__ = _stub_getattr
            added.append(name)
    try:
        yield
    finally:
        for name in added:
            sys.modules.pop(name, None)


def load_authors_model(checkout: Path, repo: str, tag: str, unused_imports: Sequence[str] = ()) -> types.ModuleType:
    """The authors' ``model.py`` from ``checkout``, on the CPU, with their ``util.py`` as the ``util`` it imports
    (both IDAM's and PRNet's ``from util import ...``) and stubs for ``unused_imports`` that do not import here.
    ``repo`` names the checkout needed in the error; ``tag`` keeps their modules apart in ``sys.modules``."""
    if not (checkout / "model.py").is_file() or not (checkout / "util.py").is_file():
        raise ConfigError(f"--authors {checkout}: no model.py/util.py (a checkout of {repo} is needed)")
    cuda_on_cpu()
    saved = sys.modules.get("util")
    try:
        sys.modules["util"] = _load_file(f"{tag}_authors_util", checkout / "util.py")
        with _stubbed(unused_imports):
            return _load_file(f"{tag}_authors_model", checkout / "model.py")
    except ImportError as exc:
        raise ConfigError(f"the authors' code needs {exc.name}") from exc
    finally:
        if saved is None:
            sys.modules.pop("util", None)
        else:
            sys.modules["util"] = saved


def se3(rot: Tensor, trans: Tensor) -> Tensor:
    """(B, 4, 4) from the authors' R (B, 3, 3) and t (B, 3) or (B, 3, 1)."""
    from src.geometry import se3_from_rt

    return se3_from_rt(rot, trans.reshape(-1, 3))


@contextlib.contextmanager
def float64_mode() -> Iterator[None]:
    """Tensors made in float64 and ``Tensor.float()`` keeping float64 (the authors' casts), for a check."""
    float_cast, default_dtype = torch.Tensor.float, torch.get_default_dtype()
    torch.Tensor.float = lambda self, *args, **kwargs: self.double()
    torch.set_default_dtype(torch.float64)
    try:
        yield
    finally:
        torch.Tensor.float = float_cast
        torch.set_default_dtype(default_dtype)


def as_double(batch: dict[str, Tensor]) -> dict[str, Tensor]:
    return {k: v.double() if torch.is_tensor(v) and v.is_floating_point() else v for k, v in batch.items()}


def validate(pair: Pair, name: str, loader, max_pairs: int | None = None) -> dict[str, float]:
    """Mean Error(R) (degrees) and Error(t) of one network over the validation pairs (eval mode)."""
    from src.metrics import pair_errors

    net = pair.nets[name]
    net.eval()
    rot, trans, seen = [], [], 0
    with torch.no_grad():
        for batch in loader:
            if max_pairs is not None:
                keep = max_pairs - seen
                if keep <= 0:
                    break
                batch = {k: v[:keep] if torch.is_tensor(v) else v for k, v in batch.items()}
            _, transform = pair.outputs(name, batch)
            errors = pair_errors(transform, batch["transform_gt"], "zyx")
            rot.append(errors["rot_deg"])
            trans.append(errors["trans_norm"])
            seen += len(errors["rot_deg"])
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


def lockstep(args: argparse.Namespace, method: types.ModuleType | None = None) -> Path:
    """Train both networks ``args.steps`` steps; write ``curves.csv`` (and ``state.pt``) in ``args.out``."""
    import hydra

    from src.compose import compose_conf

    method = method or adapter(args.method)
    torch.set_num_threads(1)
    cfg = compose_conf([*method.PROTOCOL, *DATA, f"model_scale={args.width}", f"data.batch_size={args.batch}",
                        f"seed={args.seed}", *method.overrides(args)])
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    pair = method.build(args, cfg)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    return train(pair, datamodule, args, method.check_same_start)


def train(pair: Pair, datamodule, args: argparse.Namespace, check_same_start) -> Path:
    """The loop: same batches to both, resumable from ``args.out / "state.pt"``."""
    milestones = [round(f * (args.schedule_steps or args.steps)) for f in args.milestones]
    optimizers = {n: torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
                  for n, net in pair.nets.items()}
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
        np.random.set_state(state["np_rng"])
    else:
        numpy_state = np.random.get_state()
        with torch.random.fork_rng():  # the check's draws leave the training's random streams as they were
            check_same_start(pair, next(_batches(datamodule, 0, 0)), args.out)
        np.random.set_state(numpy_state)
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
        if step_count % args.progress_every == 0:  # a sign of life between validations
            print(f"step {step_count}/{args.steps}: train loss " + ", ".join(
                f"{n} {running[n][-1]:.4f} ({cpu[n]:.0f} CPU-s)" for n in pair.nets), flush=True)
        if step_count % args.val_every == 0 or step_count == args.steps:
            with curves.open("a", newline="") as f:
                for n in pair.nets:
                    val = validate(pair, n, val_loader, getattr(args, "val_pairs", None))
                    row = [step_count, n, f"{cpu[n]:.1f}", f"{sum(running[n]) / len(running[n]):.5f}",
                           f"{val['val_rot_deg']:.3f}", f"{val['val_trans']:.4f}"]
                    csv.writer(f).writerow(row)
                    print(f"step {step_count}/{args.steps}: " + ",".join(map(str, row)), flush=True)
                    running[n] = []
            torch.save({"nets": {n: m.state_dict() for n, m in pair.nets.items()},
                        "optimizers": {n: o.state_dict() for n, o in optimizers.items()},
                        "schedulers": {n: s.state_dict() for n, s in schedulers.items()},
                        "step": step_count, "cpu_s": cpu, "rng": torch.get_rng_state(),
                        "np_rng": np.random.get_state()}, state_file.with_suffix(".tmp"))
            state_file.with_suffix(".tmp").replace(state_file)
    return curves


def write_check(out: Path, result: dict) -> None:
    """``start_check.json`` in ``out``, and the line on stdout."""
    (out / "start_check.json").write_text(json.dumps(result, indent=2))
    print(f"same start: {result}", flush=True)


#: The start check of an adapter that compares per-layer outputs and gradients (IDAM, PRNet), in float64: the largest
#: |ours − theirs| of the first iteration in eval mode, and the largest relative difference of the training loss and
#: gradients.
START_EVAL_TOLERANCE = 1e-8
START_TRAIN_TOLERANCE = 1e-6


def check_start(out: Path, result: dict, eval_diff: float, train_diff: float) -> None:
    """Write the start check (:func:`write_check`), then ConfigError if either difference exceeds its tolerance."""
    write_check(out, result)
    if eval_diff > START_EVAL_TOLERANCE or train_diff > START_TRAIN_TOLERANCE:
        raise ConfigError(f"ours and the authors' code differ at the start ({result}): the weight mapping is wrong")


def plot(curves: Path, out: Path, labels: dict[str, str], title: str) -> Path:
    """Validation Error(R) and Error(t) against steps, ours and the authors' code, from ``curves.csv``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pandas as pd

    frame = pd.read_csv(curves)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    for net, group in frame.groupby("net", sort=False):
        for ax, column in zip(axes, ("val_rot_deg", "val_trans")):
            ax.plot(group["step"], group[column], marker="o", markersize=3, label=labels.get(net, net))
    for ax, name in zip(axes, ("validation Error(R) [deg]", "validation Error(t)")):
        ax.set(xlabel="training step (same batches, same start)", ylabel=name)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def parser_for(method: types.ModuleType, prog: str, with_method: bool) -> argparse.ArgumentParser:
    """The CLI, its defaults the adapter's ``DEFAULTS``; the adapter adds its own options."""
    d = method.DEFAULTS
    parser = argparse.ArgumentParser(prog=prog, description=(method.__doc__ or __doc__).split("\n\n")[0])
    if with_method:
        parser.add_argument("--method", choices=METHODS, required=True)
    parser.add_argument("--authors", type=Path, required=True, help=f"a checkout of {method.AUTHORS_REPO}")
    parser.add_argument("--out", type=Path, required=True, help="run folder (outside the repository)")
    parser.add_argument("--steps", type=int, default=d["steps"], help="steps (default: the 1-CPU-hour budget run's)")
    parser.add_argument("--width", type=float, default=d["width"])
    parser.add_argument("--batch", type=int, default=d["batch"])
    parser.add_argument("--lr", type=float, default=d["lr"])
    parser.add_argument("--weight-decay", type=float, default=d["weight_decay"], help="Adam's, both nets")
    parser.add_argument("--milestones", type=float, nargs="*", default=d["milestones"], help="×0.1 at these fractions")
    parser.add_argument("--schedule-steps", type=int, default=None,
                        help="the run whose schedule the milestones follow (default --steps): train its first --steps")
    parser.add_argument("--val-every", type=int, default=d["val_every"])
    parser.add_argument("--progress-every", type=int, default=10, help="print the losses every N steps")
    parser.add_argument("--val-pairs", type=int, default=None, help="validate on the first N pairs only (default all)")
    parser.add_argument("--seed", type=int, default=1234, help="default: conf/config.yaml's, as src.train")
    parser.add_argument("--plot", type=Path, default=None, help="only draw --out's curves.csv into this PNG")
    method.add_arguments(parser)
    return parser


def main(argv: list[str] | None = None, method: str | None = None, prog: str = "python -m benchmarks.studies.lockstep.harness") -> int:
    """``method`` None: ``--method`` is read from ``argv``; else (an adapter's own entry point) fixed."""
    argv = sys.argv[1:] if argv is None else argv
    name = method
    if name is None:
        pre = argparse.ArgumentParser(add_help=False)
        pre.add_argument("--method", choices=METHODS)
        name = pre.parse_known_args(argv)[0].method
        if name is None:  # --help or a missing --method: the generic parser says what is wanted
            generic = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
            generic.add_argument("--method", choices=METHODS, required=True)
            generic.parse_args(argv)
    module = adapter(name)
    args = parser_for(module, prog, with_method=method is None).parse_args(argv)
    args.method = name
    if args.plot is not None:
        return exit_code_of(lambda: print(f"wrote {plot(args.out / 'curves.csv', args.plot, module.LABELS, module.TITLE)}"))
    return exit_code_of(lambda: print(f"wrote {lockstep(args, module)}"))


if __name__ == "__main__":
    sys.exit(main())
