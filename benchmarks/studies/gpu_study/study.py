"""Several trainings at once on one GPU, each for the given seconds: OMNet beyond the CPU budget (width, batch
and learning rate, a run each) and PRNet and IDAM past the steps their CPU hour bought (do they learn given more
steps?). Real airplanes (``+exp=real_airplane``: TS, PRNet manner, clean;
selection on the 200 held-out validation pairs); the test carve-out is never evaluated there.

    python -m benchmarks.studies.gpu_study.device_data pack --out .device_data                              # here, once
    python -m benchmarks.studies.gpu_study.study run --out "$OUT" --packed .device_data --seconds 480    # on the GPU machine
    python -m benchmarks.studies.gpu_study.study run --out /tmp/study --seconds 120 --dry-run           # here: the same, tiny
    python -m benchmarks.studies.gpu_study.study collect <folder of the parts> --into RUNS/gpu_study     # here: the runs back
    python -m benchmarks.studies.gpu_study.study report RUNS/gpu_study/gpu_study --cpu-step RUN=S --test RUN=METRICS_JSON   # tables

Each run trains in phases of constant learning rate, the time split by :data:`PHASE_SHARES`; a phase after the
first starts from the weights its predecessor ended with (``init_weights``: a fresh Adam), so a recipe's ×0.1
decay comes at a fixed share of the time, not of a step count unknown before the GPU is timed. A phase ends by
SIGTERM at its deadline (``last.ckpt`` at the end of the current step: src.run.signals). A run's model is its best
checkpoint on validation over all phases (its recipe's monitor), else its last weights; it comes back in float16
with every phase's logs and config, as one tar in parts of at most ``--part-mb``.
``--rates-file`` keeps each run's measured steps per second: a later run on the same machine validates every
``rate × seconds / VALIDATIONS`` steps (:data:`RUNS` gives the intervals without it).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import subprocess
import sys
import tarfile
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd
import torch
import yaml

from src.run.checkpoint_io import read_checkpoint
from src.utils.errors import ConfigError, exit_code_of
from src.metrics import ERROR_R, ERROR_T, VAL_ERROR_R, VAL_ERROR_T

SEED = 1234
PHASE_SHARES = {1: (1.0,), 2: (0.75, 0.25)}
VALIDATIONS = 20          # validations per run, when its rate is known
GRACE_SECONDS = 30        # after SIGTERM: the current step, last.ckpt, exit
PARTS = "study.tar.part"  # the tar's parts in --out: study.tar.part000, ...


@dataclass(frozen=True)
class StudyRun:
    """One training: its overrides, one constant learning rate per phase, loader workers, validation interval."""

    name: str
    overrides: tuple[str, ...]
    lrs: tuple[float, ...]
    workers: int
    val_every: int


#: OMNet: width 0.5 vs 0.25 at batch 64 and lr 1e-3 (a run each), and the CPU recipe (omnet_cpu: width 0.25,
#: batch 16, lr 3e-3), each ×0.1 for the last quarter; PRNet and IDAM at their recipes' first learning rate.
RUNS = (
    StudyRun("omnet_w05_b64", ("model=omnet", "recipe=omnet_cpu", "model_scale=0.5", "data.batch_size=64"),
             (1e-3, 1e-4), 3, 500),
    StudyRun("omnet_w025_b64", ("model=omnet", "recipe=omnet_cpu", "model_scale=0.25", "data.batch_size=64"),
             (1e-3, 1e-4), 3, 500),
    StudyRun("omnet_w025_b16", ("model=omnet", "recipe=omnet_cpu"), (3e-3, 3e-4), 2, 1000),
    StudyRun("prnet", ("model=prnet", "model_scale=1.0"), (1e-3,), 3, 200),
    StudyRun("idam", ("model=idam", "model_scale=1.0"), (1e-4,), 2, 500),
)
COMMON = (
    "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.0", "trainer.max_steps=-1", "trainer.max_epochs=-1",
    "trainer.check_val_every_n_epoch=null", "trainer.log_every_n_steps=50", "trainer.enable_progress_bar=false",
    "test_after_fit=false", "callbacks.periodic_checkpoint.train_time_interval.minutes=2", "data.eval_batch_size=50",
    "model.scheduler=null",
)
GPU = ("+exp=real_airplane", "trainer.accelerator=gpu", "trainer.precision=32-true", "data.pin_memory=true",
       "data.persistent_workers=true")
#: The dry run: the synthetic default, tiny networks and clouds, the CPU, in-process pairs.
DRY = ("+exp=unseen_shapes", "data=synthetic", "trainer.accelerator=cpu", "data.num_workers=0",
       "data.persistent_workers=false", "data.pin_memory=false", "trainer.limit_val_batches=1")
DRY_SIZE = ("model_scale=0.0625", "data.batch_size=4")


def val_interval(run: StudyRun, seconds: float, rates: dict[str, float], forced: int | None) -> int:
    """Steps between validations: ``forced``, else :data:`VALIDATIONS` over the run at its measured rate, else
    the table's."""
    if forced:
        return forced
    if run.name in rates:
        return max(20, int(rates[run.name] * seconds / VALIDATIONS))
    return run.val_every


