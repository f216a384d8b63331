"""Every learned method's training step in float32 and in bf16-mixed autocast, in one process (the same run):
the step-time ratio a CPU gives each method, beside the ratio of its bare matrix products.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.precision.step_times --out OUT \\
        [--methods omnet,dcp,...] [--model-scale 0.25] [--batch 4] [--points 256] [--steps 2]

Per method: :func:`benchmarks.speed.train_step.time_steps` (fresh weights, one fixed batch, Adam; ``--warmup`` untimed
steps, then the median of ``--steps``; process CPU time), float32 then bf16. Before the methods, the rate of a
``torch.mm`` of 1024×1024 by 1024×1024 in each precision (best of 3). Writes ``OUT/step_times.csv`` and
``OUT/step_times.md``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import pandas as pd
import torch

from benchmarks.speed.train_step import build_network, pair_batch, time_steps
from src.utils.errors import exit_code_of

METHODS = ("omnet", "dcp", "rpmnet", "fmr", "idam", "deepgmr", "pointnetlk", "pointnetlk_revisited", "prnet")


def mm_rate(dtype: torch.dtype, size: int = 1024) -> float:
    """GFLOP/s of a ``size``³ ``torch.mm`` in ``dtype`` (best of 3, process CPU time)."""
    a, b = torch.randn(size, size, dtype=dtype), torch.randn(size, size, dtype=dtype)
    torch.mm(a, b)
    best = float("inf")
    for _ in range(3):
        start = time.process_time()
        torch.mm(a, b)
        best = min(best, time.process_time() - start)
    return 2 * size**3 / max(best, 1e-9) / 1e9


def run(args: argparse.Namespace) -> pd.DataFrame:
    torch.set_num_threads(1)
    rates = {"fp32": mm_rate(torch.float32), "bf16": mm_rate(torch.bfloat16)}
    print(f"torch.mm 1024^3: fp32 {rates['fp32']:.1f} GFLOP/s, bf16 {rates['bf16']:.2f} GFLOP/s", flush=True)
    rows = []
    batch = pair_batch(args.batch, args.points, torch.device("cpu"))
    for method in args.methods.split(","):
        row = {"method": method}
        for precision in ("fp32", "bf16"):
            torch.manual_seed(0)
            network = build_network(method, args.model_scale, []).train()
            try:
                times, _, _ = time_steps(network, batch, precision, args.steps, args.warmup, clock="cpu")
                row[f"{precision}_ms"] = statistics.median(times)
            except (FloatingPointError, RuntimeError, ValueError) as err:
                row[f"{precision}_ms"] = float("nan")
                row["note"] = f"{precision}: {type(err).__name__}: {str(err).strip().splitlines()[0]}"
        row["bf16_over_fp32"] = row["bf16_ms"] / row["fp32_ms"]
        rows.append(row)
        print(f"{method}: fp32 {row['fp32_ms']:.0f} ms, bf16 {row['bf16_ms']:.0f} ms ({row['bf16_over_fp32']:.1f}x) "
              f"{row.get('note', '')}", flush=True)
    frame = pd.DataFrame(rows)
    lines = [f"torch.mm 1024³ (best of 3): fp32 {rates['fp32']:.1f} GFLOP/s, bf16 {rates['bf16']:.2f} GFLOP/s "
             f"(bf16 {rates['fp32'] / rates['bf16']:.0f}x slower)", "",
             "| method | fp32 ms/step | bf16-mixed ms/step | bf16 / fp32 |", "|---|---:|---:|---:|"]
    for _, r in frame.iterrows():
        note = r.get("note")
        ratio = f"{r['bf16_over_fp32']:.1f}x" if pd.notna(r["bf16_over_fp32"]) else str(note)
        lines.append(f"| {r['method']} | {r['fp32_ms']:.0f} | {r['bf16_ms']:.0f} | {ratio} |")
    write_report(Path(args.out), "step_times", frame, lines, args, "one thread")
    return frame


def write_report(out: Path, name: str, frame: pd.DataFrame, lines: list[str], args: argparse.Namespace, how: str) -> None:
    """``out/<name>.csv`` (``frame``) and ``out/<name>.md`` (``lines``, then the run's size, ``how`` it was timed
    and its command), the latter printed."""
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / f"{name}.csv", index=False)
    lines = [*lines, "", f"- width {args.model_scale}, batch {args.batch}, {args.points} points, median of {args.steps} "
             f"steps after {args.warmup}, process CPU time, {how}; command: "
             f"`python -m benchmarks.studies.precision.{name} {' '.join(sys.argv[1:])}`"]
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.precision.step_times", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--methods", default=",".join(METHODS), help="conf/model/<name>.yaml names (default: all learned)")
    parser.add_argument("--model-scale", type=float, default=0.25, help="channel width (default 0.25)")
    parser.add_argument("--batch", type=int, default=4, help="pairs per step (default 4)")
    parser.add_argument("--points", type=int, default=256, help="points per cloud (default 256)")
    parser.add_argument("--steps", type=int, default=2, help="timed steps (default 2)")
    parser.add_argument("--warmup", type=int, default=1, help="untimed steps first (default 1)")
    return exit_code_of(lambda: run(parser.parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
