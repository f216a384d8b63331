"""Registration speed in milliseconds per pair, shaped like the paper's speed table (supplementary,
"Speed comparison for registering a point cloud pair of various sizes"): rows = number of points,
columns = methods.

Usage: ``python -m benchmarks.speed --help``. The pairs, how each method is timed, the batched throughput,
the distance to the machine's limit and the outputs: ``docs/methods/speed.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from baselines import get_registrator, resolve_registrator
from baselines.base import Registrator
from baselines.methods import default_speed_methods, display_name, find_method, paper_rank
from src.utils.errors import ConfigError, exit_code_of
from src.utils.machine_speed import CLOCKS, MM_REFERENCE, MatmulReference

DEFAULT_SIZES = (512, 1024, 2048, 4096)
PAPER_SPEED_CSV = "supp_speed_ms.csv"
#: Examples for ``--help`` (the methods, pairs and outputs: docs/methods/speed.md).
USAGE = """examples:
  python -m benchmarks.speed                                       # every available method, 512..4096 points
  python -m benchmarks.speed --methods icp,fgr,symmetric_icp --sizes 1024 --repeats 10
  python -m benchmarks.speed --methods omnet,dcp --checkpoint omnet=outputs/.../best.ckpt
  python -m benchmarks.speed --devices cpu --max-seconds 20 --out results/speed
  python -m benchmarks.speed --methods omnet --batch-sizes 1,64,256 --compile reduce-overhead --precision bf16
"""


def _learned(name: str) -> bool:
    """A learned method of the registry (:mod:`baselines.methods`); registered extras are timed as classical."""
    method = find_method(name)
    return method is not None and method.kind == "learned"


# --- inputs ------------------------------------------------------------------------------------------


def make_pair(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A (src, ref) pair of ``n`` points each (:func:`baselines.testing.paper_range_pair`), rounded
    to float32 as the networks see it."""
    from baselines.testing import paper_range_pair

    src, ref, _ = paper_range_pair(n, seed)
    return src.astype(np.float32).astype(np.float64), ref.astype(np.float32).astype(np.float64)


# --- distance to the machine's limit (the reference product: src.utils.machine_speed) -------------------------

def count_flops(call: Callable[[], Any]) -> int:
    """Matrix-product FLOPs of one ``call()`` (:class:`torch.utils.flop_counter.FlopCounterMode`)."""
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter:
        call()
    return counter.get_total_flops()


# --- timing ------------------------------------------------------------------------------------------


@dataclass
class Timing:
    method: str
    label: str
    device: str
    weights: str
    points: int
    times_ms: list[float]  # per call of ``batch`` pairs
    note: str = ""
    batch: int = 1
    flops: int = 0  # matrix-product FLOPs of one call (0: not counted)
    mm_rates: list[float] = field(default_factory=list)  # GFLOP/s of the reference product after each timed call

    def row(self) -> dict[str, Any]:
        per_pair = [t / self.batch for t in self.times_ms]
        q = np.percentile(per_pair, [25, 75]) if per_pair else [np.nan, np.nan]
        median = statistics.median(per_pair) if per_pair else np.nan
        counted = bool(self.flops and self.mm_rates)
        rates = [self.flops / t / 1e6 for t in self.times_ms] if counted else []
        return {
            "points": self.points, "batch": self.batch, "method": self.label, "method_id": self.method,
            "device": self.device, "weights": self.weights, "ms_per_pair": median,
            "ms_p25": float(q[0]), "ms_p75": float(q[1]), "pairs_per_s": 1000.0 / median if per_pair else np.nan,
            "runs": len(per_pair), "gflop_per_call": self.flops / 1e9 if counted else np.nan,
            "gflop_per_s": self.flops / statistics.median(self.times_ms) / 1e6 if counted else np.nan,
            "mm_gflop_per_s": statistics.median(self.mm_rates) if counted else np.nan,
            "pct_of_mm": 100 * statistics.median(r / m for r, m in zip(rates, self.mm_rates)) if counted else np.nan,
            "note": self.note,
        }


