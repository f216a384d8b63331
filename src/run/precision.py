"""The precision a run trains and evaluates in.

**Training** (``trainer.precision=auto``, the default) takes bf16-mixed only where the verdict table
(``src/run/precision_verdicts.yaml``, rows written by ``benchmarks/studies/precision/time_to_accuracy.py``) has a
row for the method (its ``model.network._target_``) on this device kind (:func:`cpu_kind`: vendor and bf16 units)
whose verdict is ``bf16`` (:func:`bf16_verdict`: from the same seeds, bf16-mixed reached the validation target in
less CPU time than float32, and its final error lies within float32's seed spread). Anything else trains in
float32, and the start line (:func:`src.run.info.start_line`) names the verdict used and where it was measured, or
says that there is none (``no measured verdict for OMNet on avx2-no-bf16: fp32``). A CPU whose row says bf16 but
whose bf16 matrix products are not measurably faster than float32 here (a PyTorch build without the units' kernels:
:func:`probe_bf16_speedup`) stays in float32.

An explicit ``trainer.precision`` wins, except bf16 for a method whose row on this device kind puts bf16's final
error outside float32's seed spread: refused in one line unless ``force_precision=true``.

**Evaluation** of a checkpoint (the test at the end of ``src.train``, ``src.eval``) runs in float32 unless
``src.eval`` is given a ``trainer.precision`` (:func:`settle_precision` with ``evaluation``, :func:`switch_to_fp32`):
the numbers of a checkpoint are those of its weights, whatever precision trained them (recorded beside them).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from src.utils.errors import ConfigError

AUTO, FP32, BF16 = "auto", "32-true", "bf16-mixed"
#: Lightning's names of the bf16 precisions.
BF16_NAMES = ("bf16-mixed", "bf16-true", "bf16")
#: A verdict row's finding: train the method in bf16-mixed or in float32 on that device kind.
VERDICTS = ("bf16", "fp32")
#: Seeds a verdict row needs: the spread of fewer says nothing.
MIN_SEEDS = 3
#: ``vendor_id`` of ``/proc/cpuinfo`` -> the vendor's name in a CPU kind (ARM cores report no vendor_id).
VENDORS = {"GenuineIntel": "intel", "AuthenticAMD": "amd"}
#: ``/proc/cpuinfo`` flags of bf16 matrix units, fastest first -> their name in a CPU kind: Intel AMX, AVX-512 BF16
#: (Intel Cooper Lake+, AMD Zen 4+), Arm's BF16 extension.
BF16_UNITS = {"amx_bf16": "amx", "avx512_bf16": "avx512bf16", "bf16": "bf16"}
#: The kinds of CPUs without bf16 units (PyTorch emulates bf16 products there, many times slower than float32).
NO_BF16_KINDS = ("avx2-no-bf16", "other-no-bf16")
GPU_KINDS = ("gpu-bf16", "gpu-no-bf16")
#: Every device kind :func:`cpu_kind` and :func:`detect_device` name: the keys of the verdict table.
DEVICE_KINDS = frozenset({f"{vendor}-{unit}" for vendor in (*VENDORS.values(), "arm", "other")
                          for unit in BF16_UNITS.values()} | {*NO_BF16_KINDS, *GPU_KINDS})
#: bf16 is taken on a CPU whose verdict says bf16 only when its probed bf16 matrix products are at least this much
#: faster than float32 here (a mixed-precision step gains less than its products).
MIN_BF16_SPEEDUP = 1.5
VERDICTS_FILE = Path(__file__).with_name("precision_verdicts.yaml")
TABLE = "src/run/precision_verdicts.yaml"
EVALUATED_IN_FP32 = "a checkpoint is evaluated in float32 unless trainer.precision is given"


@dataclass(frozen=True)
class Spread:
    """A validation Error(R) over seeds, in degrees: mean and range."""

    mean: float
    min: float
    max: float

    def holds(self, value: float) -> bool:
        return self.min <= value <= self.max

    def __str__(self) -> str:
        return f"{self.mean:.1f} ({self.min:.1f}-{self.max:.1f}) deg"


@dataclass(frozen=True)
class Outcome:
    """One precision's runs in a verdict row: how many seeds reached the target, their mean steps and CPU-seconds
    to it (None unless every seed reached it) and their final validation Error(R)."""

    reached: int
    steps_to_target: float | None
    cpu_s_to_target: float | None
    final_deg: Spread


def bf16_verdict(time_to_target_speedup: float | None, fp32: Spread, bf16: Spread) -> str:
    """``bf16`` where bf16-mixed reached the target in less CPU time (``time_to_target_speedup``: float32's CPU
    time to the target over bf16's, None unless every seed of both reached it) and its final mean error lies within
    float32's seed range, else ``fp32``."""
    faster = time_to_target_speedup is not None and time_to_target_speedup > 1.0
    return "bf16" if faster and fp32.holds(bf16.mean) else "fp32"


@dataclass(frozen=True)
class Verdict:
    """One row of the verdict table: float32 against bf16-mixed for a method on a device kind, from the same seeds
    trained to a validation target (``benchmarks/studies/precision/time_to_accuracy.py`` writes rows)."""

    method: str
    cpu_kind: str
    cpu: str
    setup: str
    target_deg: float
    seeds: tuple[int, ...]
    step_speedup: float
    time_to_target_speedup: float | None
    fp32: Outcome
    bf16: Outcome
    command: str
    verdict: str

    def __post_init__(self) -> None:
        where = f"precision verdict for {self.method} on {self.cpu_kind}"
        if self.cpu_kind not in DEVICE_KINDS:
            raise ValueError(f"{where}: unknown device kind (one of {', '.join(sorted(DEVICE_KINDS))})")
        if len(set(self.seeds)) < MIN_SEEDS:
            raise ValueError(f"{where}: {len(set(self.seeds))} seeds, at least {MIN_SEEDS} needed")
        expected = bf16_verdict(self.time_to_target_speedup, self.fp32.final_deg, self.bf16.final_deg)
        if self.verdict != expected:
            raise ValueError(f"{where}: verdict {self.verdict!r}, but its numbers give {expected!r}")

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> Verdict:
        """A row as the table stores it (nested mappings, lists)."""
        fields = dict(record)
        for name in VERDICTS:
            outcome = dict(fields[name])
            fields[name] = Outcome(**{**outcome, "final_deg": Spread(**outcome["final_deg"])})
        return cls(**{**fields, "seeds": tuple(fields["seeds"])})

    def record(self) -> dict[str, Any]:
        """The row as the table stores it (:meth:`from_record` reads it back)."""
        return {**asdict(self), "seeds": list(self.seeds)}

    @property
    def changes_result(self) -> bool:
        """bf16's final mean error lies outside float32's seed range."""
        return not self.fp32.final_deg.holds(self.bf16.final_deg.mean)

    def describe(self) -> str:
        """What was measured, and where: one clause for a start line."""
        n = len(self.seeds)
        if self.time_to_target_speedup is None:
            speed = (f"not every seed reached {self.target_deg:g} deg (fp32 {self.fp32.reached}/{n}, bf16 "
                     f"{self.bf16.reached}/{n})")
        else:
            speed = f"bf16 reached {self.target_deg:g} deg {self.time_to_target_speedup:.2g}x as fast in CPU time"
        return (f"{speed}, steps {self.step_speedup:.2g}x as fast; final Error(R) bf16 {self.bf16.final_deg}, fp32 "
                f"{self.fp32.final_deg}, {n} seeds; measured on {self.cpu}")


@dataclass(frozen=True)
class Device:
    """What the run's device is: its type (``cpu``, ``cuda``, ...), its kind (the verdict table's key) and, on a CPU,
    the rate of its bf16 over float32 matrix products (None: not probed)."""

    type: str
    kind: str
    bf16_speedup: float | None = None


@dataclass(frozen=True)
class PrecisionChoice:
    precision: str
    reason: str


@functools.cache
def load_verdicts(path: Path = VERDICTS_FILE) -> dict[tuple[str, str], Verdict]:
    """(network ``_target_``, device kind) -> its verdict row."""
    verdicts: dict[tuple[str, str], Verdict] = {}
    for record in yaml.safe_load(path.read_text()) or []:
        verdict = Verdict.from_record(record)
        key = (verdict.method, verdict.cpu_kind)
        if key in verdicts:
            raise ValueError(f"{path.name}: two verdicts for {verdict.method} on {verdict.cpu_kind}")
        verdicts[key] = verdict
    return verdicts


def cpu_flags(cpuinfo: str) -> frozenset[str]:
    """The flags of the first processor in ``/proc/cpuinfo``'s text (empty if it has none, e.g. not Linux)."""
    return frozenset(_field(cpuinfo, ("flags", "Features")).split())


def _field(cpuinfo: str, keys: tuple[str, ...]) -> str:
    """The first processor's value of the first of ``keys`` found in ``/proc/cpuinfo``'s text ('' if none)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in keys:
            return value.strip()
    return ""


def cpu_kind(cpuinfo: str) -> str:
    """The verdict table's name of the CPU that ``/proc/cpuinfo``'s text describes: ``<vendor>-<bf16 unit>``
    (``intel-amx``, ``amd-avx512bf16``, ``arm-bf16``; its fastest unit) where it has bf16 units, else
    ``avx2-no-bf16`` or ``other-no-bf16``."""
    flags = cpu_flags(cpuinfo)
    vendor = VENDORS.get(_field(cpuinfo, ("vendor_id",)), "arm" if _field(cpuinfo, ("Features",)) else "other")
    unit = next((name for flag, name in BF16_UNITS.items() if flag in flags), None)
    if unit is not None:
        return f"{vendor}-{unit}"
    return NO_BF16_KINDS[0] if "avx2" in flags else NO_BF16_KINDS[1]


def cpu_model(cpuinfo: str) -> str:
    """The CPU's model name in ``/proc/cpuinfo``'s text (``unknown CPU`` if it names none)."""
    return _field(cpuinfo, ("model name", "Model name")) or "unknown CPU"


def read_cpuinfo(path: Path = Path("/proc/cpuinfo")) -> str:
    try:
        return path.read_text()
    except OSError:
        return ""


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


def _emulated(device: Device) -> str | None:
    """Why bf16 does not pay on ``device`` (a CPU whose probed bf16 products are not fast), else None."""
    if device.type != "cpu" or device.bf16_speedup is None or device.bf16_speedup >= MIN_BF16_SPEEDUP:
        return None
    return f"bf16 matrix products run {device.bf16_speedup:.2g}x the float32 rate on this CPU ({device.kind})"


def choose_precision(requested: str, target: str, verdicts: dict[tuple[str, str], Verdict], device: Device,
                     force: bool = False) -> PrecisionChoice:
    """The training precision of the network ``target`` (its ``_target_``) asked for ``requested``
    (``trainer.precision``) on ``device``; ConfigError for bf16 that the device kind's verdict refuses (unless
    ``force``)."""
    verdict = verdicts.get((target, device.kind))
    network = _name(target)
    unmeasured = f"no measured verdict for {network} on {device.kind}"
    used = f"verdict for {network} on {device.kind} ({TABLE})"
    if requested != AUTO:
        notes = []
        if requested in BF16_NAMES:
            if verdict is not None and verdict.changes_result:
                moved = f"bf16 moves {network}'s final error outside float32's seed spread on {device.kind} ({TABLE})"
                if not force:
                    raise ConfigError(f"trainer.precision={requested}: {moved} ({verdict.describe()}); use "
                                      "trainer.precision=32-true (or auto), or force_precision=true to train in it anyway")
                notes.append(f"forced: {moved} ({verdict.describe()})")
            elif verdict is not None:
                notes.append(f"{used}: {verdict.verdict} ({verdict.describe()})")
            else:
                notes.append(unmeasured)
            notes += [why for why in [_emulated(device)] if why]
        return PrecisionChoice(requested, "; ".join(["trainer.precision given", *notes]))
    if verdict is None:
        return PrecisionChoice(FP32, f"{unmeasured}: fp32")
    used = f"{used}: {verdict.verdict} ({verdict.describe()})"
    if verdict.verdict == "fp32":
        return PrecisionChoice(FP32, used)
    emulated = _emulated(device)
    if emulated:
        return PrecisionChoice(FP32, f"{used}; but {emulated}: fp32")
    return PrecisionChoice(BF16, used)


def detect_device(accelerator_type: str) -> Device:
    """This machine's :class:`Device` of ``accelerator_type`` (``cpu``, ``cuda``, ...; unprobed)."""
    import torch

    if accelerator_type == "cuda":
        return Device("cuda", GPU_KINDS[0] if torch.cuda.is_bf16_supported() else GPU_KINDS[1])
    if accelerator_type != "cpu":
        return Device(accelerator_type, accelerator_type)
    return Device("cpu", cpu_kind(read_cpuinfo()))


