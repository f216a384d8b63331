"""Does a method learn as well in bf16-mixed as in float32? Each run fits the same fixed real-airplane pairs
from fresh weights (seeded), every pair in every step, and records the training-mode Error(R) of the step's
own forward pass (before its update) at fixed steps.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.precision.fit_pairs --method omnet --seeds 0,1,2 \\
        --precisions fp32,bf16 --steps 300 --record 100,200,300 --out OUT
    ... --fp32-modules 'iterations.*.regressor'      # bf16 with these parts kept in float32 (model.fp32_modules)
    ... --kernels emulated                            # bf16 products computed in float32 (emulated.py): same numbers,
                                                      # float32 speed, where the CPU has no bf16 units

The pairs: ``+exp=real_airplane`` (TS, PRNet manner, clean), ``--points`` per cloud cropped to ``--keep``,
the first ``--pairs`` training pairs, drawn once. Runs are appended to ``OUT/fits.csv`` one row per recorded
step (method, seed, precision, fp32_modules, step, loss, Error(R), Error(t), CPU seconds so far), so a killed
study keeps what it finished; a run already in the file is skipped.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from src.utils.errors import ConfigError, exit_code_of

COLUMNS = ("method", "width", "seed", "precision", "kernels", "fp32_modules", "step", "loss", "rot_deg", "trans", "cpu_s")
PROTOCOL = ["+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "data.num_workers=0",
            "data.persistent_workers=false", "data.pin_memory=false"]


def protocol(points: int, keep: int) -> list[str]:
    """The overrides of the real-airplane pairs: :data:`PROTOCOL`, ``points`` per cloud cropped to ``keep``."""
    return [*PROTOCOL, f"data.pair.num_points={points}", f"data.pair.prnet_num_keep={keep}"]


def datamodule(method: str, overrides: Sequence[str]) -> Any:
    """The datamodule of ``overrides`` for ``method`` (normals cached for a network that reads them), set up to fit."""
    import hydra

    from src.compose import compose_conf

    normals = ["data.normals=cache"] if _uses_normals(method) else []
    data = hydra.utils.instantiate(compose_conf([*overrides, f"model={method}", *normals]).data)
    data.setup("fit")
    return data


def stacked(items: Sequence[dict[str, Any]]) -> dict[str, torch.Tensor]:
    """Pairs of a dataset as one batch (their tensors stacked)."""
    return {k: torch.stack([item[k] for item in items]) for k in items[0] if torch.is_tensor(items[0][k])}


def fixed_pairs(method: str, pairs: int, overrides: Sequence[str]) -> dict[str, torch.Tensor]:
    """The first ``pairs`` training pairs of ``overrides``' data, stacked (normals for a network that reads them)."""
    train = datamodule(method, overrides).datasets["train"]
    return stacked([train[i] for i in range(pairs)])


def _uses_normals(method: str) -> bool:
    from benchmarks.speed.train_step import build_network

    return bool(getattr(build_network(method, 0.25, []), "uses_normals", False))


