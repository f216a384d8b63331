"""Training-step time of a registration network (forward, loss, backward, Adam step), per precision
and compile mode: the issue's profile of OMNet's step (batch 64, 717 and 1,024 points, 4 iterations).

    python -m benchmarks.speed.train_step                                        # OMNet, batch 64, 717/1024 pts, fp32/bf16 x eager/compiled
    python -m benchmarks.speed.train_step --device cpu --batch 8 --precisions fp32 --compile none --steps 3
    python -m benchmarks.speed.train_step --model-overrides model.network.share_weights=true

Each configuration builds the network from ``conf/model/<model>.yaml`` (fresh weights: the step's cost
does not depend on them), one fixed batch of pairs already on the device (so data loading is not
timed), and Adam; ``--warmup`` steps (which include compilation) are not timed, then the median of
``--steps`` steps, each synchronised with the device, is reported in ms, with pairs per second.
The math is the same in every configuration; bf16 runs under autocast (OMNet keeps poses in float32).

Distance to the machine's limit: the matrix-product FLOPs of a step (forward, loss, backward) are counted
with :class:`torch.utils.flop_counter.FlopCounterMode` in an extra untimed step, and after every timed step
one ``torch.mm`` of 4096×1024 by 1024×1024 (in the step's precision) is timed; ``% of mm`` is the median over
the timed steps of the step's rate over the adjacent product's (:mod:`benchmarks.speed`). ``--clock cpu``
times with the process's CPU time (``--threads 1`` on a shared CPU).

Outputs (``--out``, default ``outputs/train_step``): ``train_step.csv`` and ``train_step.md``.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from benchmarks.speed.inference import count_flops, describe_device, format_rate
from src.utils.machine_speed import CLOCKS, MatmulReference
from src.utils.errors import ConfigError, exit_code_of


PRECISIONS = ("fp32", "bf16")
COMPILE_MODES = ("none", "default", "reduce-overhead", "max-autotune")


def pair_batch(batch: int, points: int, device: torch.device) -> dict[str, torch.Tensor]:
    """``batch`` pairs of ``points`` points (:func:`baselines.testing.paper_range_pair`) on ``device``."""
    from baselines.testing import paper_range_pair

    pairs = [paper_range_pair(points, seed) for seed in range(batch)]
    stacked = lambda i: torch.as_tensor(np.stack([p[i] for p in pairs]), dtype=torch.float32, device=device)  # noqa: E731
    return {"points_src": stacked(0), "points_ref": stacked(1), "transform_gt": stacked(2)}


def build_network(model: str, model_scale: float, overrides: list[str]) -> torch.nn.Module:
    """The network of ``conf/model/<model>.yaml`` with fresh weights."""
    import hydra

    from src.compose import compose_model_config

    return hydra.utils.instantiate(compose_model_config(model, model_scale, overrides).network)


def training_step(network: torch.nn.Module, batch: dict[str, torch.Tensor], precision: str) -> Callable[[], torch.Tensor]:
    """One training step (forward, loss, backward, Adam) of ``network`` on ``batch``, returning the loss."""
    device = batch["points_src"].device
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-4)

    def step() -> torch.Tensor:
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16"):
            outputs = network(batch["points_src"], batch["points_ref"], batch["transform_gt"])
            loss = network.loss(outputs, batch["transform_gt"])["loss"]
        loss.backward()
        optimizer.step()
        return loss

    return step


def profile_step(network: torch.nn.Module, batch: dict[str, torch.Tensor], precision: str, rows: int) -> str:
    """``torch.profiler``'s table of the ``rows`` operators with the most self CPU time in one training step
    (after one unprofiled step)."""
    from torch.profiler import ProfilerActivity, profile

    step = training_step(network, batch, precision)
    step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        step()
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def time_steps(network: torch.nn.Module, batch: dict[str, torch.Tensor], precision: str, steps: int,
               warmup: int, reference: MatmulReference | None = None, clock: str = "wall") -> tuple[list[float], int, list[float]]:
    """Milliseconds of each timed training step; with a ``reference``, also the matrix-product FLOPs of a step
    (counted in an extra step after the warm-up) and the reference product's GFLOP/s after each timed step."""
    device = batch["points_src"].device
    step = training_step(network, batch, precision)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    now = CLOCKS[clock]
    times, flops, mm_rates = [], 0, []
    for k in range(warmup + steps):
        if k == warmup and reference is not None:
            flops = count_flops(step)
        sync()
        start = now()
        loss = step()
        sync()
        if k >= warmup:
            times.append((now() - start) * 1000.0)
            if reference is not None:
                mm_rates.append(reference.rate())
    bad = [name for name, p in network.named_parameters() if p.grad is not None and not torch.isfinite(p.grad).all()]
    if not np.isfinite(loss.item()) or bad:
        raise FloatingPointError(f"non-finite loss ({loss.item():.4g}) or gradients ({len(bad)} tensors) under {precision}")
    return times, flops, mm_rates