def train_command(run: StudyRun, phase: int, phase_dir: Path, every: int, init: Path | None,
                  dry_run: bool) -> list[str]:
    """The ``src.train`` command of one phase."""
    if dry_run:
        sized = [o for o in run.overrides if not o.startswith(tuple(s.split("=")[0] + "=" for s in DRY_SIZE))]
        overrides = [*DRY, *sized, *DRY_SIZE]
    else:
        overrides = [*GPU, f"data.num_workers={run.workers}", *run.overrides]
    return [sys.executable, "-m", "src.train", *COMMON, *overrides,
            f"model.lr={run.lrs[phase]}", f"trainer.val_check_interval={every}", f"seed={SEED + phase}",
            f"task_name=gpu_study_{run.name}", f"hydra.run.dir={phase_dir}",
            *([f"init_weights={init}"] if init else [])]


def stop_at(process: subprocess.Popen, deadline: float, grace: float = GRACE_SECONDS) -> tuple[int, bool]:
    """Wait for ``process`` until ``deadline`` (perf_counter), then SIGTERM it (and after ``grace`` seconds,
    SIGKILL its process group); returns its exit status and whether it was stopped."""
    try:
        return process.wait(timeout=max(0.0, deadline - time.perf_counter())), False
    except subprocess.TimeoutExpired:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=grace), True
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        return process.wait(), True


def run_phases(run: StudyRun, root: Path, start: float, seconds: float, every: int, dry_run: bool,
               env: dict[str, str]) -> list[dict[str, Any]]:
    """Every phase of ``run`` in turn, each until its deadline; a phase without a ``last.ckpt`` ends the run."""
    records: list[dict[str, Any]] = []
    deadline, init = start, None
    for phase, share in enumerate(PHASE_SHARES[len(run.lrs)]):
        deadline += share * seconds
        phase_dir = root / run.name / f"phase{phase}"
        phase_dir.mkdir(parents=True, exist_ok=True)
        began = time.perf_counter()
        with (phase_dir / "train.log").open("w") as log:
            process = subprocess.Popen(train_command(run, phase, phase_dir, every, init, dry_run), stdout=log,
                                       stderr=subprocess.STDOUT, env=env, start_new_session=True)
            status, stopped = stop_at(process, deadline)
        last = phase_dir / "checkpoints" / "last.ckpt"
        records.append({"phase": phase, "lr": run.lrs[phase], "exit": status, "stopped_at_deadline": stopped,
                        "seconds": round(time.perf_counter() - began, 1), "val_every": every,
                        **(trained(last) if last.is_file() else {"steps": 0})})
        if not last.is_file():
            break
        init = last
    return records


def trained(checkpoint: Path) -> dict[str, Any]:
    """Steps and training wall seconds (src.run.callbacks.TrainingClock) of a checkpoint."""
    state = read_checkpoint(checkpoint)
    clock = next((v for k, v in state.get("callbacks", {}).items() if k.startswith("TrainingClock")), {})
    wall = clock.get("wall_seconds", 0.0)
    return {"steps": int(state["global_step"]), "train_wall_s": round(wall, 1),
            "steps_per_s": round(state["global_step"] / wall, 3) if wall else None}


def best_in(phase_dir: Path) -> tuple[Path, float] | None:
    """The phase's best checkpoint by its checkpoint callback's monitor, with its score (None without one)."""
    for path in sorted((phase_dir / "checkpoints").glob("best-*.ckpt")):
        state = read_checkpoint(path)
        for key, value in state.get("callbacks", {}).items():
            if key.startswith("ModelCheckpoint") and value.get("best_model_score") is not None \
                    and Path(value.get("best_model_path", "")).name == path.name:
                return path, float(value["best_model_score"])
    return None