def device_type(accelerator: str) -> str:
    """The device type Lightning picks for ``trainer.accelerator``."""
    import torch

    if accelerator in ("auto", "gpu", "cuda"):
        return "cuda" if torch.cuda.is_available() else ("cpu" if accelerator == "auto" else "cuda")
    return str(accelerator)


def settle_precision(cfg: Any, evaluation: bool = False) -> PrecisionChoice:
    """The precision of the run configured by ``cfg`` (``trainer.precision``, ``trainer.accelerator``,
    ``model.network._target_``, ``force_precision``), written into ``cfg.trainer.precision`` (the run's recorded
    config names the precision it ran in). ``evaluation``: a checkpoint's evaluation, float32 unless
    ``trainer.precision`` names one."""
    if evaluation and str(cfg.trainer.get("precision", AUTO)) == AUTO:
        choice = PrecisionChoice(FP32, EVALUATED_IN_FP32)
    else:
        choice = run_precision(cfg)
    cfg.trainer.precision = choice.precision
    return choice


def run_precision(cfg: Any) -> PrecisionChoice:
    """:func:`choose_precision` for the run configured by ``cfg`` on this machine (the CPU's bf16 speed probed only
    where bf16 is asked for or its verdict says bf16)."""
    requested = str(cfg.trainer.get("precision", AUTO))
    target = str(cfg.model.network._target_)
    verdicts = load_verdicts()
    device = detect_device(device_type(str(cfg.trainer.get("accelerator", "auto"))))
    verdict = verdicts.get((target, device.kind))
    bf16_candidate = requested in BF16_NAMES or (requested == AUTO and getattr(verdict, "verdict", "") == "bf16")
    if device.type == "cpu" and bf16_candidate:
        device = replace(device, bf16_speedup=probe_bf16_speedup())
    return choose_precision(requested, target, verdicts, device, bool(cfg.get("force_precision", False)))


def switch_to_fp32(trainer: Any, module: Any) -> None:
    """Switch ``trainer`` (a Lightning Trainer that trained ``module`` in a lower precision: bf16, fp16) to float32
    for its test: the test of a checkpoint measures its weights, not the training precision (its run records that).
    A float32 or float64 trainer is left as it is."""
    if trainer.precision in (FP32, "64-true"):
        return
    from lightning.pytorch.plugins.precision import Precision

    trainer.strategy.precision_plugin = Precision()
    module.float()  # bf16-true trains the module's own weights in bf16
    trainer.precision_choice = PrecisionChoice(FP32, EVALUATED_IN_FP32)