def run(args: argparse.Namespace) -> pd.DataFrame:
    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: CUDA is not available on this machine")
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = args.tf32
        torch.backends.cudnn.allow_tf32 = args.tf32
    points_list = [int(p) for p in args.points.split(",")]
    rows = []
    precisions, compile_modes = args.precisions.split(","), args.compile.split(",")
    for name, values, allowed in (("precision", precisions, PRECISIONS), ("compile mode", compile_modes, COMPILE_MODES)):
        unknown = [v for v in values if v not in allowed]
        if unknown:
            raise ConfigError(f"unknown {name} {unknown[0]!r}: choose from {', '.join(allowed)}")
    if args.clock == "cpu" and device.type == "cuda":
        raise ConfigError("--clock cpu times the CPU only; use the wall clock with --device cuda")
    if args.threads:
        torch.set_num_threads(args.threads)
    references = {p: MatmulReference(device.type, torch.bfloat16 if p == "bf16" else torch.float32, args.clock) for p in precisions}
    for points, precision, compile_mode in itertools.product(points_list, precisions, compile_modes):
        torch.manual_seed(0)
        network = build_network(args.model, args.model_scale, args.model_overrides).to(device).train()
        step_network = network if compile_mode == "none" else torch.compile(
            network, mode=None if compile_mode == "default" else compile_mode)
        step_network.loss = network.loss
        batch = pair_batch(args.batch, points, device)
        note = ""
        try:
            times, flops, mm_rates = time_steps(step_network, batch, precision, args.steps, args.warmup,
                                                references[precision], args.clock)
        # non-finite training, compilation failure, out of memory, or a batch of one pair (BatchNorm cannot train on it)
        except (FloatingPointError, RuntimeError, ValueError) as err:
            times, flops, mm_rates = [], 0, []
            note = f"failed: {type(err).__name__}: {str(err).strip().splitlines()[0]}"
        median = statistics.median(times) if times else float("nan")
        rates = [flops / t / 1e6 for t in times]
        rows.append({"model": args.model, "model_scale": args.model_scale, "points": points, "batch": args.batch,
                     "precision": precision, "compile": compile_mode, "device": device.type,
                     "ms_per_step": median, "ms_min": min(times, default=float("nan")),
                     "pairs_per_s": args.batch * 1000.0 / median, "steps": len(times),
                     "gflop_per_step": flops / 1e9 if times else float("nan"),
                     "gflop_per_s": flops / median / 1e6 if times else float("nan"),
                     "mm_gflop_per_s": statistics.median(mm_rates) if times else float("nan"),
                     "pct_of_mm": 100 * statistics.median(r / m for r, m in zip(rates, mm_rates)) if times else float("nan"),
                     "parameters": sum(p.numel() for p in network.parameters()), "note": note})
        print(f"{points} points, {precision}, compile={compile_mode}: {median:.1f} ms/step "
              f"{rows[-1]['gflop_per_s']:.1f} GFLOP/s ({rows[-1]['pct_of_mm']:.0f} % of mm) {note}", flush=True)
        if args.profile and not note:
            table = profile_step(step_network, batch, precision, args.profile)
            Path(args.out).mkdir(parents=True, exist_ok=True)
            (Path(args.out) / f"profile_{points}_{precision}_{compile_mode}.txt").write_text(table)
            print(table, flush=True)
        del network, step_network, batch
        if device.type == "cuda":
            torch.cuda.empty_cache()
    frame = pd.DataFrame(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "train_step.csv", index=False)
    markdown = markdown_table(frame, describe_device(device.type), args)
    (out / "train_step.md").write_text(markdown)
    print(markdown)
    return frame