def time_method(
    registrator: Registrator, sizes: list[int], repeats: int, warmup: int, max_seconds: float | None,
    label: str, device: str, weights: str, progress: bool = True, batch: int = 1,
    reference: MatmulReference | None = None, clock: str = "wall",
) -> list[Timing]:
    """Median-ready timings (ms) of ``registrator.register`` (``register_batch`` of ``batch`` stacked
    pairs when ``batch > 1``) at each size; a size that fails is recorded with no times and the
    reason, and larger sizes are still tried. With a ``reference``, the FLOPs of a call are counted and
    the reference product is timed after each timed call."""
    from tqdm.auto import tqdm

    registrator.setup()
    sync = getattr(registrator, "synchronize", lambda: None)
    now = CLOCKS[clock]
    out = []
    for n in sizes:
        times: list[float] = []
        timing = Timing(registrator.name, label, device, weights, n, times, "", batch)
        inputs = [make_pair(n, seed) for seed in range(warmup + repeats)]
        if batch > 1:  # each call: `batch` pairs (the sampled pairs repeated to fill it)
            inputs = [tuple(np.stack([inputs[(k + j) % len(inputs)][i] for j in range(batch)]) for i in (0, 1))
                      for k in range(len(inputs))]
        register = registrator.register if batch == 1 else registrator.register_batch
        started = time.perf_counter()
        bar = tqdm(total=warmup + repeats, disable=not progress, desc=f"{label} {device} {n}x{batch}", unit="call",
                   leave=False)
        try:
            for k, (src, ref) in enumerate(inputs):
                if k == warmup and reference is not None:
                    timing.flops = count_flops(lambda: register(src, ref))  # noqa: B023 - called at once
                sync()
                start = now()
                register(src, ref)
                sync()
                elapsed = (now() - start) * 1000.0
                bar.update(1)
                if k >= warmup:
                    times.append(elapsed)
                    if reference is not None:
                        timing.mm_rates.append(reference.rate())
                    if max_seconds is not None and time.perf_counter() - started > max_seconds:
                        timing.note = f"stopped after {len(times)} timed runs (--max-seconds {max_seconds:g})"
                        break
        except Exception as exc:  # noqa: BLE001 - e.g. out of memory: record and go on
            lines = str(exc).strip().splitlines()
            timing.note = f"failed: {type(exc).__name__}: {lines[0] if lines else ''}".strip()
            times.clear()
            _free_cuda()
        finally:
            bar.close()
        out.append(timing)
    return out


def _free_cuda() -> None:
    try:
        import torch

        if torch.cuda.is_available():
            torch.cuda.empty_cache()
    except ImportError:  # pragma: no cover
        pass


def describe_device(device: str) -> str:
    """``CPU: <model> (<n> usable cores), torch <v>`` or ``GPU: <name>, CUDA <v>, torch <v>``."""
    import torch

    if device == "cuda":
        return f"GPU: {torch.cuda.get_device_name(0)}, CUDA {torch.version.cuda}, torch {torch.__version__}"
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:  # pragma: no cover - not Linux
        pass
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover
        cores = os.cpu_count() or 1
    return f"CPU: {model} ({cores} usable cores, torch threads {torch.get_num_threads()}), torch {torch.__version__}"


# --- tables ------------------------------------------------------------------------------------------


def _fmt_ms(value: float) -> str:
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:.0f}" if value >= 10 else f"{value:.1f}"


def _column_order(method: str) -> tuple:
    """The paper's column order (the registry's ``speed``); other methods before OMNet (the last column, as in the paper)."""
    return (*paper_rank(method, "speed"), method)


def _fmt_paper(value: float) -> str:
    return f"{value:.0f}" if value is not None and np.isfinite(value) else "-"


