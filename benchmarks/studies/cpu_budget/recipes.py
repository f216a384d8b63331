"""Accuracy per CPU-hour: OMNet training recipes compared at equal CPU cost on real data.

Each recipe trains OMNet with ``python -m src.train`` on the real-airplane carve-out protocol (TS,
PRNet manner, noise σ = 0.01, the paper's Gaussian-noise setting) for a budget of CPU time, one
torch thread, pairs generated in the training process (``num_workers=0``), validating every
``--val-every`` steps. The budget becomes a step count from a short probe of the recipe's own step
cost, so schedules that need their length (step decay at 80 %, cosine, one-cycle) know it. Every
run logs its cumulative CPU time (``src.run.callbacks.TrainingClock``, in every run's callbacks), and the report draws validation
Error(R) against CPU hours.

    python -m benchmarks.studies.cpu_budget.recipes run --root RUNS [--recipes base,width_0.5] [--budget-min 30] [--parallel 1]
    python -m benchmarks.studies.cpu_budget.recipes report --root RUNS [RUNS2 ...] --out benchmarks/studies/cpu_budget/results

``run`` is resumable: a finished recipe (``done.json``) is skipped, an interrupted one resumes from
its ``last.ckpt`` (written every few minutes). Keep ``--root`` outside the repository. The
``airplane+bathtub`` recipe trains on both real categories (the validation carve-out stays the
airplanes'): prepare the cache from both shared archives first (docs/data.md: Real ModelNet40 shapes).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd

from src.utils.errors import ConfigError, exit_code_of
from src.metrics import ERROR_R, ERROR_T, VAL_ERROR_R, VAL_ERROR_T

#: What every recipe shares: the real-airplane protocol with noise, one thread, in-process data.
COMMON = [
    "+exp=real_airplane", "sampling=ts", "partial=prnet", "data.pair.noise_sigma=0.01",
    "trainer.accelerator=cpu", "data.num_workers=0", "data.persistent_workers=false", "data.pin_memory=false",
    "data.eval_batch_size=50", "trainer.check_val_every_n_epoch=null", "trainer.log_every_n_steps=20",
    "trainer.enable_progress_bar=false", "test_after_fit=false",
    "callbacks.periodic_checkpoint.train_time_interval.minutes=5",
]

#: One factor at a time from ``base`` (width 0.25, per-iteration weights, batch 16, Adam 1e-3 with a
#: ×0.1 step at 80 % of the steps). ``{milestone}`` (80 % of the steps) and ``{warmup}`` (5 %) are
#: filled from the budget.
RECIPES: dict[str, dict] = {
    "base": {"model_scale": 0.25, "batch": 16, "overrides": ["model.lr=1e-3"]},
    "width_0.5": {"model_scale": 0.5, "batch": 16, "overrides": ["model.lr=1e-3"]},
    "shared_weights": {"model_scale": 0.25, "batch": 16, "overrides": ["model.lr=1e-3", "model.network.share_weights=true"]},
    "batch_8": {"model_scale": 0.25, "batch": 8, "overrides": ["model.lr=1e-3"]},
    "batch_32": {"model_scale": 0.25, "batch": 32, "overrides": ["model.lr=1e-3"]},
    "lr_3e-3": {"model_scale": 0.25, "batch": 16, "overrides": ["model.lr=3e-3"]},
    "cosine_warmup": {"model_scale": 0.25, "batch": 16, "overrides": ["model.lr=1e-3"],
                      "schedule": ["~model.scheduler", "+model.scheduler={{name: cosine, warmup_steps: {warmup}}}"]},
    "onecycle_3e-3": {"model_scale": 0.25, "batch": 16, "overrides": ["model.lr=3e-3"],
                      "schedule": ["~model.scheduler", "+model.scheduler={{name: onecycle}}"]},
    "airplane+bathtub": {"model_scale": 0.25, "batch": 16,
                         "overrides": ["model.lr=1e-3", "real_train_categories=[airplane,bathtub]"]},
}
#: One torch thread per run (two runs at once beat one run with two threads on two cores: benchmarks/results/
#: train_step_learned_cpu.md, "Threads"), and glibc's allocator kept from returning (then zero-filling) freed pages:
#: measured in benchmarks/results/speed_cpu_omnet.md (the "allocator setting" rows).
CPU_TRAINING_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MALLOC_MMAP_MAX_": "0",
                    "MALLOC_TRIM_THRESHOLD_": "68719476736"}
STEP_DECAY = ["model.scheduler.milestones=[{milestone}]", "model.scheduler.gamma=0.1"]


def probe_step_seconds(recipe: dict, points: int = 768, steps: int = 3) -> float:
    """CPU seconds of one training step of the recipe's network (one thread; fresh weights)."""
    import torch

    from benchmarks.speed.train_step import build_network, pair_batch

    torch.set_num_threads(1)
    overrides = [o for o in recipe["overrides"] if o.startswith("model.network.")]
    network = build_network("omnet", recipe["model_scale"], overrides).train()
    batch = pair_batch(recipe["batch"], points, torch.device("cpu"))
    optimizer = torch.optim.Adam(network.parameters(), lr=1e-4)

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        outputs = network(batch["points_src"], batch["points_ref"], batch["transform_gt"])
        network.loss(outputs, batch["transform_gt"])["loss"].backward()
        optimizer.step()

    step()  # warm-up
    start = time.process_time()
    for _ in range(steps):
        step()
    return (time.process_time() - start) / steps


