"""The precision a run trains and evaluates in: ``trainer.precision=auto`` (the default) chooses it.

Two facts decide (:func:`choose_precision`, a pure function of them):

* **the method's verdict** (``src/run/precision_verdicts.yaml``, from the precision study,
  ``benchmarks/results/precision.md``): whether bf16-mixed leaves the network's result within the
  seed-to-seed spread of float32 (``same``) or changes it (``changes``). A network without a verdict is
  not measured. bf16 is chosen only for ``same``;
* **the device**: a GPU that supports bf16; a CPU whose bf16 matrix products are measurably faster than its
  float32 ones (:func:`probe_bf16_speedup`, a few milliseconds). CPUs with bf16 units (``amx_bf16``,
  ``avx512_bf16`` in ``/proc/cpuinfo``) are; elsewhere PyTorch emulates bf16 products, many times slower
  than float32, and the run stays in float32.

An explicit ``trainer.precision`` wins, except bf16 for a network whose verdict is ``changes``: refused in
one line unless ``force_precision=true``. The choice and its reason are printed in the run's start line
(:func:`src.run.info.start_line`).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from src.utils.errors import ConfigError

AUTO, FP32, BF16 = "auto", "32-true", "bf16-mixed"
#: Lightning's names of the bf16 precisions (the verdicts are about these).
BF16_NAMES = ("bf16-mixed", "bf16-true", "bf16")
#: ``/proc/cpuinfo`` flags of bf16 matrix units: Intel AMX, AVX-512 BF16 (Intel Cooper Lake+, AMD Zen 4+).
BF16_FLAGS = ("amx_bf16", "avx512_bf16")
#: bf16 is taken on a CPU only when its probed matrix products are at least this much faster than float32
#: (a mixed-precision step gains less than its products).
MIN_BF16_SPEEDUP = 1.5
VERDICTS_FILE = Path(__file__).with_name("precision_verdicts.yaml")
VERDICTS = ("same", "changes")


@dataclass(frozen=True)
class Verdict:
    """The precision study's finding for one network: bf16-mixed ``same`` as float32 or ``changes`` its result."""

    bf16: str
    evidence: str

    def __post_init__(self) -> None:
        if self.bf16 not in VERDICTS:
            raise ValueError(f"precision verdict bf16={self.bf16!r}: must be one of {', '.join(VERDICTS)}")


@dataclass(frozen=True)
class Device:
    """What the run's device offers. ``bf16_speedup``: the CPU's bf16 over float32 matrix-product rate (None:
    not probed); ``bf16_flags``: the CPU's bf16 flags found; ``gpu_bf16``: a GPU that supports bf16."""

    kind: str
    bf16_flags: tuple[str, ...] = ()
    bf16_speedup: float | None = None
    gpu_bf16: bool = False


@dataclass(frozen=True)
class PrecisionChoice:
    precision: str
    reason: str


@functools.cache
def load_verdicts(path: Path = VERDICTS_FILE) -> dict[str, Verdict]:
    """Network ``_target_`` -> its verdict."""
    raw = yaml.safe_load(path.read_text()) or {}
    return {str(target): Verdict(**fields) for target, fields in raw.items()}


