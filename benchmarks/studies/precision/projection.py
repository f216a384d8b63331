"""Where a training step's time goes in float32 and in bf16-mixed autocast, and what a CPU whose bf16 matrix
units run ``R`` times the float32 product rate can make of it.

    OMP_NUM_THREADS=1 python -m benchmarks.studies.precision.projection --out OUT \\
        [--methods omnet] [--model-scale 0.5] [--batch 16] [--points 768] [--steps 2] [--ratios 7.1]

On one CPU (without bf16 units, where bf16 products are emulated at float32 speed: :mod:`.emulated`) every operation
of a step is timed by :class:`TimedOps` (process CPU time, one thread): the matrix products and convolutions
(:data:`.emulated.PRODUCTS`, forward and backward; fused attention kernels with them, :data:`ATTENTION`) apart from
the rest; the timing's own cost per operation (a float32 step timed with and without it) is taken out. A bf16
step's non-product time is measured (autocast's casts, bf16 elementwise work, BatchNorm, the optimizer); its
products are assumed to take the float32 products' time divided by ``R``. Then, per ``R``:

    projected bf16 step = bf16 non-product time + float32 product time / R
    speed-up            = float32 step / projected bf16 step
    % of the bf16 rate  = the step's product FLOPs / projected step / (R x the float32 torch.mm rate)

``R`` = infinity bounds what any product unit can give (Amdahl). A projection, not a measurement: the non-product
work of another CPU differs (wider vector units convert and add bf16 faster), and the products are assumed to keep
their float32 efficiency. Writes ``OUT/projection.csv`` and ``OUT/projection.md``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections import Counter
from pathlib import Path

import pandas as pd
import torch

from benchmarks.speed.inference import count_flops
from benchmarks.speed.train_step import build_network, pair_batch, training_step
from benchmarks.studies.precision.emulated import PRODUCTS, Bf16ProductsInFp32
from benchmarks.studies.precision.step_times import mm_rate, write_report
from src.utils.errors import exit_code_of

#: The bf16 over float32 torch.mm rate measured on an Intel Xeon with AMX (one thread, 2048x1024 by 1024x1024:
#: 676 against 95 GFLOP/s), the CPU class this projection is for.
AMX_RATIO = 676 / 95
PRODUCT = "matrix products"
#: Fused attention kernels compute their products inside the kernel: in bf16 on a CPU without bf16 units they run
#: the fallback's slow products too, so they are projected like the products (from their float32 time).
ATTENTION = "attention kernels"


class TimedOps(Bf16ProductsInFp32):
    """Times every operation dispatched inside it (process CPU time), by name, and counts them; bf16 products are
    computed as :class:`.emulated.Bf16ProductsInFp32` does and counted under :data:`PRODUCT` with the other
    products."""

    def __init__(self) -> None:
        super().__init__()
        self.seconds: Counter[str] = Counter()
        self.calls = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        start = time.process_time()
        result = super().__torch_dispatch__(func, types, args, kwargs)
        self.seconds[_bucket(func)] += time.process_time() - start
        self.calls += 1
        return result


def _bucket(func: torch._ops.OpOverload) -> str:
    name = func.overloadpacket.__name__
    return PRODUCT if func in PRODUCTS else ATTENTION if name.startswith("_scaled_dot_product") else name


def step_profile(network: torch.nn.Module, batch: dict[str, torch.Tensor], precision: str, steps: int,
                 warmup: int) -> tuple[float, Counter[str], int]:
    """Median seconds of a plain step (no dispatch mode: float32 only, bf16 products being slow fallbacks here)
    or ``nan``; of the median step under :class:`TimedOps`, the seconds of each operation (:data:`PRODUCT` for the
    products; ``"step"``: the step's total, the mode's own overhead included) and its operation count."""
    step = training_step(network, batch, precision)
    for _ in range(warmup):
        step()
    plain, timed_runs = [], []
    for _ in range(steps):
        if precision == "fp32":
            start = time.process_time()
            step()
            plain.append(time.process_time() - start)
        with TimedOps() as timed:
            start = time.process_time()
            loss = step()
            timed.seconds["step"] = time.process_time() - start
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss under {precision}")
        timed_runs.append(timed)
    middle = sorted(timed_runs, key=lambda t: t.seconds["step"])[len(timed_runs) // 2]
    return (statistics.median(plain) if plain else float("nan")), middle.seconds, middle.calls


def project(fp32_step: float, fp32_products: float, bf16_rest: float, flops: int, mm32_gflops: float,
            ratio: float) -> dict[str, float]:
    """The projected bf16 step for products ``ratio`` times faster than float32 (``inf``: free products)."""
    projected = bf16_rest + fp32_products / ratio
    return {"ratio": ratio, "projected_s": projected, "speedup": fp32_step / projected,
            "pct_of_bf16_mm": 100 * flops / projected / (ratio * mm32_gflops * 1e9) if ratio != float("inf") else float("nan")}


def run(args: argparse.Namespace) -> pd.DataFrame:
    torch.set_num_threads(1)
    mm32 = mm_rate(torch.float32)
    batch = pair_batch(args.batch, args.points, torch.device("cpu"))
    rows, lines = [], []
    for method in args.methods.split(","):
        profiles = {}
        for precision in ("fp32", "bf16"):
            torch.manual_seed(0)
            network = build_network(method, args.model_scale, []).train()
            profiles[precision] = step_profile(network, batch, precision, args.steps, args.warmup)
        (fp32_step, fp32, fp32_calls), (_, bf16, bf16_calls) = profiles["fp32"], profiles["bf16"]
        per_call = max(fp32["step"] - fp32_step, 0.0) / fp32_calls  # the dispatch mode's own cost per operation
        bf16_rest = bf16["step"] - bf16[PRODUCT] - bf16[ATTENTION] - per_call * bf16_calls
        fp32_products = fp32[PRODUCT] + fp32[ATTENTION]
        torch.manual_seed(0)
        flops = count_flops(training_step(build_network(method, args.model_scale, []).train(), batch, "fp32"))
        base = {"method": method, "fp32_step_s": fp32_step, "fp32_products_s": fp32_products,
                "fp32_rest_s": fp32_step - fp32_products, "bf16_rest_s": bf16_rest, "mode_us_per_op": 1e6 * per_call,
                "gflop": flops / 1e9, "mm32_gflops": mm32, "fp32_pct_of_mm": 100 * flops / fp32_step / (mm32 * 1e9)}
        for ratio in [*args.ratios, float("inf")]:
            rows.append({**base, **project(fp32_step, fp32_products, bf16_rest, flops, mm32, ratio)})
        lines += _describe(method, fp32, bf16, base, rows[-len(args.ratios) - 1:], args.top)
    frame = pd.DataFrame(rows)
    write_report(Path(args.out), "projection", frame, lines, args, "one thread, bf16 products emulated")
    return frame


def _describe(method: str, fp32: Counter[str], bf16: Counter[str], base: dict, projections: list[dict],
              top: int) -> list[str]:
    """Markdown: the step's split, the projection per ratio and the ``top`` non-product operations of the bf16 step."""
    lines = [f"## {method}", "",
             f"float32 step {base['fp32_step_s']:.2f} s: products (attention kernels included) {base['fp32_products_s']:.2f} s "
             f"({100 * base['fp32_products_s'] / base['fp32_step_s']:.0f} %), the rest {base['fp32_rest_s']:.2f} s; "
             f"{base['gflop']:.1f} GFLOP of products, {base['fp32_pct_of_mm']:.0f} % of the float32 torch.mm rate "
             f"({base['mm32_gflops']:.1f} GFLOP/s). bf16-mixed step without its products: {base['bf16_rest_s']:.2f} s "
             f"(the timing's own {base['mode_us_per_op']:.0f} µs per operation taken out).", "",
             "| bf16 / fp32 product rate | projected bf16 step (s) | speed-up over fp32 | % of the bf16 mm rate |",
             "|---:|---:|---:|---:|"]
    for p in projections:
        ratio = "unbounded" if p["ratio"] == float("inf") else f"{p['ratio']:.1f}x"
        pct = "-" if p["pct_of_bf16_mm"] != p["pct_of_bf16_mm"] else f"{p['pct_of_bf16_mm']:.0f} %"
        lines.append(f"| {ratio} | {p['projected_s']:.2f} | {p['speedup']:.2f}x | {pct} |")
    rest = Counter({k: v for k, v in bf16.items() if k not in ("step", PRODUCT, ATTENTION)})
    lines += ["", "Non-product operations with the most time in the bf16 step (float32 step beside):", "",
              "| operation | bf16 step (s) | float32 step (s) |", "|---|---:|---:|"]
    lines += [f"| {name} | {seconds:.3f} | {fp32.get(name, 0.0):.3f} |" for name, seconds in rest.most_common(top)]
    return lines + [""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--methods", default="omnet")
    parser.add_argument("--model-scale", type=float, default=0.5)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--points", type=int, default=768)
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--ratios", type=lambda s: [float(x) for x in s.split(",")], default=[AMX_RATIO])
    parser.add_argument("--top", type=int, default=10)
    parser.add_argument("--out", default="outputs/precision_projection")
    args = parser.parse_args(argv)
    try:
        run(args)
    except Exception as err:
        return exit_code_of(err)
    return 0


if __name__ == "__main__":
    sys.exit(main())
