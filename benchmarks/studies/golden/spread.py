"""How far float32 estimates move when only the math library's instruction path changes.

    python -m benchmarks.studies.golden.spread [--methods dcp_v1 ...] [--authors dcp_v1=CHECKOUT ...] \\
        [--out benchmarks/results/float32_spread.md]

Each golden method (ours, and the authors' code where ``--authors`` gives a checkout) registers the golden pairs
in float32 once per :data:`SETTINGS` entry, each in a fresh process with that environment (the knobs are read when
the libraries load). Per pair, the spread is the largest rotation difference between any two settings; the report
gives its median and maximum over the pairs, each setting's largest difference from the first, and the float32
estimates' distance from the float64 golden file. A knob whose results equal the first setting's is reported as
such: on a CPU without AVX-512 some paths (MKL's and oneDNN's AVX-512 kernels) cannot be reached at all, so the
spread measured on one machine is a lower bound of the spread across machines.
"""

from __future__ import annotations

import argparse
import itertools
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.studies.golden.golden_file import (
    golden_path,
    read_golden,
    rotation_difference_deg,
)
from benchmarks.studies.golden.pairs import PAIRS_PER_SAMPLING, SAMPLINGS
from src.utils.errors import ConfigError, exit_code_of

#: name → (environment, torch threads). The first is the reference the others are compared with.
SETTINGS: dict[str, tuple[dict[str, str], int]] = {
    "default (1 thread)": ({}, 1),
    "2 threads": ({}, 2),
    "ATEN_CPU_CAPABILITY=default": ({"ATEN_CPU_CAPABILITY": "default"}, 1),
    "MKL_CBWR=COMPATIBLE": ({"MKL_CBWR": "COMPATIBLE"}, 1),
    "ATEN_CPU_CAPABILITY=default + MKL_CBWR=COMPATIBLE": ({"ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "COMPATIBLE"}, 1),
    "MKL_ENABLE_INSTRUCTIONS=SSE4_2": ({"MKL_ENABLE_INSTRUCTIONS": "SSE4_2"}, 1),
    "ONEDNN_MAX_CPU_ISA=SSE41": ({"ONEDNN_MAX_CPU_ISA": "SSE41"}, 1),
}
#: The environment variables of SETTINGS: cleared for every run, so that only a setting's own apply.
KNOBS = sorted({k for env, _ in SETTINGS.values() for k in env})


def _worker(method: str, impl: str, pairs_file: Path, out: Path, checkout: Path | None, threads: int) -> None:
    """One float32 run (in a process of its own): ``out`` ← (P, 4, 4) estimates."""
    import torch

    from benchmarks.studies.golden import authors, ours

    torch.set_num_threads(threads)
    with np.load(pairs_file) as data:
        pairs = {k: data[k] for k in data.files}
    if impl == "ours":
        estimates = ours.estimates(method, pairs, torch.float32)
    else:
        estimates = authors.REFERENCES[method].run(checkout, pairs, torch.float32)
    np.save(out, estimates)


def run_setting(method: str, impl: str, setting: str, pairs_file: Path, out: Path, checkout: Path | None) -> np.ndarray:
    """The estimates of one (method, implementation, setting), from a fresh process."""
    env_extra, threads = SETTINGS[setting]
    env = {k: v for k, v in os.environ.items() if k not in KNOBS} | env_extra
    command = [sys.executable, "-m", "benchmarks.studies.golden.spread", "--worker", method, impl, str(pairs_file),
               str(out), str(checkout or ""), str(threads)]
    subprocess.run(command, env=env, check=True)
    return np.load(out)


def summarise(runs: dict[str, np.ndarray], golden: np.ndarray | None) -> dict:
    """Per-pair spread (largest difference between any two settings), its median and max; each setting's
    largest difference from the first; per pair the largest distance of any setting from the float64
    ``golden`` (where there is one), its median and max."""
    names = list(runs)
    spread = np.max([rotation_difference_deg(runs[a], runs[b]) for a, b in itertools.combinations(names, 2)], axis=0)
    result = {"median": float(np.median(spread)), "max": float(spread.max()),
              "per_setting": {n: float(rotation_difference_deg(runs[n], runs[names[0]]).max()) for n in names[1:]}}
    if golden is not None:
        to_golden = np.max([rotation_difference_deg(run, golden) for run in runs.values()], axis=0)
        result |= {"golden_median": float(np.median(to_golden)), "golden_max": float(to_golden.max())}
    return result


def conditions() -> str:
    """The torch build and the CPU capability the runs had (what bounds the paths they could reach)."""
    import torch

    return (f"torch {torch.__version__}, ATen CPU capability {torch.backends.cpu.get_cpu_capability()}: the paths of "
            "a higher capability (AVX-512) are not reached, so the spread is a lower bound of the spread across CPUs.")


def report(results: dict[tuple[str, str], dict], pairs: int, command: str) -> str:
    """The Markdown report of :func:`measure`'s results."""
    lines = ["# float32 spread across math-library instruction paths", "",
             (f"Rotation difference (degrees) between float32 estimates of the same {pairs} golden pairs (real "
              "airplanes, PRNet manner, OS and TS, 768 points; `benchmarks/studies/golden/pairs.py`) when only the "
              "environment of the math libraries changes. Spread per pair: the largest difference between any two "
              "settings. float32 vs float64 golden: per pair the largest distance of any setting's float32 estimate "
              "from the authors' float64 one (`tests/fixtures/golden/`)."), "", conditions(), "", "    " + command, "",
             "| method | code | spread median [deg] | spread max [deg] | float32 vs float64 golden, median / max [deg] |",
             "|---|---|---|---|---|"]
    for (method, impl), r in results.items():
        golden = f"{r['golden_median']:.2e} / {r['golden_max']:.2e}" if "golden_median" in r else "no golden file"
        lines.append(f"| {method} | {impl} | {r['median']:.2e} | {r['max']:.2e} | {golden} |")
    settings = list(SETTINGS)[1:]
    lines += ["", (f"Largest difference from `{next(iter(SETTINGS))}` per setting [deg]. Runs of the same settings in "
                   "two processes can differ too (MKL is not bit-reproducible between processes unless `MKL_CBWR` is "
                   "set): columns equal to each other in a row are such runs, not a knob's effect:"), "",
              "| method | code | " + " | ".join(f"`{s}`" for s in settings) + " |", "|---|---|" + "---|" * len(settings)]
    for (method, impl), r in results.items():
        lines.append(f"| {method} | {impl} | " + " | ".join(f"{r['per_setting'][s]:.2e}" for s in settings) + " |")
    return "\n".join(lines) + "\n"


def measure(methods: list[str], checkouts: dict[str, Path]) -> dict[tuple[str, str], dict]:
    """The spread of every method (ours, and the authors' where a checkout is given)."""
    from benchmarks.studies.golden.pairs import golden_pairs, prepare_cache

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        pairs_file = Path(tmp) / "pairs.npz"
        pairs = golden_pairs(prepare_cache(Path(tmp) / "cache"))
        np.savez(pairs_file, **{k: v for k, v in pairs.items() if k in ("src", "ref")})
        for method in methods:
            golden = read_golden(method)["transforms"] if golden_path(method).is_file() else None
            for impl in ("ours", "authors") if method in checkouts else ("ours",):
                runs = {s: run_setting(method, impl, s, pairs_file, Path(tmp) / f"{method}_{impl}_{i}.npy",
                                       checkouts.get(method)) for i, s in enumerate(SETTINGS)}
                results[(method, impl)] = summarise(runs, golden)
                print(method, impl, results[(method, impl)], flush=True)
    return results


def _checkouts(values: list[str]) -> dict[str, Path]:
    out = {}
    for value in values:
        method, sep, path = value.partition("=")
        if not sep:
            raise ConfigError(f"--authors {value!r}: METHOD=CHECKOUT")
        out[method] = Path(path)
    return out


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        method, impl, pairs_file, out, checkout, threads = argv[1:]
        _worker(method, impl, Path(pairs_file), Path(out), Path(checkout) if checkout else None, int(threads))
        return 0
    from benchmarks.studies.golden.authors import REFERENCES
    from benchmarks.studies.golden.ours import METHODS

    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.golden.spread", description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", nargs="+", choices=sorted(METHODS), default=sorted(METHODS))
    parser.add_argument("--authors", nargs="*", default=[], help="METHOD=CHECKOUT of the authors' repository")
    parser.add_argument("--out", type=Path, default=None, help="the Markdown report (default: print it)")
    args = parser.parse_args(argv)

    def run() -> None:
        checkouts = _checkouts(args.authors)
        results = measure(args.methods, checkouts)
        shown = " ".join(["python -m benchmarks.studies.golden.spread", "--methods", *args.methods,
                          *(["--authors", *(f"{m}=<checkout of {REFERENCES[m].repo}>" for m in checkouts)] if checkouts else []),
                          *(["--out", str(args.out)] if args.out else [])])
        text = report(results, len(SAMPLINGS) * PAIRS_PER_SAMPLING, shown)
        if args.out:
            args.out.write_text(text)
        print(text)

    return exit_code_of(run)


if __name__ == "__main__":
    sys.exit(main())