def select(run_dir: Path, phases: int) -> dict[str, Any]:
    """The run's model: the best validated checkpoint of all its phases under its recipe's monitor and mode,
    else the last phase's ``last.ckpt``."""
    config = yaml.safe_load((run_dir / "phase0" / "config_resolved.yaml").read_text())
    monitor, mode = config["callbacks"]["checkpoint"]["monitor"], config["callbacks"]["checkpoint"]["mode"]
    candidates = [(found, k) for k in range(phases) if (found := best_in(run_dir / f"phase{k}"))]
    if monitor and candidates:
        (path, score), phase = (min if mode == "min" else max)(candidates, key=lambda c: c[0][1])
        return {"checkpoint": str(path.relative_to(run_dir)), "phase": phase, "monitor": monitor, "score": score}
    last = run_dir / f"phase{phases - 1}" / "checkpoints" / "last.ckpt"
    return {"checkpoint": str(last.relative_to(run_dir)), "phase": phases - 1, "monitor": None, "score": None}


def export_selected(run_dir: Path, selection: dict[str, Any]) -> Path:
    """``<run>/model.ckpt``: the selected checkpoint's weights in float16 (src.eval loads it as float32)."""
    from src.models.pretrained import stored_weights

    full = read_checkpoint(run_dir / selection["checkpoint"])
    target = run_dir / "model.ckpt"
    torch.save({"state_dict": stored_weights(full["state_dict"], half=True),
                **{key: full[key] for key in ("hyper_parameters", "global_step", "pytorch-lightning_version")}}, target)
    return target


def pack_parts(root: Path, out: Path, part_bytes: int) -> list[Path]:
    """``root`` without its training checkpoints as one tar, written to ``out`` in parts of ``part_bytes``."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(root, arcname=root.name, filter=lambda info: None if "checkpoints" in Path(info.name).parts else info)
    data = buffer.getvalue()
    out.mkdir(parents=True, exist_ok=True)
    parts = []
    for k, offset in enumerate(range(0, len(data), part_bytes)):
        parts.append(out / f"{PARTS}{k:03d}")
        parts[-1].write_bytes(data[offset:offset + part_bytes])
    return parts


def collect(folder: Path, into: Path) -> Path:
    """Join the parts :func:`pack_parts` wrote and unpack them into ``into``."""
    parts = sorted(folder.glob(f"{PARTS}*"))
    if not parts:
        raise ConfigError(f"no {PARTS}* files in {folder}: give the folder the device run's files came back to")
    into.mkdir(parents=True, exist_ok=True)
    with tarfile.open(fileobj=io.BytesIO(b"".join(p.read_bytes() for p in parts)), mode="r") as tar:
        tar.extractall(into, filter="data")
    return into


def run_curve(run_dir: Path, phases: list[dict[str, Any]], batch: int) -> pd.DataFrame:
    """A run's validations over all its phases: step counted on from the phases before, pairs seen."""
    from src.run.reporting import read_csv_logs

    frames, offset = [], 0
    for phase in phases:
        logs = read_csv_logs(run_dir / f"phase{phase['phase']}")
        if VAL_ERROR_R in logs:
            validated = logs[[c for c in logs.columns if c.startswith("val/")]].notna().any(axis=1)  # NaN metrics too
            rows = logs[validated][["step", VAL_ERROR_R, VAL_ERROR_T, "val/score"]]
            frames.append(rows.assign(step=rows["step"] + 1 + offset, phase=phase["phase"]))
        offset += phase.get("steps", 0)
    curve = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=["step", VAL_ERROR_R, VAL_ERROR_T,
                                                                                      "val/score"])
    return curve.rename(columns={VAL_ERROR_R: ERROR_R, VAL_ERROR_T: ERROR_T}).assign(pairs=lambda f: f["step"] * batch)