def code_version() -> str:
    """The repository commit the runs train with (``+dirty`` if the tree has changes), for the report."""
    from src.utils.paths import REPO_ROOT

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(REPO_ROOT), *args], capture_output=True, text=True).stdout.strip()

    commit = git("rev-parse", "--short", "HEAD") or "unknown"
    return commit + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def recipe_command(name: str, recipe: dict, run_dir: Path, max_steps: int, val_every: int) -> list[str]:
    """The ``src.train`` command line of one recipe (resuming from ``last.ckpt`` when there is one)."""
    milestone, warmup = max(1, int(0.8 * max_steps)), max(1, int(0.05 * max_steps))
    schedule = [o.format(milestone=milestone, warmup=warmup) for o in recipe.get("schedule", STEP_DECAY)]
    command = [sys.executable, "-m", "src.train", *COMMON, f"model_scale={recipe['model_scale']}",
               f"data.batch_size={recipe['batch']}", f"trainer.max_steps={max_steps}",
               f"trainer.val_check_interval={val_every}", *recipe["overrides"], *schedule,
               f"task_name=cpu_recipe_{name}", f"hydra.run.dir={run_dir}"]
    last = run_dir / "checkpoints" / "last.ckpt"
    return command + ([f"ckpt_path={last}"] if last.is_file() else [])


def run_recipe(name: str, root: Path, budget_min: float, val_every: int) -> str:
    """Train one recipe to its budget (or resume it); returns a one-line status."""
    recipe = RECIPES[name]
    run_dir = root / name
    done = run_dir / "done.json"
    if done.is_file():
        return f"{name}: done earlier"
    run_dir.mkdir(parents=True, exist_ok=True)
    plan_file = run_dir / "plan.json"
    if plan_file.is_file():
        plan = json.loads(plan_file.read_text())
    else:
        step_s = probe_step_seconds(recipe)
        plan = {"recipe": recipe, "budget_cpu_min": budget_min, "probe_step_cpu_s": step_s,
                "max_steps": max(val_every, int(budget_min * 60 / step_s)), "code": code_version()}
        plan_file.write_text(json.dumps(plan, indent=2))
    command = recipe_command(name, recipe, run_dir, plan["max_steps"], val_every)
    code = train_logged(run_dir, command)
    if code != 0:
        return f"{name}: exit {code} (see {run_dir / 'train.log'}; run again to resume)"
    done.write_text(json.dumps({**plan, "command": " ".join(command[1:])}, indent=2))
    return f"{name}: finished {plan['max_steps']} steps"


def add_run_parser(sub: argparse._SubParsersAction, what: str, known: Sequence[str], budget: tuple[str, float, str],
                   parallel: int) -> argparse.ArgumentParser:
    """The ``run`` sub-command shared by the training studies: ``--root``, ``--<what>`` (comma-separated, of
    ``known``), the budget flag (``(flag, default, unit)``) and ``--parallel`` (default ``parallel``)."""
    flag, default, unit = budget
    run = sub.add_parser("run", help=f"train the {what} (resumable)")
    run.add_argument("--root", type=Path, required=True, help="folder of the runs (outside the repository)")
    run.add_argument(f"--{what}", default=",".join(known), help=f"comma-separated, of: {', '.join(known)}")
    run.add_argument(flag, type=float, default=default, help=f"{unit} per {what[:-1]}, one thread (default {default:g})")
    run.add_argument("--parallel", type=int, default=parallel,
                     help=f"{what} trained at once, one thread each (default {parallel})")
    return run


def run_each(names: str, known: Sequence[str], what: str, budget: tuple[str, float], parallel: int,
             run_one: Callable[[str], str]) -> None:
    """``run_one`` for each of the comma-separated ``names`` (all of ``known``), ``parallel`` at once, printing
    each status line; ConfigError for an unknown name or a budget (``(flag, value)``) that is not positive."""
    chosen = [n.strip() for n in names.split(",") if n.strip()]
    unknown = sorted(set(chosen) - set(known))
    if unknown:
        raise ConfigError(f"unknown {what} {unknown}; known: {', '.join(known)}")
    flag, value = budget
    if not math.isfinite(value) or value <= 0:
        raise ConfigError(f"{flag} must be positive, got {value}")
    with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
        for status in pool.map(run_one, chosen):
            print(status, flush=True)