def markdown_table(frame: pd.DataFrame, device: str, header: str) -> str:
    """Rows = number of points, columns = methods (the paper's layout); ms per pair (median)."""
    part = frame[((frame["device"] == device) | (frame["weights"] == "none")) & (frame["batch"] == 1)]
    if part.empty:
        return ""
    order = sorted(part["method_id"].unique(), key=_column_order)
    labels = {}
    for method in order:
        rows = part[part["method_id"] == method]
        label = str(rows["method"].iloc[0])
        if (rows["weights"] == "untrained").any():
            label = label.replace(" (untrained)", "") + "†"
        labels[method] = label
    lines = [f"**Speed (ms per pair, median) — {header}**", "",
             "| # points | " + " | ".join(labels[m] for m in order) + " |",
             "|---:|" + "---:|" * len(order)]
    for points in sorted(part["points"].unique()):
        cells = []
        for method in order:
            hit = part[(part["points"] == points) & (part["method_id"] == method)]
            cells.append(_fmt_ms(float(hit["ms_per_pair"].iloc[0])) if len(hit) else "")
        lines.append(f"| {points} | " + " | ".join(cells) + " |")
    notes = []
    if any(label.endswith("†") for label in labels.values()):
        notes.append("† freshly initialised weights (timing only; no trained checkpoint was given)")
    if (part["weights"] == "none").any() and device != "cpu":
        notes.append("classical methods always run on the CPU")
    runs = part["runs"]
    if len(runs):
        span = f"{int(runs.min())}" if runs.min() == runs.max() else f"{int(runs.min())}–{int(runs.max())}"
        notes.append(f"median over {span} timed runs per cell, after warm-up; one pair per call (batch 1)")
    for _, row in part[part["note"].astype(bool)].iterrows():
        notes.append(f"{row['method']} at {row['points']} points: {row['note']}")
    return "\n".join(lines + [""] + [f"- {n}" for n in notes]) + "\n"


def format_rate(value: float) -> str:
    """Pairs per second: whole numbers from 10 up, two significant digits below, ``-`` if missing."""
    if value is None or not np.isfinite(value):
        return "-"
    return f"{value:,.0f}" if value >= 10 else f"{value:.2g}"


