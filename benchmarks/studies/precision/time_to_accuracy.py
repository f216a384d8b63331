"""Does bf16-mixed reach a validation target in less CPU time than float32, and where does it end? The rows of
``trainer.precision=auto``'s verdict table (``src/run/precision_verdicts.yaml``) for this machine's CPU kind.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.precision.time_to_accuracy --method omnet --seeds 0,1,2 \\
        --target 20 --batch 16 --steps 3000 --val-every 100 --val-pairs 200 --out OUT      # training
    OMP_NUM_THREADS=1 python -m benchmarks.studies.precision.time_to_accuracy --method omnet --seeds 0,1,2 \\
        --pairs 16 --points 512 --keep 384 --target 10 --steps 600 --val-every 25 --out OUT   # fitting probe

Per seed, float32 and bf16-mixed (CPU autocast around the forward pass and the loss, PyTorch's own kernels) train
the same network from the same initial weights on the same batches for ``--steps`` Adam steps; every
``--val-every`` steps the validation Error(R) is measured in float32 (eval mode, autocast off). Training: batches of
``--batch`` training pairs, validated on the first ``--val-pairs`` validation pairs; fitting probe (``--pairs N``):
the first N training pairs in every step, validated on themselves. The pairs: the real airplanes (``+exp=real_airplane``,
TS, PRNet manner, clean, ``--points`` cropped to ``--keep``), or the Hydra overrides given after the options.

Recorded per run (``OUT/runs.csv``, one row; a run already there is skipped): the CPU-seconds of the optimiser
steps (batches made and validation apart), the first validated step below ``--target`` and the CPU-seconds to it,
the final validation Error(R). Per method, over the seeds (``OUT/verdicts.yaml``, the table's format:
:class:`src.run.precision.Verdict`): the step and time-to-target speed-ups, each precision's final error and seed
spread, the command, the verdict (:func:`src.run.precision.bf16_verdict`).
"""

from __future__ import annotations

import argparse
import itertools
import shlex
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
import yaml

from benchmarks.studies.precision.fit_pairs import datamodule, fixed_pairs, protocol, stacked
from src.compose import compose_conf, compose_model_config
from src.run.precision import (
    MIN_SEEDS,
    Outcome,
    Spread,
    Verdict,
    bf16_verdict,
    cpu_kind,
    cpu_model,
    read_cpuinfo,
)
from src.utils.errors import ConfigError, exit_code_of

PRECISIONS = ("fp32", "bf16")
COLUMNS = ("setup", "method", "seed", "precision", "steps", "cpu_s", "s_per_step", "step_to_target", "cpu_s_to_target",
           "final_deg", "curve", "cpu_kind", "cpu")
VAL_BATCH = 32


@dataclass(frozen=True)
class Pairs:
    """What a run trains on (one batch per step) and validates on."""

    train: Callable[[], Iterator[dict[str, torch.Tensor]]]
    val: list[dict[str, torch.Tensor]]
    euler_seq: str


def fixed_probe(method: str, pairs: int, overrides: Sequence[str]) -> Pairs:
    """The first ``pairs`` training pairs, every step, validated on themselves."""
    batch = fixed_pairs(method, pairs, overrides)
    return Pairs(lambda: itertools.repeat(batch), [batch], _euler_seq(overrides))


def training_pairs(method: str, batch: int, val_pairs: int, overrides: Sequence[str]) -> Pairs:
    """Batches of ``batch`` training pairs in the datamodule's seeded order, epoch after epoch; the first
    ``val_pairs`` validation pairs."""
    data = datamodule(method, [*overrides, f"data.batch_size={batch}"])
    val = data.datasets["val"]
    items = [val[i] for i in range(min(val_pairs, len(val)))]

    def epochs() -> Iterator[dict[str, torch.Tensor]]:
        loader = data.train_dataloader()
        epoch = 0
        while True:
            loader.sampler.set_epoch(epoch)
            yield from loader
            epoch += 1

    return Pairs(epochs, [stacked(items[i:i + VAL_BATCH]) for i in range(0, len(items), VAL_BATCH)],
                 _euler_seq(overrides))


def _euler_seq(overrides: Sequence[str]) -> str:
    """The experiment's Euler convention of the metrics (``model.euler_seq``)."""
    return str(compose_conf(list(overrides)).model.euler_seq)


def _inputs(network: torch.nn.Module, batch: dict[str, torch.Tensor]) -> tuple[list[torch.Tensor], dict[str, Any]]:
    normals = {k: batch[k] for k in ("normals_src", "normals_ref") if k in batch and getattr(network, "uses_normals", False)}
    return [batch["points_src"], batch["points_ref"], batch["transform_gt"]], normals


