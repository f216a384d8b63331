"""The precision table from ``fit_pairs``' ``fits.csv`` files: per method and recorded step, float32 and bf16
Error(R) over the seeds, the gap, the seed-to-seed spread, and the early-step verdict (the history of
``benchmarks/results/precision.md``; ``trainer.precision=auto``'s verdicts come from ``time_to_accuracy.py``).

    python -m benchmarks.studies.precision.report RUN/fits.csv [RUN2/fits.csv ...] [--out table.md]

Verdict (at the method's last recorded step with at least two seeds in each precision): ``changes`` when the bf16
seeds' mean Error(R) lies outside the range of the float32 seeds (min to max) and the float32 mean outside the
range of the bf16 seeds (higher or lower: either changes the result), else ``same``; runs with float32 parts (``fp32_modules``) are separate rows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from src.utils.errors import ConfigError, exit_code_of

KEYS = ["method", "width", "fp32_modules"]
MIN_SEEDS = 2


def _runs(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per (method, width, fp32_modules of the bf16 runs, step): both precisions' seeds."""
    frame = frame.fillna({"fp32_modules": "", "kernels": ""})
    fp32 = frame[frame["precision"] == "fp32"]
    rows = []
    for (method, width, modules), bf16 in frame[frame["precision"] == "bf16"].groupby(KEYS):
        for step, at in bf16.groupby("step"):
            ref = fp32[(fp32["method"] == method) & (fp32["width"] == width) & (fp32["step"] == step)]
            seeds = sorted(set(at["seed"]) & set(ref["seed"]))
            if not seeds:
                continue
            a = ref.set_index("seed").loc[seeds, "rot_deg"]
            b = at.set_index("seed").loc[seeds, "rot_deg"]
            rows.append({"method": method, "width": width, "fp32_modules": modules, "step": step, "seeds": len(seeds),
                         "kernels": ", ".join(sorted(set(at["kernels"]))),
                         "fp32_mean": a.mean(), "fp32_min": a.min(), "fp32_max": a.max(),
                         "bf16_mean": b.mean(), "bf16_min": b.min(), "bf16_max": b.max(), "gap": b.mean() - a.mean()})
    return pd.DataFrame(rows)


def verdicts(runs: pd.DataFrame) -> dict[tuple, tuple[int, str]]:
    """(method, width, fp32_modules) -> (the step judged, ``same`` or ``changes (bf16 higher|lower)``): the last
    recorded step with at least :data:`MIN_SEEDS` seeds."""
    out = {}
    for key, group in runs.groupby(KEYS):
        enough = group[group["seeds"] >= MIN_SEEDS]
        if enough.empty:
            out[key] = (int(group["step"].max()), f"- (fewer than {MIN_SEEDS} seeds)")
            continue
        last = enough.loc[enough["step"].idxmax()]
        within = (last["fp32_min"] <= last["bf16_mean"] <= last["fp32_max"]
                  or last["bf16_min"] <= last["fp32_mean"] <= last["bf16_max"])
        direction = "higher" if last["gap"] > 0 else "lower"
        out[key] = (int(last["step"]), "same" if within else f"changes (bf16 {direction})")
    return out


def table(runs: pd.DataFrame) -> str:
    found = verdicts(runs)
    lines = ["| method | width | bf16 with float32 parts | step | seeds | fp32 Error(R) mean (min–max) | "
             "bf16 Error(R) mean (min–max) | bf16 − fp32 | verdict |", "|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for _, r in runs.sort_values([*KEYS, "step"]).iterrows():
        step, verdict = found[(r["method"], r["width"], r["fp32_modules"])]
        lines.append(f"| {r['method']} | {r['width']:g} | {r['fp32_modules'] or '-'} | {r['step']} | {r['seeds']} | "
                     f"{r['fp32_mean']:.2f} ({r['fp32_min']:.2f}–{r['fp32_max']:.2f}) | "
                     f"{r['bf16_mean']:.2f} ({r['bf16_min']:.2f}–{r['bf16_max']:.2f}) | {r['gap']:+.2f} | "
                     f"{verdict if r['step'] == step else ''} |")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> str:
    missing = [p for p in args.fits if not Path(p).is_file()]
    if missing:
        raise ConfigError(f"no such file: {missing[0]}")
    runs = _runs(pd.concat([pd.read_csv(p, keep_default_na=False) for p in args.fits], ignore_index=True))
    if runs.empty:
        raise ConfigError("no method has float32 and bf16 runs of the same seed at the same step in these files")
    text = table(runs)
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.precision.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("fits", nargs="+", help="fits.csv files of benchmarks.studies.precision.fit_pairs")
    parser.add_argument("--out", default=None, help="write the table here too")
    return exit_code_of(lambda: run(parser.parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
