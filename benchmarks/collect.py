"""Collect a Hydra multirun into one tidy table: one row per job × metric, plus a wide view.

    python -m benchmarks.collect multirun/sweep_noise/2025-01-01_12-00-00
    python -m benchmarks.collect multirun/sweep_ablation/* multirun/sweep_lambda/* --out results/table3

Every job directory (``<sweep dir>/<job num>/``) is read: ``.hydra/overrides.yaml`` (what the job
changed), ``config_resolved.yaml`` (everything else), ``metrics.json`` (test metrics) and
``failure.json`` (written by a job that raised, see ``on_failure`` in src/train.py). A job with
neither metrics nor a failure record was killed (timeout, out of memory, segfault), is still
running, or ran with ``test_after_fit=false``; it is reported as ``missing``. A job that failed
before writing ``config_resolved.yaml`` (e.g. on an invalid value) is described by its overrides
(``.hydra/overrides.yaml``, else the ones ``failure.json`` records). With the sweep's
``multirun.yaml`` the number of jobs the sweep should have produced is checked as well.

Columns of the tidy frame (``results.parquet`` / ``results.csv``): ``sweep``, ``job``,
``method`` (the ``variant`` label if the config has one, e.g. ``B+M``, else the display name of the
network's method in :mod:`baselines.methods`, else the network class),
``network``, ``experiment`` (named by its data: ``unseen_shapes``, ``unseen_categories``, with
``_noise`` appended when σ > 0; other experiments keep their task name), ``dataset``,
``sampling``, ``partial``, ``noise_sigma``, ``overlap_ratio``, ``num_iters``,
``trans_loss_weight``, ``variant``, ``task``, ``seed``, then one column per swept override key
(e.g. ``data.pair.noise_sigma``, ``model/ablation``), then ``metric``, ``value``, ``run_dir``.
``results_wide.*`` has one row per job and one column per metric; ``jobs.csv`` one row per job
with its ``status`` (ok / failed / missing) and ``reason``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml
from omegaconf import DictConfig, OmegaConf

from baselines.methods import method_of_network
from src.metrics import SUMMARY_METRICS

MARKERS = (".hydra/overrides.yaml", "config_resolved.yaml", "metrics.json", "failure.json")
STANDARD_COLUMNS: dict[str, str] = {
    "dataset": "data.dataset",
    "sampling": "sampling",
    "partial": "partial",
    "noise_sigma": "data.pair.noise_sigma",
    "overlap_ratio": "data.pair.overlap_ratio",
    "num_iters": "model.network.num_iters",
    "trans_loss_weight": "model.network.trans_loss_weight",
    "variant": "variant",
    "task": "task_name",
    "seed": "seed",
}
LEADING = ["sweep", "job", "method", "network", "experiment", *STANDARD_COLUMNS]


@dataclass
class Collected:
    """``tidy``: job × metric rows of the jobs with metrics; ``wide``: one row per such job;
    ``jobs``: every job found (status ok / failed / missing, reason); ``swept``: the override keys
    that differ between jobs; ``expected``: jobs the sweeps should have made (None if unknown)."""

    tidy: pd.DataFrame
    wide: pd.DataFrame
    jobs: pd.DataFrame
    swept: list[str] = field(default_factory=list)
    expected: int | None = None
    roots: list[Path] = field(default_factory=list)

    @property
    def failures(self) -> pd.DataFrame:
        return self.jobs[self.jobs["status"] != "ok"]


# --- reading one job ---------------------------------------------------------------------------


def find_job_dirs(root: Path) -> list[Path]:
    """Directories under (or equal to) ``root`` holding any of a job's files."""
    found: set[Path] = set()
    for marker in MARKERS:
        depth = marker.count("/") + 1
        for path in root.rglob(Path(marker).name):
            if path.as_posix().endswith(marker):
                found.add(path.parents[depth - 1])
    return sorted(found, key=_job_sort_key)


def _job_sort_key(path: Path) -> tuple:
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in path.parts)