def cpu_flags(cpuinfo: str) -> frozenset[str]:
    """The flags of the first processor in ``/proc/cpuinfo``'s text (empty if it has none, e.g. not Linux x86)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return frozenset(value.split())
    return frozenset()


def read_cpu_flags(path: Path = Path("/proc/cpuinfo")) -> frozenset[str]:
    try:
        return cpu_flags(path.read_text())
    except OSError:
        return frozenset()


def probe_bf16_speedup(size: int = 256, repeats: int = 3) -> float:
    """The rate of a bf16 ``torch.mm`` of ``size``³ over a float32 one on the CPU (best of ``repeats`` each after a
    warm-up; bf16 stops after one timed product that is already slower than float32: emulated kernels take ~1 s)."""
    import torch

    a = torch.randn(size, size)
    b = torch.randn(size, size)

    def best(x: Any, y: Any, give_up_above: float = math.inf) -> float:
        torch.mm(x, y)  # warm-up
        times: list[float] = []
        for _ in range(repeats):
            start = time.perf_counter()
            torch.mm(x, y)
            times.append(time.perf_counter() - start)
            if times[-1] > give_up_above:
                break
        return max(min(times), 1e-9)

    fp32 = best(a, b)
    return fp32 / best(a.bfloat16(), b.bfloat16(), give_up_above=fp32)


def _name(target: str) -> str:
    return target.rsplit(".", 1)[-1]


def _bf16_on(device: Device) -> tuple[bool, str]:
    """Whether bf16 pays on ``device``, and why."""
    if device.kind == "cuda":
        return (True, "the GPU supports bf16") if device.gpu_bf16 else (False, "the GPU has no bf16 support")
    if device.kind != "cpu":
        return False, f"bf16 is not chosen automatically on {device.kind}"
    flags = f"bf16 units: {', '.join(device.bf16_flags)}" if device.bf16_flags else f"no bf16 units ({'/'.join(BF16_FLAGS)})"
    if device.bf16_speedup is None:
        return False, f"bf16 speed on this CPU not measured; {flags}"
    speed = f"bf16 matrix products {device.bf16_speedup:.2g}x the float32 rate on this CPU; {flags}"
    if device.bf16_speedup >= MIN_BF16_SPEEDUP:
        return True, speed
    return False, f"{speed}: bf16 is emulated and slower"


def choose_precision(requested: str, target: str, verdicts: dict[str, Verdict], device: Device,
                     force: bool = False) -> PrecisionChoice:
    """The precision of a run of the network ``target`` (its ``_target_``) asked for ``requested``
    (``trainer.precision``); ConfigError for bf16 that the verdict refuses (unless ``force``)."""
    verdict = verdicts.get(target)
    network = _name(target)
    if requested != AUTO:
        notes = []
        if requested in BF16_NAMES:
            if verdict is not None and verdict.bf16 == "changes":
                if not force:
                    raise ConfigError(
                        f"trainer.precision={requested}: bf16 changes {network}'s result ({verdict.evidence}); "
                        f"use trainer.precision=32-true (or auto), or force_precision=true to train in it anyway")
                notes.append(f"forced: bf16 changes {network}'s result ({verdict.evidence})")
            elif verdict is None:
                notes.append(f"bf16's effect on {network}'s result is not measured")
            fast, why = _bf16_on(device)
            if not fast and device.kind == "cpu":
                notes.append(why)
        return PrecisionChoice(requested, "; ".join(["trainer.precision given", *notes]))
    if verdict is None:
        return PrecisionChoice(FP32, f"bf16's effect on {network}'s result is not measured")
    if verdict.bf16 == "changes":
        return PrecisionChoice(FP32, f"bf16 changes {network}'s result ({verdict.evidence})")
    fast, why = _bf16_on(device)
    if fast:
        return PrecisionChoice(BF16, f"{why}; bf16 leaves {network}'s result unchanged ({verdict.evidence})")
    return PrecisionChoice(FP32, why)


def detect_device(kind: str, probe: bool) -> Device:
    """The facts of :class:`Device` on this machine (``probe``: measure the CPU's bf16 speed)."""
    import torch

    if kind == "cuda":
        return Device("cuda", gpu_bf16=torch.cuda.is_bf16_supported())
    if kind != "cpu":
        return Device(kind)
    flags = tuple(f for f in BF16_FLAGS if f in read_cpu_flags())
    return Device("cpu", flags, probe_bf16_speedup() if probe else None)


def device_kind(accelerator: str) -> str:
    """The device type Lightning picks for ``trainer.accelerator``."""
    import torch

    if accelerator in ("auto", "gpu", "cuda"):
        return "cuda" if torch.cuda.is_available() else ("cpu" if accelerator == "auto" else "cuda")
    return str(accelerator)


def settle_precision(cfg: Any) -> PrecisionChoice:
    """The precision of the run configured by ``cfg`` (``trainer.precision``, ``trainer.accelerator``,
    ``model.network._target_``, ``force_precision``), written into ``cfg.trainer.precision`` (the run's
    recorded config names the precision it ran in)."""
    choice = run_precision(cfg)
    cfg.trainer.precision = choice.precision
    return choice


def run_precision(cfg: Any) -> PrecisionChoice:
    """:func:`choose_precision` for the run configured by ``cfg`` on this machine."""
    requested = str(cfg.trainer.get("precision", AUTO))
    target = str(cfg.model.network._target_)
    verdicts = load_verdicts()
    kind = device_kind(str(cfg.trainer.get("accelerator", "auto")))
    wants_speed = requested in BF16_NAMES or (requested == AUTO and getattr(verdicts.get(target), "bf16", "") == "same")
    return choose_precision(requested, target, verdicts, detect_device(kind, probe=wants_speed and kind == "cpu"),
                            bool(cfg.get("force_precision", False)))