def markdown_table(frame: pd.DataFrame, device: str, args: argparse.Namespace) -> str:
    eager = frame[(frame["precision"] == "fp32") & (frame["compile"] == "none")].set_index("points")["ms_per_step"]
    lines = [f"**Training step of {args.model} (width {args.model_scale}, {int(frame['parameters'].iloc[0]):,} "
             f"parameters), batch {args.batch} — {device}**", "",
             "| # points | precision | compile | ms/step (median) | pairs/s | vs eager fp32 | GFLOP/s | % of mm |",
             "|---:|---|---|---:|---:|---:|---:|---:|"]
    for _, row in frame.iterrows():
        if row["note"]:
            lines.append(f"| {row['points']} | {row['precision']} | {row['compile']} | {row['note']} | - | - | - | - |")
            continue
        ratio = eager.get(row["points"])
        speedup = f"{ratio / row['ms_per_step']:.2f}×" if ratio is not None and np.isfinite(ratio) else "-"
        lines.append(f"| {row['points']} | {row['precision']} | {row['compile']} | {row['ms_per_step']:.1f} | "
                     f"{format_rate(row['pairs_per_s'])} | {speedup} | {row['gflop_per_s']:.1f} | {row['pct_of_mm']:.0f} |")
    timed = frame.loc[frame["steps"] > 0]
    lines += ["", f"- median of {int(timed['steps'].min()) if len(timed) else 0} timed steps after {args.warmup} warm-up steps; "
              f"fresh weights; one fixed batch on the device (data loading not timed)" + ("; process CPU time" if args.clock == "cpu" else ""),
              f"- GFLOP/s: matrix-product FLOPs of a step ({', '.join(f'{g:.1f}' for g in timed['gflop_per_step'].unique())} GFLOP, "
              f"FlopCounterMode) over the median time; % of mm: median over the timed steps of the step's rate over that of "
              f"a torch.mm of 4096×1024 by 1024×1024 timed after it "
              f"({timed['mm_gflop_per_s'].min():.1f}–{timed['mm_gflop_per_s'].max():.1f} GFLOP/s)" if len(timed) else "- no step timed",
              f"- command: `python -m benchmarks.speed.train_step {' '.join(sys.argv[1:])}`"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed.train_step", description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="omnet", help="conf/model/<name>.yaml (default omnet)")
    parser.add_argument("--model-scale", type=float, default=1.0, help="channel width (default 1.0 = the paper's)")
    parser.add_argument("--model-overrides", nargs="*", default=[], help="Hydra overrides, e.g. model.network.share_weights=true")
    parser.add_argument("--points", default="717,1024", help="points per cloud (default 717,1024)")
    parser.add_argument("--batch", type=int, default=64, help="pairs per step (default 64)")
    parser.add_argument("--precisions", default="fp32,bf16", help="fp32 and/or bf16 (default both)")
    parser.add_argument("--compile", default="none,default", help="torch.compile modes: none, default, reduce-overhead, max-autotune")
    parser.add_argument("--steps", type=int, default=20, help="timed steps (default 20)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first, incl. compilation (default 5)")
    parser.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    parser.add_argument("--tf32", action=argparse.BooleanOptionalAction, default=False,
                        help="allow TF32 matmuls in fp32 on the GPU (changes fp32 rounding; default off)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--clock", default="wall", choices=tuple(CLOCKS),
                        help="wall clock, or the process's CPU time (CPU only: waiting for a busy core not counted)")
    parser.add_argument("--out", default="outputs/train_step", help="output folder")
    parser.add_argument("--profile", type=int, default=0, metavar="ROWS",
                        help="also profile one step: the ROWS operators with the most CPU time (profile_*.txt in --out)")
    args = parser.parse_args(argv)
    return exit_code_of(lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())