def parse_override(text: str) -> tuple[str, str]:
    """``+model/ablation=B`` -> (``model/ablation``, ``B``); ``~key`` -> (``key``, ``<deleted>``)."""
    if text.startswith("~"):
        return text.lstrip("~").split("=", 1)[0], "<deleted>"
    key, _, value = text.partition("=")
    return key.lstrip("+"), value


def _plain_value(text: str) -> Any:
    """An override value as a Python scalar (``0.01`` -> 0.01, ``null`` -> None, ``os`` -> "os")."""
    try:
        value = yaml.safe_load(text)
    except yaml.YAMLError:
        return text
    return value if isinstance(value, (int, float, str, bool)) or value is None else text


def _select(cfg: DictConfig | None, key: str) -> Any:
    if cfg is None:
        return None
    try:
        value = OmegaConf.select(cfg, key, throw_on_missing=False)
    except Exception:  # noqa: BLE001 - an unresolvable value is just unknown here
        return None
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def experiment_name(cfg: DictConfig | None) -> str | None:
    """The experiment a job ran, named by its data (see the module docstring)."""
    if cfg is None:
        return None
    test = _select(cfg, "data.splits.test") or {}
    train = _select(cfg, "data.splits.train") or {}
    base = _select(cfg, "task_name")
    if test.get("split") == "test" and not test.get("slice") and train.get("categories", "half1") == "half1":
        if test.get("categories") == "half2":
            base = "unseen_categories"
        elif test.get("categories") == "half1":
            base = "unseen_shapes"
    sigma = _select(cfg, "data.pair.noise_sigma")
    if base and isinstance(sigma, (int, float)) and sigma > 0:
        base = f"{base}_noise"
    return base


def _read_json(path: Path) -> tuple[dict | None, str | None]:
    try:
        return json.loads(path.read_text()), None
    except (OSError, ValueError) as err:
        return None, f"unreadable {path.name} ({type(err).__name__})"


def read_job(job_dir: Path) -> dict[str, Any]:
    """Everything known about one job; ``metrics`` is {} unless it finished."""
    info: dict[str, Any] = {"run_dir": str(job_dir), "overrides": {}, "metrics": {}, "status": "ok", "reason": None}
    overrides_file = job_dir / ".hydra" / "overrides.yaml"
    if overrides_file.is_file():
        items = yaml.safe_load(overrides_file.read_text()) or []
        info["overrides"] = dict(parse_override(str(o)) for o in items)
    cfg = None
    if (job_dir / "config_resolved.yaml").is_file():
        cfg = OmegaConf.load(job_dir / "config_resolved.yaml")
    info["cfg"] = cfg
    metrics, metrics_problem = (None, None)
    if (job_dir / "metrics.json").is_file():
        metrics, metrics_problem = _read_json(job_dir / "metrics.json")
    failures = sorted(job_dir.glob("failure*.json"))
    if failures:
        record, problem = _read_json(failures[0])
        if not info["overrides"]:  # no .hydra folder (hydra.output_subdir=null): the failure record has them
            info["overrides"] = dict(parse_override(str(o)) for o in (record or {}).get("overrides", []))
        info["status"] = "failed"
        info["reason"] = problem or (record or {}).get("reason") or (record or {}).get("error_type", "failed")
        if failures[0].name != "failure.json":
            info["reason"] = f"{failures[0].stem}: {info['reason']}"
    elif metrics is None:
        info["status"] = "missing" if not metrics_problem else "failed"
        info["reason"] = metrics_problem or (
            "no metrics.json and no failure.json: killed (timeout, out of memory, segfault), still running, "
            "or test_after_fit=false"
        )
    elif not metrics.get("metrics"):
        info["status"], info["reason"] = "missing", "metrics.json holds no metrics"
    if metrics and info["status"] == "ok":
        info["metrics"] = {k: float(v) for k, v in metrics["metrics"].items()}
        info["context"] = {k: v for k, v in metrics.items() if k != "metrics"}
    return info


