"""A time-boxed trial of the paper's training on a GPU: time the step, the loader, train for the minutes left,
and project the paper's schedule.

    python -m benchmarks.speed.gpu_trial --out trial --minutes 30                   # on a GPU
    python -m benchmarks.speed.gpu_trial --out trial --minutes 30 --shard-mb 100    # weights in files of <= 100 MB
    python -m benchmarks.speed.gpu_trial --out /tmp/trial --dry-run                 # end to end on the CPU, tiny

1. **Training step** (:mod:`benchmarks.speed.train_step`): the full-width OMNet at batch 64 and 256, 1,024
   points, fp32/bf16 x eager/``torch.compile``.
2. **Loader**: training pairs per second of the real-airplane protocol (``+exp=real_airplane``, TS, PRNet
   manner) with one loader worker per CPU core.
3. **Training**: ``src.train +exp=real_airplane`` at full width with shared weights (13.4 M parameters) for the
   minutes left, ``last.ckpt`` every two minutes in ``--run-dir`` (run the same command again to continue it);
   then the best and the last weights are written to ``--out``, in files of at most ``--shard-mb`` when given
   (for transfers with a per-file limit): ``python -m benchmarks.speed.gpu_trial join <folder> <file.ckpt>``
   rebuilds a checkpoint ``src.eval`` loads.
4. **Report** (``gpu_trial.md``): the tables, the loader rate, and the projected wall time of the paper's
   schedule (260k steps of batch 64) from the measured step time.

``--dry-run`` shrinks every part (a width-1/16 network, batch 2, 64 points, the synthetic data, four
training steps, the CPU) so a test runs the whole script; its numbers mean nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
import torch

from src.run.resume import best_checkpoint, own_last_checkpoint
from src.utils.errors import CheckpointError, ConfigError, exit_code_of

PAPER_STEPS, PAPER_BATCH = 260_000, 64
SHARD_GLOB = "weights-*.pt"


@dataclass(frozen=True)
class Plan:
    """What each part runs: the real trial, or the tiny CPU dry run."""

    device: str
    model_scale: float
    batches: tuple[int, ...]
    points: int
    precisions: str
    compile_modes: str
    timed_steps: int
    warmup: int
    data: list[str]
    loader_batches: int
    train: list[str]

    @classmethod
    def for_trial(cls, dry_run: bool) -> Plan:
        if dry_run:
            return cls("cpu", 0.0625, (2,), 64, "fp32", "none", 1, 0, ["data=synthetic"], 2,
                       ["model_scale=0.0625", "data.batch_size=4", "data.eval_batch_size=8", "trainer.max_steps=4",
                        "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "trainer.accelerator=cpu",
                        "data.num_workers=0", "data.persistent_workers=false"])
        return cls("cuda", 1.0, (64, 256), 1024, "fp32,bf16", "none,default", 20, 5, ["+exp=real_airplane"], 200,
                   ["+exp=real_airplane", "model_scale=1.0", "model.network.share_weights=true", "data.batch_size=64",
                    f"data.num_workers={os.cpu_count() or 1}", "trainer.val_check_interval=500",
                    "trainer.check_val_every_n_epoch=null"])


def time_training_steps(plan: Plan, out: Path) -> pd.DataFrame:
    """``benchmarks.speed.train_step`` for each batch size; the rows of all of them."""
    from benchmarks.speed import train_step

    frames = []
    for batch in plan.batches:
        folder = out / f"train_step_b{batch}"
        code = train_step.main(["--model-scale", str(plan.model_scale), "--points", str(plan.points), "--batch", str(batch),
                                "--precisions", plan.precisions, "--compile", plan.compile_modes, "--device", plan.device,
                                "--steps", str(plan.timed_steps), "--warmup", str(plan.warmup), "--out", str(folder)])
        if code != 0:
            raise ConfigError(f"benchmarks.speed.train_step failed for batch {batch} (exit {code})")
        frames.append(pd.read_csv(folder / "train_step.csv"))
    return pd.concat(frames, ignore_index=True)


def loader_pairs_per_second(plan: Plan, batches: int) -> float:
    """Training pairs per second of the experiment's train loader, one worker per CPU core
    (:func:`benchmarks.speed.loader.measure`)."""
    from benchmarks.speed.loader import measure

    workers = 0 if plan.device == "cpu" else (os.cpu_count() or 1)
    return measure([*plan.data, *(["data.batch_size=4"] if plan.device == "cpu" else [])], batches, workers).pairs_per_s


def train(plan: Plan, run_dir: Path, seconds: float) -> int:
    """``src.train`` for at most ``seconds`` (resuming ``run_dir``'s ``last.ckpt`` if there is one)."""
    last = own_last_checkpoint(run_dir)
    command = [sys.executable, "-m", "src.train", *plan.train, "test_after_fit=false",
               "callbacks.periodic_checkpoint.train_time_interval.minutes=2", f"hydra.run.dir={run_dir}",
               *([f"ckpt_path={last}"] if last.is_file() else [])]
    try:
        return subprocess.run(command, timeout=max(1.0, seconds)).returncode
    except subprocess.TimeoutExpired:
        return 124  # the time is up: last.ckpt holds the progress


def split_weights(checkpoint: Path, folder: Path, shard_bytes: int | None = None) -> list[Path]:
    """The network weights and hyper-parameters of a ``src.train`` checkpoint as shards of at most
    ``shard_bytes`` (one shard without a limit; no optimiser state): ``weights-000.pt`` holds the
    hyper-parameters too."""
    from src.run.checkpoint_io import read_checkpoint

    full = read_checkpoint(checkpoint)
    folder.mkdir(parents=True, exist_ok=True)
    shards: list[dict] = [{}]
    size = 0
    for name, tensor in full["state_dict"].items():
        nbytes = tensor.numel() * tensor.element_size()
        if shard_bytes is not None and nbytes > shard_bytes:
            raise CheckpointError(f"{name} alone ({nbytes / 2**20:.1f} MB) exceeds the {shard_bytes / 2**20:.0f} MB shard size")
        if shard_bytes is not None and size + nbytes > shard_bytes and shards[-1]:
            shards.append({})
            size = 0
        shards[-1][name] = tensor.clone()
        size += nbytes
    paths = []
    for k, state in enumerate(shards):
        payload = {"state_dict": state, **({"hyper_parameters": full["hyper_parameters"],
                                             "global_step": full.get("global_step", 0)} if k == 0 else {})}
        paths.append(folder / f"weights-{k:03d}.pt")
        torch.save(payload, paths[-1])
    return paths


def join_weights(folder: Path, target: Path) -> Path:
    """A weights-only checkpoint (``src.eval ckpt_path=``) from the shards :func:`split_weights` wrote."""
    shards = sorted(folder.glob(SHARD_GLOB))
    if not shards:
        raise CheckpointError(f"no {SHARD_GLOB} shards in {folder}")
    parts = [torch.load(p, map_location="cpu", weights_only=False) for p in shards]
    state = {name: tensor for part in parts for name, tensor in part["state_dict"].items()}
    torch.save({"state_dict": state, "hyper_parameters": parts[0]["hyper_parameters"],
                "global_step": parts[0]["global_step"], "pytorch-lightning_version": "2"}, target)
    return target


def selected_checkpoint(run_dir: Path) -> Path | None:
    """The run's best checkpoint (:func:`src.run.resume.best_checkpoint`), else its ``last.ckpt``."""
    last = own_last_checkpoint(run_dir)
    return best_checkpoint(run_dir) or (last if last.is_file() else None)


def projection(steps: pd.DataFrame) -> str:
    """Wall time of the paper's 260k steps of batch 64 at the measured batch-64 step times."""
    rows = steps[(steps["batch"] == PAPER_BATCH) & steps["note"].fillna("").eq("")]
    if rows.empty:
        return f"- no batch-{PAPER_BATCH} step was timed: no projection"
    lines = []
    for _, row in rows.iterrows():
        hours = PAPER_STEPS * row["ms_per_step"] / 1000 / 3600
        lines.append(f"- {row['precision']}, compile={row['compile']}: {row['ms_per_step']:.1f} ms/step → "
                     f"{PAPER_STEPS:,} steps ≈ {hours:.1f} h")
    return "\n".join(lines)


def trial(out: Path, minutes: float, dry_run: bool, run_dir: Path, shard_bytes: int | None) -> Path:
    """Every part in order; returns the report's path. ``shard_bytes``: the exported files' size limit (None: one file)."""
    start = time.perf_counter()
    plan = Plan.for_trial(dry_run)
    if plan.device == "cuda" and not torch.cuda.is_available():
        raise ConfigError("no CUDA device here: run on the GPU machine, or pass --dry-run to check the script on the CPU")
    out.mkdir(parents=True, exist_ok=True)
    steps = time_training_steps(plan, out)
    rate = loader_pairs_per_second(plan, plan.loader_batches)
    left = minutes * 60 - (time.perf_counter() - start) - 60  # a minute for the export
    code = train(plan, run_dir, left) if left > 0 else None
    exported = {}
    for name, checkpoint in (("best", selected_checkpoint(run_dir)), ("last", own_last_checkpoint(run_dir))):
        if checkpoint is not None and checkpoint.is_file():
            exported[name] = [p.name for p in split_weights(checkpoint, out / f"weights_{name}", shard_bytes)]
    device = torch.cuda.get_device_name(0) if plan.device == "cuda" else "CPU (dry run)"
    report = "\n".join([
        f"# GPU trial — {device}{' (DRY RUN: tiny network, numbers mean nothing)' if dry_run else ''}", "",
        *[(out / f"train_step_b{b}" / "train_step.md").read_text() for b in plan.batches], "",
        f"**Loader**: {rate:.0f} training pairs/s ({plan.data[0]}, {os.cpu_count()} CPU cores, "
        f"{'0 workers' if dry_run else 'one worker per core'})", "",
        f"**Projected wall time of the paper's schedule** ({PAPER_STEPS:,} steps of batch {PAPER_BATCH}):",
        projection(steps), "",
        f"**Training**: {'not started (no time left)' if code is None else f'src.train exit {code} (124: stopped at the time limit)'}; "
        f"run folder {run_dir}; weights exported: {json.dumps(exported)}", "",
        f"- total {time.perf_counter() - start:.0f} s; join shards with "
        "`python -m benchmarks.speed.gpu_trial join <out>/weights_best <file>.ckpt`",
    ])
    (out / "gpu_trial.md").write_text(report + "\n")
    print(report)
    return out / "gpu_trial.md"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command")
    join = sub.add_parser("join", help="rebuild a checkpoint from the exported weight shards")
    join.add_argument("folder", type=Path)
    join.add_argument("target", type=Path)
    parser.add_argument("--out", type=Path, help="the folder of the report and the exported weights")
    parser.add_argument("--minutes", type=float, default=9.0, help="the whole trial's time, export included (default 9)")
    parser.add_argument("--dry-run", action="store_true", help="tiny, on the CPU: checks the script end to end")
    parser.add_argument("--run-dir", type=Path, default=Path("outputs/gpu_trial"),
                        help="the training's run folder (its full checkpoints; the same folder continues it)")
    parser.add_argument("--shard-mb", type=float, default=None,
                        help="write the exported weights in files of at most this many MB (default: one file)")
    args = parser.parse_args(argv)

    def action() -> None:
        if args.command == "join":
            print(f"wrote {join_weights(args.folder, args.target)}")
            return
        if args.out is None:
            raise ConfigError("--out is required (the folder the report and the weights go to)")
        if not math.isfinite(args.minutes) or args.minutes <= 0:
            raise ConfigError(f"--minutes must be positive, got {args.minutes}")
        if args.shard_mb is not None and not (math.isfinite(args.shard_mb) and args.shard_mb > 0):
            raise ConfigError(f"--shard-mb must be a positive number of MB, got {args.shard_mb}")
        shard_bytes = None if args.shard_mb is None else int(args.shard_mb * 2**20)
        trial(args.out, args.minutes, args.dry_run, args.run_dir, shard_bytes)

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
