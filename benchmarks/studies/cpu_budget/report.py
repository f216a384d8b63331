"""The equal-budget study's report: validation curves against CPU hours, the table, the plot.

Reads the run folders of ``python -m benchmarks.studies.cpu_budget.budget run --root RUNS`` (each method's ``plan.json``,
its stages' CSV logs and test ``metrics.json``); a stage that precedes the method's registration stage
(PointNetLK's classifier) shifts its curve by the CPU hours it took.

    python -m benchmarks.studies.cpu_budget.report --root benchmarks/studies/cpu_budget/results/runs --out benchmarks/studies/cpu_budget/results
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from collections.abc import Collection

import pandas as pd

from benchmarks.studies.cpu_budget.budget import Stage, logged_cpu_hours, run_folders, steps_trained
from src.utils.errors import ConfigError, exit_code_of
from src.run.reporting import read_csv_logs
from src.metrics import ERROR_R, ERROR_T, VAL_ERROR_R, VAL_ERROR_T

#: The process's torch.mm rate, logged at each validation (src.run.callbacks.TrainingClock): what a CPU hour bought.
MM_RATE = "time/mm_gflops"
CURVE_COLUMNS = {"time/cpu_hours": "cpu_hours", VAL_ERROR_R: ERROR_R, VAL_ERROR_T: ERROR_T}


def method_curve(method_dir: Path) -> tuple[dict, pd.DataFrame]:
    """(plan, validation rows of the registration stage: step, cpu_hours (all stages), Error(R), Error(t))."""
    plan = json.loads((method_dir / "plan.json").read_text())
    offset, curve = 0.0, pd.DataFrame(columns=["step", *CURVE_COLUMNS.values()])
    for stage in (Stage(**s) for s in plan["stages"]):
        logs = read_csv_logs(method_dir / stage.name)
        if logs.empty:
            break
        if VAL_ERROR_R in logs:
            rows = logs.dropna(subset=[VAL_ERROR_R])[["step", *CURVE_COLUMNS]].rename(columns=CURVE_COLUMNS)
            curve = rows.assign(cpu_hours=rows["cpu_hours"] + offset)
        offset += logged_cpu_hours(logs)
    return plan, curve.assign(method=method_dir.name)


def _test_metrics(run_dir: Path) -> dict[str, float]:
    path = run_dir / "metrics.json"
    return json.loads(path.read_text())["metrics"] if path.is_file() else {}


def summary_row(method_dir: Path, plan: dict, curve: pd.DataFrame) -> dict:
    """One row of the table: what was trained, what it cost, where validation and test ended."""
    stages = [Stage(**s) for s in plan["stages"]]
    last = stages[-1]
    logs = [read_csv_logs(method_dir / s.name) for s in stages]
    steps = [steps_trained(method_dir / s.name, frame) for s, frame in zip(stages, logs)]
    row = {"method": method_dir.name, "width": plan["width"], "batch": last.batch, "steps": steps[-1],
           "planned steps": last.max_steps, "pairs seen": steps[-1] * last.batch,
           "CPU h": sum(logged_cpu_hours(frame) for frame in logs if not frame.empty)}
    rates = [value for frame in logs if MM_RATE in frame for value in frame[MM_RATE].dropna()]
    row["mm GFLOP/s"] = float(pd.Series(rates).median()) if rates else None  # the machine's speed during the run
    if len(stages) > 1:
        row["steps"] = " + ".join(str(n) for n in steps)
        row["pairs seen"] = sum(n * s.batch for n, s in zip(steps, stages))
    if not curve.empty:
        best = curve.loc[curve[ERROR_R].idxmin()]
        row.update({"last val Error(R)": curve[ERROR_R].iloc[-1], "last val Error(t)": curve[ERROR_T].iloc[-1],
                    "best val Error(R)": best[ERROR_R], "best val Error(t)": best[ERROR_T]})
    test = _test_metrics(method_dir / last.name)
    row.update({"test Error(R)": test.get(ERROR_R), "test Error(t)": test.get(ERROR_T),
                "done": (method_dir / last.name / "done.json").is_file()})
    return row


def collect(root: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(curves of every method under ``root``, the summary table), in the grid's method order."""
    dirs = [root / name for name in run_folders(root)]
    if not dirs:
        raise ConfigError(f"no method run under {root}: run `python -m benchmarks.studies.cpu_budget.budget run --root {root}` first")
    curves, rows = [], []
    for method_dir in dirs:
        plan, curve = method_curve(method_dir)
        curves.append(curve)
        rows.append(summary_row(method_dir, plan, curve))
    return pd.concat(curves, ignore_index=True), pd.DataFrame(rows)


def plot(curves: pd.DataFrame, out: Path, budget_h: float, dashed: Collection[str] = (),
         xlabel: str = "training CPU hours (one thread)", log_x: bool = False) -> None:
    """Validation Error(R) against CPU hours, one line per method (``dashed``: those methods' lines), log y (and
    log x with ``log_x``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    many = curves["method"].nunique() > 10  # beyond the default ten colours: twenty, the legend beside the axes
    fig, ax = plt.subplots(figsize=(10.5, 5.2) if many else (7.5, 4.8))
    if many:
        ax.set_prop_cycle(color=plt.cm.tab20.colors)
    for method, group in curves.groupby("method", sort=False):
        ax.plot(group["cpu_hours"], group[ERROR_R], marker="o", markersize=2.5, label=method,
                linestyle="--" if method in dashed else "-")
    ax.axvline(budget_h, color="grey", linestyle=":", linewidth=1)
    ax.set(xlabel=xlabel, ylabel="validation Error(R) [deg], lower is better", yscale="log",
           title="Learned methods on real airplanes (TS, PRNet manner, clean)", xscale="log" if log_x else "linear")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, **({"loc": "upper left", "bbox_to_anchor": (1.01, 1.0)} if many else {"ncol": 2}))
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def report(root: Path, out: Path) -> list[Path]:
    """``cpu_budget_curves.csv``, ``cpu_budget_summary.md`` and ``cpu_budget.png`` in ``out``."""
    curves, table = collect(root)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "cpu_budget_curves.csv", out / "cpu_budget_summary.md", out / "cpu_budget.png"]
    curves.to_csv(paths[0], index=False)
    paths[1].write_text(table.to_markdown(index=False, floatfmt=".3f") + "\n")
    budget_h = json.loads((root / table["method"].iloc[0] / "plan.json").read_text())["budget_cpu_h"]
    plot(curves, paths[2], budget_h)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.cpu_budget.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="runs of benchmarks.studies.cpu_budget.budget, or their archive")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/studies/cpu_budget/results"))
    args = parser.parse_args(argv)
    return exit_code_of(lambda: print("\n".join(f"wrote {path}" for path in report(args.root, args.out))))


if __name__ == "__main__":
    sys.exit(main())