def validate(network: torch.nn.Module, val: list[dict[str, torch.Tensor]], euler_seq: str) -> float:
    """Mean Error(R) in degrees over the validation pairs, in float32 (eval mode, autocast off)."""
    from src.metrics import pair_errors

    network.eval()
    errors = []
    with torch.no_grad(), torch.autocast("cpu", enabled=False):
        for batch in val:
            args, normals = _inputs(network, batch)
            transform = network(*args, **normals)["transforms"][-1].float()
            errors.append(pair_errors(transform, batch["transform_gt"], euler_seq)["rot_deg"])
    network.train()
    return float(torch.cat(errors).mean())


def _step(network: torch.nn.Module, optimizer: torch.optim.Optimizer, batch: dict[str, torch.Tensor],
          precision: str) -> float:
    """One Adam step (bf16: autocast around the forward pass and the loss, as Lightning's bf16-mixed); its CPU-seconds."""
    start = time.process_time()
    optimizer.zero_grad(set_to_none=True)
    args, normals = _inputs(network, batch)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
        outputs = network(*args, **normals)
        loss = network.loss(outputs, batch["transform_gt"])["loss"]
    loss.backward()
    optimizer.step()
    return time.process_time() - start


def warm_up(method: str, width: float, pairs: Pairs) -> None:
    """A step of a throwaway network in each precision: the first call's one-off costs (kernel set-up, allocations)
    would otherwise fall on the first timed run."""
    from benchmarks.speed.train_step import build_network

    for precision in PRECISIONS:
        network = build_network(method, width, []).train()
        _step(network, torch.optim.Adam(network.parameters()), next(pairs.train()), precision)


def train_to_target(method: str, width: float, seed: int, precision: str, pairs: Pairs, steps: int, val_every: int,
                    target: float, lr: float) -> dict[str, Any]:
    """One run: its CPU time, when validation first fell below ``target``, its final validation error and curve."""
    from benchmarks.speed.train_step import build_network

    torch.manual_seed(seed)
    network = build_network(method, width, []).train()
    optimizer = torch.optim.Adam(network.parameters(), lr=lr)
    batches = pairs.train()
    cpu_s, reached, curve = 0.0, None, []
    for step in range(1, steps + 1):
        cpu_s += _step(network, optimizer, next(batches), precision)
        if step % val_every and step != steps:
            continue
        error = validate(network, pairs.val, pairs.euler_seq)
        curve.append(f"{step}:{error:.3f}")
        if reached is None and error < target:
            reached = (step, round(cpu_s, 2))
        print(f"{method} seed {seed} {precision} step {step}: validation Error(R) {error:.2f} deg ({cpu_s:.1f} CPU s)",
              flush=True)
    return {"steps": steps, "cpu_s": round(cpu_s, 2), "s_per_step": cpu_s / steps,
            "step_to_target": None if reached is None else reached[0],
            "cpu_s_to_target": None if reached is None else reached[1], "final_deg": error, "curve": " ".join(curve)}


def verdict_of(runs: pd.DataFrame, target: str, target_deg: float, setup: str, command: str) -> Verdict:
    """The verdict row of one method's runs (both precisions, the seeds both ran) on the CPU they ran on."""
    seeds = sorted(set(runs.loc[runs["precision"] == "fp32", "seed"]) & set(runs.loc[runs["precision"] == "bf16", "seed"]))
    by = {p: runs[(runs["precision"] == p) & runs["seed"].isin(seeds)] for p in PRECISIONS}

    def outcome(frame: pd.DataFrame) -> Outcome:
        reached = int(frame["step_to_target"].notna().sum())
        every = reached == len(frame)
        final = frame["final_deg"].astype(float)
        return Outcome(reached, round(float(frame["step_to_target"].mean()), 1) if every else None,
                       round(float(frame["cpu_s_to_target"].mean()), 2) if every else None,
                       Spread(*(round(float(v), 3) for v in (final.mean(), final.min(), final.max()))))

    fp32, bf16 = outcome(by["fp32"]), outcome(by["bf16"])
    speedup = (None if fp32.cpu_s_to_target is None or bf16.cpu_s_to_target is None
               else round(fp32.cpu_s_to_target / bf16.cpu_s_to_target, 3))
    step_speedup = round(float(by["fp32"]["s_per_step"].mean() / by["bf16"]["s_per_step"].mean()), 3)
    first = runs.iloc[0]
    return Verdict(target, str(first["cpu_kind"]), str(first["cpu"]), setup, target_deg, tuple(int(s) for s in seeds),
                   step_speedup, speedup, fp32, bf16, command, bf16_verdict(speedup, fp32.final_deg, bf16.final_deg))


def write_verdict(path: Path, verdict: Verdict) -> None:
    """``verdict`` into the table at ``path``, replacing the row of the same method and kind."""
    rows = (yaml.safe_load(path.read_text()) or []) if path.is_file() else []
    rows = [r for r in rows if (r["method"], r["cpu_kind"]) != (verdict.method, verdict.cpu_kind)]
    path.write_text(yaml.safe_dump([*rows, verdict.record()], sort_keys=False, allow_unicode=True,
                                   default_flow_style=None, width=120))