def report(root: Path, out: Path, cpu_seconds: dict[str, float], tests: dict[str, Path],
           cpu_curves: Path | None) -> list[Path]:
    """``gpu_study_curves.csv``, ``gpu_study_summary.md`` and ``gpu_study.png`` in ``out`` from a collected study:
    each run's validations, its steps and pairs, the CPU hours its steps would take at ``cpu_seconds`` (one
    thread's measured seconds per step of the same network and batch), its test metrics (``tests``: metrics.json
    of ``src.eval`` on the selected model); the plot puts the runs (dashed, x = CPU-hour equivalent) over the
    CPU-budget curves (``cpu_curves``: benchmarks.studies.cpu_budget.report's CSV)."""
    from benchmarks.studies.cpu_budget.report import plot

    record = json.loads((root / "study.json").read_text())
    curves, rows = [], []
    for name, entry in record["runs"].items():
        config = yaml.safe_load((root / name / "phase0" / "config_resolved.yaml").read_text())
        batch, phases = config["data"]["batch_size"], entry["phases"]
        curve = run_curve(root / name, phases, batch)
        steps = sum(p.get("steps", 0) for p in phases)
        finite = curve.dropna(subset=[ERROR_R])
        best = finite.loc[finite["val/score"].idxmin()] if not finite.empty else None
        test = json.loads(tests[name].read_text())["metrics"] if name in tests else {}
        rows.append({
            "run": name, "width": config["model_scale"], "batch": batch,
            "phases (lr x s)": " + ".join(f"{p['lr']:g} x {p['seconds']:.0f}" for p in phases if p.get("steps")),
            "steps": steps, "pairs": steps * batch, "GPU train s": round(sum(p.get("train_wall_s", 0) for p in phases)),
            "CPU-h equivalent": round(steps * cpu_seconds[name] / 3600, 1) if name in cpu_seconds else None,
            "non-finite validations": int(curve[ERROR_R].isna().sum()),
            "best val Error(R) / Error(t)":
                None if best is None else f"{best[ERROR_R]:.2f} / {best[ERROR_T]:.3f} (step {best['step']:.0f})",
            "selected": None if "selected" not in entry else
                f"phase {entry['selected']['phase']}, {Path(entry['selected']['checkpoint']).name}",
            "test Error(R) / Error(t)": f"{test[ERROR_R]:.2f} / {test[ERROR_T]:.3f}" if test else None,
        })
        if name in cpu_seconds:
            curves.append(finite.assign(cpu_hours=finite["step"] * cpu_seconds[name] / 3600, method=f"{name} (GPU)"))
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "gpu_study_curves.csv", out / "gpu_study_summary.md", out / "gpu_study.png"]
    gpu = pd.concat(curves, ignore_index=True) if curves else pd.DataFrame(columns=["cpu_hours", ERROR_R, "method"])
    gpu.to_csv(paths[0], index=False)
    paths[1].write_text(pd.DataFrame(rows).to_markdown(index=False) + "\n")
    cpu = pd.read_csv(cpu_curves) if cpu_curves else pd.DataFrame(columns=gpu.columns)
    plot(pd.concat([cpu, gpu], ignore_index=True), paths[2], budget_h=1.0, dashed=set(gpu["method"]),
         xlabel="training CPU hours (one thread; GPU runs, dashed: steps x the CPU's measured s/step)", log_x=True)
    return paths


def device_facts(dry_run: bool) -> dict[str, Any]:
    """What the runs ran on: device, torch, the fp32 and TF32 ``torch.mm`` rates (the speed yardstick)."""
    from src.utils.machine_speed import MatmulReference

    if dry_run:
        return {"device": "CPU (dry run)", "torch": torch.__version__}
    facts = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__, "cpus": os.cpu_count()}
    for name, tf32 in (("mm_gflops_fp32", False), ("mm_gflops_tf32", True)):
        torch.backends.cuda.matmul.allow_tf32 = tf32
        facts[name] = round(max(MatmulReference("cuda").rate() for _ in range(3)), 1)
    return facts


def study(out: Path, seconds: float, dry_run: bool, root: Path, names: Sequence[str], rates_file: Path | None,
          val_every: int | None = None, part_bytes: int = 15 * 2**20) -> Path:
    """Every run of ``names`` at once for ``seconds``; their selected models, logs and ``study.json`` to ``out``
    as a tar in parts of ``part_bytes``."""
    if not dry_run and not torch.cuda.is_available():
        raise ConfigError("no CUDA device here: run on the GPU machine, or pass --dry-run to check the study on the CPU")
    runs = [run for run in RUNS if run.name in names]
    rates = json.loads(rates_file.read_text()) if rates_file and rates_file.is_file() else {}
    env = {**os.environ, "OMP_NUM_THREADS": "1", "TORCH_ALLOW_TF32_CUBLAS_OVERRIDE": "1", "PYTHONUNBUFFERED": "1"}
    facts = device_facts(dry_run)
    start = time.perf_counter()
    with ThreadPoolExecutor(len(runs)) as pool:
        every = {run.name: val_interval(run, seconds, rates, val_every or (2 if dry_run else None)) for run in runs}
        futures = {run.name: pool.submit(run_phases, run, root, start, seconds, every[run.name], dry_run, env)
                   for run in runs}
    record: dict[str, Any] = {"facts": facts, "seconds": seconds, "runs": {}}
    for run in runs:
        phases = futures[run.name].result()
        entry: dict[str, Any] = {"overrides": list(run.overrides), "lrs": list(run.lrs), "phases": phases}
        if phases and phases[0].get("steps"):
            entry["selected"] = select(root / run.name, len([p for p in phases if p.get("steps")]))
            export_selected(root / run.name, entry["selected"])
        record["runs"][run.name] = entry
    (root / "study.json").write_text(json.dumps(record, indent=2))
    if rates_file:
        rates_file.write_text(json.dumps({name: p[0]["steps_per_s"] for name, e in record["runs"].items()
                                          if (p := e["phases"]) and p[0].get("steps_per_s")}))
    parts = pack_parts(root, out, part_bytes)
    print(json.dumps(record, indent=1))
    print(f"wrote {len(parts)} part(s) to {out}")
    return root / "study.json"