def train_logged(run_dir: Path, command: list[str]) -> int:
    """Run one training command with :data:`CPU_TRAINING_ENV`, appending it and its output to
    ``run_dir/train.log`` (the command first, so the run folder says how to resume); its exit code."""
    env = {**os.environ, **CPU_TRAINING_ENV}
    with open(run_dir / "train.log", "a") as log:
        log.write(f"\n$ {' '.join(command)}\n")
        log.flush()
        return subprocess.call(command, stdout=log, stderr=subprocess.STDOUT, env=env)


def curves(roots: list[Path]) -> pd.DataFrame:
    """Validation rows of every recipe under ``roots``: recipe, code, step, cpu_hours, Error(R), Error(t).
    A recipe name found under several roots is labelled with its root's name."""
    from src.run.reporting import read_csv_logs

    run_dirs = [p for root in roots for p in sorted(root.iterdir()) if (p / "plan.json").is_file()]
    names = [p.name for p in run_dirs]
    frames = []
    for run_dir in run_dirs:
        label = run_dir.name if names.count(run_dir.name) == 1 else f"{run_dir.name} ({run_dir.parent.name})"
        logs = read_csv_logs(run_dir)
        if logs.empty or VAL_ERROR_R not in logs:
            continue
        val = logs.dropna(subset=[VAL_ERROR_R])[["step", "time/cpu_hours", VAL_ERROR_R, VAL_ERROR_T]]
        code = json.loads((run_dir / "plan.json").read_text()).get("code", "unknown")
        frames.append(val.assign(recipe=label, code=code))
    if not frames:
        where = ", ".join(map(str, roots))
        raise ConfigError(f"no recipe run with validation results under {where}: run `python -m benchmarks.studies.cpu_budget.recipes run` first")
    frame = pd.concat(frames, ignore_index=True)
    return frame.rename(columns={"time/cpu_hours": "cpu_hours", VAL_ERROR_R: ERROR_R, VAL_ERROR_T: ERROR_T})


def summary(frame: pd.DataFrame) -> pd.DataFrame:
    """Per recipe: steps and CPU hours run, the last and the best validation Error(R)/Error(t)."""
    rows = []
    for name, group in frame.groupby("recipe", sort=False):
        group = group.sort_values("step")
        best = group.loc[group[ERROR_R].idxmin()]
        rows.append({"recipe": name, "code": group["code"].iloc[0], "steps": int(group["step"].max()) + 1,
                     "CPU h": group["cpu_hours"].max(),
                     "last Error(R)": group[ERROR_R].iloc[-1], "last Error(t)": group[ERROR_T].iloc[-1],
                     "best Error(R)": best[ERROR_R], "best at CPU h": best["cpu_hours"]})
    return pd.DataFrame(rows).sort_values("last Error(R)")


def report(roots: list[Path], out: Path) -> list[Path]:
    """``cpu_recipes.csv`` (the curves), ``cpu_recipes.md`` (summary) and ``cpu_recipes.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    frame = curves(roots)
    out.mkdir(parents=True, exist_ok=True)
    frame.to_csv(out / "cpu_recipes.csv", index=False)
    table = summary(frame)
    (out / "cpu_recipes_summary.md").write_text(table.to_markdown(index=False, floatfmt=".3f") + "\n")
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, group in frame.groupby("recipe", sort=False):
        group = group.sort_values("step")
        ax.plot(group["cpu_hours"], group[ERROR_R], marker="o", markersize=2.5, label=name)
    ax.set(xlabel="CPU hours (one thread)", ylabel="validation Error(R) [deg]", yscale="log",
           title="OMNet recipes on real airplanes (TS, PRNet manner, σ = 0.01)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "cpu_recipes.png", dpi=110)
    plt.close(fig)
    return [out / "cpu_recipes.csv", out / "cpu_recipes_summary.md", out / "cpu_recipes.png"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = add_run_parser(sub, "recipes", RECIPES, ("--budget-min", 30.0, "CPU minutes"), parallel=1)
    run.add_argument("--val-every", type=int, default=100, help="steps between validations (default 100)")
    rep = sub.add_parser("report", help="curves, summary table and plot")
    rep.add_argument("--root", type=Path, required=True, nargs="+", help="one or more run folders")
    rep.add_argument("--out", type=Path, default=Path("benchmarks/studies/cpu_budget/results"))
    args = parser.parse_args(argv)

    def action() -> None:
        if args.command == "report":
            for path in report(args.root, args.out):
                print(f"wrote {path}")
            return
        run_each(args.recipes, RECIPES, "recipes", ("--budget-min", args.budget_min), args.parallel,
                 lambda n: run_recipe(n, args.root, args.budget_min, args.val_every))

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