def _describe(job: dict[str, Any], cfg: DictConfig | None) -> dict[str, Any]:
    """The standard columns of a job: from its resolved config, else its metrics' context, else its
    overrides (a job that failed before resolving its config, e.g. on an invalid value)."""
    row = {name: _select(cfg, path) for name, path in STANDARD_COLUMNS.items()}
    for name, path in STANDARD_COLUMNS.items():
        if row[name] is None and path in job["overrides"]:
            row[name] = _plain_value(job["overrides"][path])
    context = job.get("context", {})
    for name in ("dataset", "sampling", "partial"):
        if row[name] is None and name in context:
            row[name] = context[name]
    if row["task"] is None:
        row["task"] = context.get("task")
    target = _select(cfg, "model.network._target_")
    row["network"] = str(target).rsplit(".", 1)[-1] if target else None
    method = method_of_network(str(target)) if target else None
    row["method"] = row["variant"] or (method.display if method else row["network"])
    row["experiment"] = experiment_name(cfg)
    return row


# --- the sweep as a whole ----------------------------------------------------------------------


def expected_jobs(root: Path) -> int | None:
    """Jobs a basic-sweeper grid in ``root/multirun.yaml`` should produce (None if unknown)."""
    path = root / "multirun.yaml"
    if not path.is_file():
        return None
    try:
        from hydra.core.override_parser.overrides_parser import OverridesParser

        conf = OmegaConf.load(path)
        params = conf.hydra.sweeper.get("params")
        params = OmegaConf.to_container(params, resolve=False) if OmegaConf.is_config(params) else {}
        texts = [f"{k}={v}" for k, v in params.items()] + list(conf.hydra.overrides.task)
        by_key: dict[str, Any] = {}
        for override in OverridesParser.create().parse_overrides(texts):
            by_key[override.get_key_element()] = override  # command line replaces the config's params
        total = 1
        for override in by_key.values():
            if override.is_sweep_override():
                total *= len(list(override.sweep_string_iterator()))
        return total
    except Exception:  # noqa: BLE001 - glob sweeps, other sweepers: the count is just unknown
        return None


def _arrow_safe(frame: pd.DataFrame) -> pd.DataFrame:
    """Object columns holding mixed types become numbers (if all are) or strings, for parquet."""
    out = frame.copy()
    for col in out.columns:
        if out[col].dtype != object:
            continue
        values = [v for v in out[col] if v is not None and not (isinstance(v, float) and math.isnan(v))]
        if all(isinstance(v, bool) for v in values) or all(isinstance(v, str) for v in values):
            continue
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            out[col] = pd.to_numeric(out[col])
        else:
            out[col] = [None if v is None or (isinstance(v, float) and math.isnan(v)) else str(v) for v in out[col]]
    return out


def collect(*roots: str | Path) -> Collected:
    """Read every job under ``roots`` (multirun dirs, or single job dirs)."""
    root_paths = [Path(r).resolve() for r in roots]
    for root in root_paths:
        if not root.is_dir():
            raise FileNotFoundError(f"{root} is not a directory")
    jobs: list[dict[str, Any]] = []
    for root in root_paths:
        for job_dir in find_job_dirs(root):
            job = read_job(job_dir)
            job["sweep"] = root.name if len(root_paths) == 1 else str(root)
            rel = job_dir.relative_to(root).as_posix()
            job["job"] = rel if rel != "." else job_dir.name
            jobs.append(job)
    expected = [expected_jobs(r) for r in root_paths]
    total_expected = None if any(e is None for e in expected) else sum(expected)  # type: ignore[arg-type]

    keys = sorted({k for job in jobs for k in job["overrides"]})
    swept = [k for k in keys if len({job["overrides"].get(k) for job in jobs}) > 1]
    job_rows, tidy_rows = [], []
    for job in jobs:
        cfg = job["cfg"]
        row = {"sweep": job["sweep"], "job": job["job"], **_describe(job, cfg)}
        for key in swept:
            if key in row:
                continue
            value = _select(cfg, key) if "/" not in key else None
            row[key] = value if value is not None else _plain_value(job["overrides"].get(key, "")) if key in job["overrides"] else None
        job_rows.append({**row, "status": job["status"], "reason": job["reason"], "run_dir": job["run_dir"]})
        for metric, value in job["metrics"].items():
            tidy_rows.append({**row, "metric": metric, "value": value, "run_dir": job["run_dir"]})

    id_columns = [*LEADING, *[k for k in swept if k not in LEADING]]
    jobs_frame = _arrow_safe(pd.DataFrame(job_rows, columns=[*id_columns, "status", "reason", "run_dir"]))
    tidy = _arrow_safe(pd.DataFrame(tidy_rows, columns=[*id_columns, "metric", "value", "run_dir"]))
    if tidy.empty:
        wide = pd.DataFrame(columns=[*id_columns, "run_dir"])
    else:
        order = list(dict.fromkeys(tidy["metric"]))
        wide = tidy.pivot(index="run_dir", columns="metric", values="value")[order].reset_index()
        ok_jobs = jobs_frame[jobs_frame["status"] == "ok"][[*id_columns, "run_dir"]]
        wide = ok_jobs.merge(wide, on="run_dir", how="left")
        wide = wide[[*id_columns, *order, "run_dir"]]
    wide.columns.name = None
    return Collected(tidy=tidy, wide=wide, jobs=jobs_frame, swept=swept, expected=total_expected, roots=root_paths)