def describe(args: argparse.Namespace, overrides: Sequence[str]) -> str:
    """The set-up of a verdict row: data, steps, network, optimiser, validation."""
    if args.pairs:
        data = f"fitting the first {args.pairs} training pairs in every step, validated on them"
    else:
        data = f"batches of {args.batch} training pairs, validated on the first {args.val_pairs} validation pairs"
    return (f"{data}; {' '.join(overrides)}; width {args.width:g}, Adam lr {args.lr:g}, {args.steps} steps, "
            f"validation Error(R) in float32 every {args.val_every} steps")


def _train(args: argparse.Namespace, overrides: Sequence[str], todo: Sequence[tuple[int, str]], done: pd.DataFrame,
           runs_csv: Path) -> pd.DataFrame:
    """The runs ``todo`` (seed, precision), each appended to ``done`` and written to ``runs_csv`` when it ends."""
    cpuinfo = read_cpuinfo()
    pairs = (fixed_probe(args.method, args.pairs, overrides) if args.pairs
             else training_pairs(args.method, args.batch, args.val_pairs, overrides))
    warm_up(args.method, args.width, pairs)
    for seed, precision in todo:
        result = train_to_target(args.method, args.width, seed, precision, pairs, args.steps, args.val_every,
                                 args.target, args.lr)
        row = {"setup": describe(args, overrides), "method": args.method, "seed": seed, "precision": precision,
               **result, "cpu_kind": cpu_kind(cpuinfo), "cpu": cpu_model(cpuinfo)}
        done = pd.concat([done, pd.DataFrame([row], columns=COLUMNS)], ignore_index=True)
        done.to_csv(runs_csv, index=False)
    return done


def run(args: argparse.Namespace, argv: Sequence[str]) -> Path:
    seeds = [int(s) for s in args.seeds.split(",")]
    if len(set(seeds)) < MIN_SEEDS:
        raise ConfigError(f"--seeds: a verdict needs at least {MIN_SEEDS} seeds, got {args.seeds!r}")
    if not 1 <= args.val_every <= args.steps:
        raise ConfigError(f"--val-every: between 1 and --steps ({args.steps}), got {args.val_every}")
    overrides = args.overrides or protocol(args.points, args.keep)
    setup = describe(args, overrides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs_csv = out / "runs.csv"
    done = pd.read_csv(runs_csv) if runs_csv.is_file() else pd.DataFrame(columns=COLUMNS)
    kind = cpu_kind(read_cpuinfo())

    def mine(frame: pd.DataFrame) -> pd.DataFrame:  # this set-up's runs of the method on this kind of CPU
        return frame[(frame["setup"] == setup) & (frame["method"] == args.method) & (frame["cpu_kind"] == kind)]

    finished = {(r.seed, r.precision) for r in mine(done).itertuples()}
    todo = [(seed, precision) for seed in seeds for precision in PRECISIONS if (seed, precision) not in finished]
    if todo:
        done = _train(args, overrides, todo, done, runs_csv)
    target = str(compose_model_config(args.method, args.width).network._target_)
    command = " ".join(["python -m benchmarks.studies.precision.time_to_accuracy", *map(shlex.quote, argv)])
    runs = mine(done)
    verdict = verdict_of(runs[runs["seed"].isin(seeds)], target, args.target, setup, command)
    write_verdict(out / "verdicts.yaml", verdict)
    print(f"{args.method} on {verdict.cpu_kind}: {verdict.verdict} ({verdict.describe()})")
    return out / "verdicts.yaml"


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.precision.time_to_accuracy",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", default="omnet", help="conf/model/<name>.yaml (default omnet)")
    parser.add_argument("--width", type=float, default=0.25, help="model_scale (default 0.25)")
    parser.add_argument("--seeds", default="0,1,2", help=f"weight-initialisation seeds, at least {MIN_SEEDS} (default 0,1,2)")
    parser.add_argument("--target", type=float, required=True, help="validation Error(R) to reach, degrees")
    parser.add_argument("--steps", type=int, default=3000, help="optimiser steps of every run (default 3000)")
    parser.add_argument("--val-every", type=int, default=100, help="validate every N steps (default 100)")
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    parser.add_argument("--batch", type=int, default=16, help="training: pairs per batch (default 16)")
    parser.add_argument("--val-pairs", type=int, default=200, help="training: validation pairs (default 200)")
    parser.add_argument("--pairs", type=int, default=None, help="fitting probe: N fixed training pairs, every step")
    parser.add_argument("--points", type=int, default=512, help="real airplanes: points per cloud (default 512)")
    parser.add_argument("--keep", type=int, default=384, help="real airplanes: points kept by the crop (default 384)")
    parser.add_argument("--out", required=True, help="output folder (runs.csv, verdicts.yaml)")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the pairs, instead of the real airplanes")
    args = parser.parse_args(argv)
    return exit_code_of(lambda: run(args, argv))


if __name__ == "__main__":
    sys.exit(main())