def fit(method: str, width: float, seed: int, precision: str, fp32_modules: list[str], batch: dict[str, torch.Tensor],
        steps: int, record: set[int], lr: float, kernels: str = "native") -> list[dict]:
    """One run: rows of the recorded steps (training-mode errors of that step's forward pass). ``kernels``
    ``emulated``: bf16 products in float32 (:class:`~benchmarks.studies.precision.emulated.Bf16ProductsInFp32`)."""
    import contextlib

    from benchmarks.studies.precision.emulated import Bf16ProductsInFp32
    from benchmarks.speed.train_step import build_network
    from src.metrics import pair_errors
    from src.models.fp32_regions import keep_fp32

    torch.manual_seed(seed)
    network = build_network(method, width, []).train()
    keep_fp32(network, fp32_modules)
    optimizer = torch.optim.Adam(network.parameters(), lr=lr)
    normals = {k: batch[k] for k in ("normals_src", "normals_ref") if k in batch and getattr(network, "uses_normals", False)}
    emulate = precision == "bf16" and kernels == "emulated"
    rows, start = [], time.process_time()
    for step in range(1, steps + 1):
        optimizer.zero_grad(set_to_none=True)
        with Bf16ProductsInFp32() if emulate else contextlib.nullcontext():
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
                outputs = network(batch["points_src"], batch["points_ref"], batch["transform_gt"], **normals)
                loss = network.loss(outputs, batch["transform_gt"])["loss"]
            loss.backward()
        optimizer.step()
        if step in record:
            errors = pair_errors(outputs["transforms"][-1].detach().float(), batch["transform_gt"], "zyx")
            rows.append({"method": method, "width": width, "seed": seed, "precision": precision,
                         "kernels": kernels if precision == "bf16" else "", "fp32_modules": " ".join(fp32_modules), "step": step, "loss": loss.item(),
                         "rot_deg": errors["rot_deg"].mean().item(), "trans": errors["trans_norm"].mean().item(),
                         "cpu_s": round(time.process_time() - start, 1)})
            print(f"{method} seed {seed} {precision} [{' '.join(fp32_modules) or '-'}] step {step}: "
                  f"loss {loss.item():.4f} Error(R) {rows[-1]['rot_deg']:.2f} deg ({rows[-1]['cpu_s']} CPU s)", flush=True)
    return rows


def _done(path: Path) -> set[tuple]:
    if not path.is_file():
        return set()
    with path.open() as f:
        return {(r["method"], float(r["width"]), int(r["seed"]), r["precision"], r["kernels"], r["fp32_modules"])
                for r in csv.DictReader(f)}


def run(args: argparse.Namespace) -> Path:
    precisions = args.precisions.split(",")
    if set(precisions) - {"fp32", "bf16"}:
        raise ConfigError(f"--precisions: fp32 and/or bf16, got {args.precisions!r}")
    record = {int(s) for s in args.record.split(",")}
    if not record or max(record) > args.steps or min(record) < 1:
        raise ConfigError(f"--record: steps between 1 and --steps ({args.steps}), got {args.record!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "fits.csv"
    done = _done(path)
    batch = fixed_pairs(args.method, args.pairs, protocol(args.points, args.keep))
    for seed in (int(s) for s in args.seeds.split(",")):
        for precision in precisions:
            modules = args.fp32_modules if precision == "bf16" else []
            kernels = args.kernels if precision == "bf16" else ""
            if (args.method, args.width, seed, precision, kernels, " ".join(modules)) in done:
                continue
            rows = fit(args.method, args.width, seed, precision, modules, batch, args.steps, record, args.lr, args.kernels)
            new = not path.is_file()
            with path.open("a", newline="") as f:
                writer = csv.DictWriter(f, fieldnames=COLUMNS)
                if new:
                    writer.writeheader()
                writer.writerows(rows)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.precision.fit_pairs",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="omnet", help="conf/model/<name>.yaml (default omnet)")
    parser.add_argument("--width", type=float, default=0.25, help="model_scale (default 0.25)")
    parser.add_argument("--seeds", default="0,1,2", help="weight-initialisation seeds (default 0,1,2)")
    parser.add_argument("--precisions", default="fp32,bf16", help="fp32 and/or bf16 (CPU autocast) (default both)")
    parser.add_argument("--kernels", choices=("native", "emulated"), default="native",
                        help="bf16 products: PyTorch's kernels, or emulated in float32 (CPUs without bf16 units)")
    parser.add_argument("--fp32-modules", nargs="*", default=[], help="bf16 runs: submodules kept in float32")
    parser.add_argument("--pairs", type=int, default=16, help="fixed training pairs, all in every step (default 16)")
    parser.add_argument("--points", type=int, default=512, help="points per cloud before the crop (default 512)")
    parser.add_argument("--keep", type=int, default=384, help="points kept by the PRNet-manner crop (default 384)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    parser.add_argument("--steps", type=int, default=300, help="optimiser steps (default 300)")
    parser.add_argument("--record", default="100,200,300", help="steps whose errors are recorded (default 100,200,300)")
    parser.add_argument("--out", required=True, help="output folder (fits.csv is appended to)")
    args = parser.parse_args(argv)
    return exit_code_of(lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())