def save(result: Collected, out_dir: Path) -> list[Path]:
    """results.parquet/.csv (tidy), results_wide.parquet/.csv, jobs.csv."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, frame in (("results", result.tidy), ("results_wide", result.wide)):
        frame.to_parquet(out_dir / f"{name}.parquet", index=False)
        frame.to_csv(out_dir / f"{name}.csv", index=False)
        written += [out_dir / f"{name}.parquet", out_dir / f"{name}.csv"]
    result.jobs.to_csv(out_dir / "jobs.csv", index=False)
    written.append(out_dir / "jobs.csv")
    return written


def summary(result: Collected) -> str:
    jobs = result.jobs
    counts = jobs["status"].value_counts()
    lines = [
        f"{len(jobs)} jobs in {', '.join(str(r) for r in result.roots)}: {counts.get('ok', 0)} ok, "
        f"{counts.get('failed', 0)} failed, {counts.get('missing', 0)} missing"
        + (f" (the sweep{'s' if len(result.roots) > 1 else ''} should have {result.expected})" if result.expected is not None else "")
    ]
    if result.expected is not None and result.expected > len(jobs):
        lines.append(f"  {result.expected - len(jobs)} job(s) never started (the sweep was interrupted before them)")
    for key in result.swept:
        values = list(dict.fromkeys(str(v) for v in jobs[key])) if key in jobs else []
        lines.append(f"swept {key}: {', '.join(values)}")
    if not result.wide.empty:
        show = [c for c in ("job", "method", "experiment", "sampling", "partial", *result.swept) if c in result.wide]
        show = list(dict.fromkeys(show)) + [m for m in SUMMARY_METRICS if m in result.wide]
        with pd.option_context("display.width", 160, "display.max_columns", 30, "display.float_format", "{:.4g}".format):
            lines += ["", result.wide[show].to_string(index=False)]
    if not result.failures.empty:
        lines += ["", "failed or missing jobs (the others' results are above):"]
        for _, row in result.failures.iterrows():
            where = ", ".join(f"{k}={row[k]}" for k in result.swept if k in row)
            lines.append(f"  {row['job']} [{row['status']}] {('(' + where + ') ') if where else ''}{row['reason']}  -- {row['run_dir']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.collect", description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="multirun dir(s) (or single run dirs)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: <dir>/collected for one dir, else ./collected)")
    parser.add_argument("--strict", action="store_true", help="exit 1 if any job failed or is missing")
    args = parser.parse_args(argv)
    try:
        result = collect(*args.dirs)
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if result.jobs.empty:
        print(f"error: no job found under {', '.join(map(str, args.dirs))} (no metrics.json, failure.json, "
              "config_resolved.yaml or .hydra/overrides.yaml)", file=sys.stderr)
        return 2
    out = args.out or (args.dirs[0] / "collected" if len(args.dirs) == 1 else Path("collected"))
    written = save(result, out)
    print(summary(result))
    print("\nwrote " + ", ".join(str(p) for p in written))
    incomplete = not result.failures.empty or (result.expected is not None and result.expected > len(result.jobs))
    return 1 if args.strict and incomplete else 0


if __name__ == "__main__":
    sys.exit(main())