def throughput_table(frame: pd.DataFrame, device: str, header: str) -> str:
    """Learned networks with batch > 1: pairs per second (median call), rows = points."""
    part = frame[(frame["device"] == device) & (frame["weights"] != "none")]
    if not (part["batch"] > 1).any():
        return ""
    columns = list(dict.fromkeys(zip(part["method"], part["batch"])))
    lines = [f"**Throughput (pairs per second) — {header}**", "",
             "| # points | " + " | ".join(f"{m} B={b}" for m, b in columns) + " |", "|---:|" + "---:|" * len(columns)]
    for points in sorted(part["points"].unique()):
        cells = []
        for method, batch in columns:
            hit = part[(part["points"] == points) & (part["method"] == method) & (part["batch"] == batch)]
            value = float(hit["pairs_per_s"].iloc[0]) if len(hit) else np.nan
            cells.append(format_rate(value))
        lines.append(f"| {points} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def limit_table(frame: pd.DataFrame, device: str, header: str) -> str:
    """Learned networks: matrix-product GFLOP/s and % of the reference ``torch.mm``'s, rows = points."""
    part = frame[(frame["device"] == device) & frame["gflop_per_s"].notna()]
    if part.empty:
        return ""
    m, k, n = MM_REFERENCE
    columns = list(dict.fromkeys(zip(part["method"], part["batch"])))
    lines = [f"**Distance to the limit (matrix-product GFLOP/s and % of the rate of a torch.mm of {m}×{k} by {k}×{n} "
             f"timed after each call) — {header}**", "",
             "| # points | " + " | ".join(f"{method} B={batch}" for method, batch in columns) + " |",
             "|---:|" + "---:|" * len(columns)]
    for points in sorted(part["points"].unique()):
        cells = []
        for method, batch in columns:
            hit = part[(part["points"] == points) & (part["method"] == method) & (part["batch"] == batch)]
            cells.append(f"{hit['gflop_per_s'].iloc[0]:.1f} ({hit['pct_of_mm'].iloc[0]:.0f} %)" if len(hit) else "-")
        lines.append(f"| {points} | " + " | ".join(cells) + " |")
    mm = part["mm_gflop_per_s"]
    lines += ["", f"- torch.mm: {mm.min():.1f}–{mm.max():.1f} GFLOP/s (median per cell); % of mm: median over the timed "
              "calls of the call's rate over the next product's; FLOPs counted with FlopCounterMode"]
    return "\n".join(lines) + "\n"


def paper_table(paper_dir: Path | None = None) -> str:
    """The paper's own speed table (from its CSV), for reference."""
    from benchmarks.tables.paper import default_paper_dir

    path = Path(paper_dir or default_paper_dir()) / PAPER_SPEED_CSV
    if not path.is_file():
        return ""
    paper = pd.read_csv(path)
    wide = paper.pivot_table(index="points", columns="method", values="ms_per_pair", sort=False)
    methods = list(dict.fromkeys(paper["method"]))
    lines = ["**The paper's speed table (ms per pair; learned methods on an RTX 2080Ti GPU, the others on two "
             "Xeon Gold 6130 CPUs)**", "", "| # points | " + " | ".join(methods) + " |", "|---:|" + "---:|" * len(methods)]
    for points in wide.index:
        lines.append(f"| {points} | " + " | ".join(_fmt_paper(wide.loc[points, m]) if m in wide.columns else "-" for m in methods) + " |")
    return "\n".join(lines) + "\n"


# --- command line -------------------------------------------------------------------------------------


def _parse_checkpoints(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--checkpoint takes NAME=PATH (e.g. omnet=outputs/.../best.ckpt), got {item!r}")
        name, path = item.split("=", 1)
        out[resolve_registrator(name.strip()).name] = path.strip()
    return out


def default_methods() -> list[str]:
    """The registry's default speed methods (:func:`baselines.methods.default_speed_methods`)."""
    return default_speed_methods()


def build(method: str, device: str, checkpoints: dict[str, str], model_scale: float) -> tuple[Registrator, str]:
    """The registrator and its weights label (``trained`` / ``untrained`` / ``none``). Fresh weights are drawn
    from seed 0, so that runs (and versions of the code) time the same network: OMNet's work depends on its
    masks, hence on its weights."""
    import torch

    if not _learned(method):
        return get_registrator(method), "none"
    if method in checkpoints:
        return get_registrator(method, checkpoint=checkpoints[method], device=device), "trained"
    registrator = get_registrator(method, fresh_weights=True, model_scale=model_scale, device=device)
    torch.manual_seed(0)
    registrator.setup()  # builds the network now, from the seed
    return registrator, "untrained"


def accelerate(registrator: Registrator, compile_mode: str, precision: str) -> str:
    """Apply ``torch.compile`` / bf16 autocast to a learned registrator's network; returns a label suffix."""
    import torch

    if compile_mode == "none" and precision == "fp32":
        return ""
    module = registrator.module
    network = module.network
    if compile_mode != "none":
        network = torch.compile(network, mode=None if compile_mode == "default" else compile_mode)
    if precision == "bf16":
        network = _autocast(network, registrator.device.type)
    module.network = network
    return " [" + ", ".join(x for x in (f"compile={compile_mode}" if compile_mode != "none" else "",
                                         precision if precision != "fp32" else "") if x) + "]"


def _autocast(network: Any, device_type: str) -> Any:
    """``network`` called under bf16 autocast, as a module (it replaces the module's network)."""
    import torch

    class Autocast(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.inner = network

        def forward(self, *args: Any, **kwargs: Any) -> Any:
            with torch.autocast(device_type, dtype=torch.bfloat16):
                return self.inner(*args, **kwargs)

    return Autocast()


def run(args: argparse.Namespace) -> pd.DataFrame:
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    methods = [resolve_registrator(m.strip()).name for m in args.methods.split(",") if m.strip()] if args.methods else default_methods()
    sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    if not sizes or min(sizes) < 3:
        raise ConfigError(f"--sizes must list point counts >= 3, got {args.sizes!r}")
    if args.repeats < 1 or args.warmup < 0:
        raise ConfigError("--repeats must be >= 1 and --warmup >= 0")
    batch_sizes = [int(b) for b in args.batch_sizes.split(",") if b.strip()]
    if not batch_sizes or min(batch_sizes) < 1:
        raise ConfigError(f"--batch-sizes must list sizes >= 1, got {args.batch_sizes!r}")
    devices = [d.strip() for d in (args.devices or ("cpu,cuda" if torch.cuda.is_available() else "cpu")).split(",") if d.strip()]
    for device in devices:
        if device not in ("cpu", "cuda"):
            raise ConfigError(f"--devices takes cpu and/or cuda, got {device!r}")
        if device == "cuda" and not torch.cuda.is_available():
            raise ConfigError("--devices cuda: CUDA is not available on this machine")
    if args.clock == "cpu" and "cuda" in devices:
        raise ConfigError("--clock cpu times the CPU only; use the wall clock with --devices cuda")
    checkpoints = _parse_checkpoints(args.checkpoint or [])
    references: dict[str, MatmulReference] = {}
    timings: list[Timing] = []
    for method in methods:
        learned = _learned(method)
        for device in devices if learned else ["cpu"]:
            try:
                registrator, weights = build(method, device, checkpoints, args.model_scale)
            except ConfigError as err:
                if args.methods:  # named explicitly: a user error
                    raise
                print(f"note: skipping {method}: {err}", file=sys.stderr)
                break
            label = getattr(registrator, "label", display_name(method))
            reference = None
            if learned:
                label += accelerate(registrator, args.compile, args.precision)
                if device not in references:
                    dtype = torch.bfloat16 if args.precision == "bf16" else torch.float32
                    references[device] = MatmulReference(device, dtype, args.clock)
                reference = references[device]
            for batch in batch_sizes if learned else [1]:
                timings += time_method(registrator, sizes, args.repeats, args.warmup, args.max_seconds, label,
                                       device, weights, progress=not args.no_progress, batch=batch,
                                       reference=reference, clock=args.clock)
            del registrator
            _free_cuda()
    frame = pd.DataFrame([t.row() for t in timings])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "speed.csv", index=False)
    parts = [f"# Registration speed\n\nGenerated by `python -m benchmarks.speed` on {time.strftime('%Y-%m-%d %H:%M')}.\n"]
    for device in devices:
        table = markdown_table(frame, device, describe_device(device) + ("" if device == "cpu" else "; classical methods on the " + describe_device("cpu")))
        if table:
            parts.append(table)
        throughput = throughput_table(frame, device, describe_device(device))
        if throughput:
            parts.append(throughput)
        limit = limit_table(frame, device, describe_device(device))
        if limit:
            parts.append(limit)
    if args.clock == "cpu":
        parts.append("Times are the process's CPU time (`--clock cpu`), not the wall clock.\n")
    if args.paper:
        reference = paper_table(args.paper_dir)
        if reference:
            parts.append(reference)
    markdown = "\n".join(parts)
    (out / "speed.md").write_text(markdown)
    print(markdown)
    print(f"wrote {out / 'speed.csv'}, {out / 'speed.md'}")
    return frame


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed", description=__doc__.split("\n\n")[0],
                                     epilog=USAGE, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default=None,
                        help=f"comma-separated method names (default: {','.join(default_methods())})")
    parser.add_argument("--sizes", default=",".join(map(str, DEFAULT_SIZES)),
                        help="comma-separated point counts (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=10, help="timed pairs per cell (default 10)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed pairs first (default 2)")
    parser.add_argument("--devices", default=None, help="cpu and/or cuda for the learned methods (default: cpu, plus cuda if available)")
    parser.add_argument("--checkpoint", action="append", metavar="NAME=PATH", help="trained weights of a learned method (repeatable)")
    parser.add_argument("--batch-sizes", default="1", help="pairs per forward pass of learned networks, e.g. 1,64,256 (default 1)")
    parser.add_argument("--compile", default="none", choices=("none", "default", "reduce-overhead", "max-autotune"),
                        help="torch.compile the learned networks (reduce-overhead: CUDA graphs on a GPU)")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16"), help="bf16: autocast the networks")
    parser.add_argument("--model-scale", type=float, default=1.0, help="width of untrained networks (default 1.0 = the paper's)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--max-seconds", type=float, default=None, help="stop timing a cell after this many seconds (>= 1 timed run)")
    parser.add_argument("--clock", default="wall", choices=tuple(CLOCKS),
                        help="wall clock, or the process's CPU time (all its threads; CPU only: waiting for a busy core not counted)")
    parser.add_argument("--out", default="outputs/speed", help="output folder (default outputs/speed)")
    parser.add_argument("--paper", action=argparse.BooleanOptionalAction, default=True, help="append the paper's table (default on)")
    parser.add_argument("--paper-dir", type=Path, default=None, help="folder of the paper's CSVs")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    return exit_code_of(lambda: run(args))