def assignments(items: Sequence[str], flag: str, kind: Callable[[str], Any]) -> dict[str, Any]:
    """``RUN=VALUE`` command-line items as ``{RUN: kind(VALUE)}``; a malformed one is a ConfigError."""
    try:
        return {name: kind(value) for name, value in (item.split("=", 1) for item in items)}
    except ValueError:
        raise ConfigError(f"{flag} takes RUN=VALUE items (e.g. {flag} omnet_w05_b64=26.2), got {list(items)}") from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train the runs at once (on the GPU machine; --dry-run: tiny, on the CPU)")
    run.add_argument("--out", type=Path, required=True, help="where the tar's parts go")
    run.add_argument("--part-mb", type=float, default=15.0, help="the size of each part of the returned tar (default 15)")
    run.add_argument("--seconds", type=float, required=True, help="training time of every run, all phases")
    run.add_argument("--packed", type=Path, help="a benchmarks.studies.gpu_study.device_data pack folder: unpacked into the cache first")
    run.add_argument("--root", type=Path, default=Path("/tmp/gpu_study"), help="the run folders (outside --out)")
    run.add_argument("--runs", default=",".join(r.name for r in RUNS), help="comma-separated names of RUNS")
    run.add_argument("--rates-file", type=Path, help="steps per second per run: read if present, then written")
    run.add_argument("--val-every", type=int, help="steps between validations for every run (default: from the rates)")
    run.add_argument("--dry-run", action="store_true")
    back = sub.add_parser("collect", help="join the returned parts and unpack the runs")
    back.add_argument("folder", type=Path)
    back.add_argument("--into", type=Path, required=True)
    summary = sub.add_parser("report", help="curves, table and plot of a collected study")
    summary.add_argument("root", type=Path, help="the collected study folder (holding study.json)")
    summary.add_argument("--out", type=Path, default=Path("benchmarks/studies/gpu_study/results"))
    summary.add_argument("--cpu-step", action="append", default=[], metavar="RUN=SECONDS",
                         help="one thread's CPU seconds per step of the run's network and batch (benchmarks.speed.train_step)")
    summary.add_argument("--test", action="append", default=[], metavar="RUN=METRICS_JSON",
                         help="src.eval's metrics.json of the run's selected model on the test set")
    summary.add_argument("--cpu-curves", type=Path, help="benchmarks.studies.cpu_budget.report's curves CSV, drawn beside")
    args = parser.parse_args(argv)

    def action() -> None:
        if args.command == "collect":
            print(f"unpacked into {collect(args.folder, args.into)}")
            return
        if args.command == "report":
            paths = report(args.root, args.out, assignments(args.cpu_step, "--cpu-step", float),
                           assignments(args.test, "--test", Path), args.cpu_curves)
            print("\n".join(f"wrote {path}" for path in paths))
            return
        names = [n for n in args.runs.split(",") if n]
        unknown = sorted(set(names) - {r.name for r in RUNS})
        if unknown or not names:
            raise ConfigError(f"--runs: unknown {unknown or 'none given'}; choose from {', '.join(r.name for r in RUNS)}")
        if not args.seconds > 0:
            raise ConfigError(f"--seconds must be positive, got {args.seconds}")
        if args.packed:
            from benchmarks.studies.gpu_study.device_data import unpack
            from src.data.cache import default_cache_root

            unpack(args.packed, default_cache_root())
        study(args.out, args.seconds, args.dry_run, args.root, names, args.rates_file, args.val_every,
              int(args.part_mb * 2**20))

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
