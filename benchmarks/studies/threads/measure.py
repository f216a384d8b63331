"""Two cores: one training run with two intra-op threads, or two runs with one thread each?

    python -m benchmarks.studies.threads.measure --out OUT [--rounds 2] [-- TRAIN_STEP_ARGS]

Each round times ``benchmarks.speed.train_step`` (wall clock, its ``torch.mm`` reference after every step) once as one
process with ``--threads 2`` and once as two processes with ``--threads 1`` started together, alternating so that
a changing load on a shared machine falls on both. Throughput is pairs per second summed over the processes; each
process's rate is also given over its own mm rate (``% of mm``), which the load moves less than absolute times.
Writes ``OUT/threads.csv`` (one row per process and round) and ``OUT/threads.md`` (the summary).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd

from src.utils.errors import ConfigError, exit_code_of

DEFAULT_STEP = ["--model", "omnet", "--model-scale", "0.25", "--points", "384", "--batch", "16", "--precisions", "fp32",
                "--compile", "none", "--steps", "5", "--warmup", "1", "--clock", "wall"]
SETUPS = {"1 run x 2 threads": (1, 2), "2 runs x 1 thread": (2, 1)}


def run_setup(name: str, processes: int, threads: int, step_args: list[str], out: Path) -> list[dict]:
    """Start ``processes`` train_step runs of ``threads`` threads together; their rows."""
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    folders = [out / f"{name.replace(' ', '_')}_{k}" for k in range(processes)]
    children = [subprocess.Popen([sys.executable, "-m", "benchmarks.speed.train_step", *step_args, "--threads", str(threads),
                                  "--out", str(folder)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                for folder in folders]
    rows = []
    for child, folder in zip(children, folders):
        _, err = child.communicate()
        if child.returncode != 0:
            raise ConfigError(f"benchmarks.speed.train_step failed ({name}): {(err.strip().splitlines() or ['?'])[-1]}")
        row = pd.read_csv(folder / "train_step.csv").iloc[0]
        rows.append({"setup": name, "threads": threads, "ms_per_step": row["ms_per_step"], "pairs_per_s": row["pairs_per_s"],
                     "mm_gflop_per_s": row["mm_gflop_per_s"], "pct_of_mm": row["pct_of_mm"]})
    return rows


def summary(frame: pd.DataFrame, command: str) -> str:
    """Per setup: pairs/s summed over its processes (median over rounds), ms/step and % of mm per process."""
    per_round = frame.groupby(["setup", "round"]).agg(pairs_per_s=("pairs_per_s", "sum"), ms=("ms_per_step", "median"),
                                                      pct=("pct_of_mm", "median"), mm=("mm_gflop_per_s", "median"))
    table = per_round.groupby("setup").median()
    base = table.loc["1 run x 2 threads", "pairs_per_s"]
    lines = ["| setup | pairs/s (all processes) | vs 1 run x 2 threads | ms/step per process | % of mm per process | mm GFLOP/s |",
             "|---|---:|---:|---:|---:|---:|"]
    for setup, row in table.iterrows():
        lines.append(f"| {setup} | {row['pairs_per_s']:.2f} | {row['pairs_per_s'] / base:.2f}x | {row['ms']:.0f} | "
                     f"{row['pct']:.0f} | {row['mm']:.1f} |")
    rounds = frame["round"].nunique()
    return "\n".join(lines + ["", f"- median over {rounds} alternating rounds; wall clock; command: `{command}`"]) + "\n"


def run(args: argparse.Namespace) -> pd.DataFrame:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    step_args = args.step_args or DEFAULT_STEP
    rows = []
    for k in range(args.rounds):
        for name, (processes, threads) in SETUPS.items():
            rows += [{**r, "round": k} for r in run_setup(name, processes, threads, step_args, out / f"round_{k}")]
    frame = pd.DataFrame(rows)
    frame.to_csv(out / "threads.csv", index=False)
    text = summary(frame, " ".join(["python -m benchmarks.studies.threads.measure", *sys.argv[1:]]))
    (out / "threads.md").write_text(text)
    print(text)
    return frame


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.threads.measure", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds of both setups (default 2)")
    parser.add_argument("step_args", nargs="*", help=f"benchmarks.speed.train_step arguments after -- (default: {' '.join(DEFAULT_STEP)})")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    return exit_code_of(lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())
