"""Running the grid's cells: registering their pairs, scoring them, writing their files, and the
tidy table of a run (see :mod:`benchmarks.grid` for the files).
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from omegaconf import DictConfig

from baselines import RegistrationResult, run_pairs
from baselines.methods import display_name
from benchmarks.grid.plan import Cell, numbers_digest, plan
from src.config import euler_seq_for
from src.data.cache import file_sha256
from src.utils.errors import UserError
from src.utils.files import read_parquet, write_atomic, write_parquet, write_text_atomic
from src.metrics import CHAMFER, ERROR_R, ERROR_T, MAE_R, MAE_T, MODIFIED_CHAMFER, PAIR_ERRORS

PROGRESS_COLUMNS = ("cell", "transform", "seconds", "failed", "timed_out", "reason", "wall")
TIDY_COLUMNS = ("method", "method_id", "experiment", "sampling", "partial", "dataset", "noise_sigma", "metric",
                "value", "n_pairs", "n_failed", "seconds", "seconds_per_pair", "cell")


def cell_metrics(
    results: Sequence[RegistrationResult], pairs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], euler_seq: str,
    raw: Sequence[np.ndarray] | None = None,
) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """RegistrationMetrics over the cell (failed pairs count with their identity estimate) and the
    per-pair errors; with ``raw`` (each pair's clean full reference) RPM-Net's modified Chamfer distance
    too (else NaN per pair and no cell value)."""
    import torch

    from src.geometry import se3_apply
    from src.metrics import RegistrationMetrics, chamfer_distance, modified_chamfer, pair_errors

    metric = RegistrationMetrics(euler_seq)
    per_pair: dict[str, list[float]] = {name: [] for name in PAIR_ERRORS}
    for k, (result, (src, ref, gt)) in enumerate(zip(results, pairs)):
        pred_t = torch.tensor(np.asarray(result.transform), dtype=torch.float64)[None]
        gt_t = torch.as_tensor(gt, dtype=torch.float32)[None]
        src_t = torch.as_tensor(src, dtype=torch.float32)[None]
        ref_t = torch.as_tensor(ref, dtype=torch.float32)[None]
        raw_t = None if raw is None else torch.as_tensor(raw[k], dtype=torch.float32)[None]
        metric.update(pred_t, gt_t, src_t, ref_t, raw_t)
        err = pair_errors(pred_t, gt_t, euler_seq)
        per_pair[ERROR_R].append(float(err["rot_deg"][0]))
        per_pair[ERROR_T].append(float(err["trans_norm"][0]))
        per_pair[MAE_R].append(float(err["euler_err"][0].abs().mean()))
        per_pair[MAE_T].append(float(err["trans_err"][0].abs().mean()))
        moved = se3_apply(pred_t.float(), src_t)
        per_pair[CHAMFER].append(float(chamfer_distance(moved, ref_t)[0]))
        per_pair[MODIFIED_CHAMFER].append(
            float("nan") if raw_t is None else float(modified_chamfer(pred_t, gt_t, src_t, ref_t, raw_t)[0]))
    return metric.compute(), {k: np.asarray(v) for k, v in per_pair.items()}


def register(registrator: Any, pairs: Sequence[tuple[np.ndarray, np.ndarray]], workers: int | None = None,
             timeout_s: float | None = None, progress: bool = True) -> list[RegistrationResult]:
    """One result per ``(src, ref)`` pair: a learned registrator's in batches (:func:`run_batches`), a classical
    one's in worker processes (:func:`run_pairs`)."""
    if getattr(registrator, "needs_training", False):
        from baselines.learned.adapter import run_batches

        return run_batches(registrator, pairs, progress=progress)
    return run_pairs(registrator, pairs, workers=workers, timeout_s=timeout_s, progress=progress)


#: The first call of a cell's pairs when progress is saved: enough to measure the method's rate.
FIRST_CHUNK_PAIRS = 32


def load_progress(cell: Cell) -> tuple[list[RegistrationResult], list[float]]:
    """The results an interrupted run saved for ``cell`` (its first pairs, in order) and each one's share of the
    wall time; none when nothing was saved, or (one warning line) when the file is damaged or not this cell's."""
    path = cell.progress_path
    if not path.is_file():
        return [], []
    try:
        frame = read_parquet(path)
    except UserError as err:
        print(f"warning: cell {cell.key}: {path.name} is damaged ({err}); registering its pairs again", file=sys.stderr)
        return [], []
    if not set(PROGRESS_COLUMNS) <= set(frame.columns) or (frame["cell"] != cell.digest).any() or len(frame) > cell.n_pairs:
        print(f"warning: cell {cell.key}: {path.name} is not this cell's; registering its pairs again", file=sys.stderr)
        return [], []
    results = [RegistrationResult(np.asarray(row.transform, dtype=np.float64).reshape(4, 4), float(row.seconds),
                                  bool(row.failed), bool(row.timed_out), str(row.reason)) for row in frame.itertuples()]
    return results, [float(w) for w in frame["wall"]]


def result_columns(results: Sequence[RegistrationResult]) -> dict[str, list]:
    """The columns of a cell's per-pair files that hold its results: transform, seconds, failed, reason."""
    return {"transform": [np.asarray(r.transform, dtype=np.float64).reshape(-1).tolist() for r in results],
            "seconds": [float(r.seconds) for r in results],
            "failed": [bool(r.failed) for r in results],
            "reason": [r.reason for r in results]}


def save_progress(cell: Cell, results: Sequence[RegistrationResult], walls: Sequence[float]) -> None:
    """Keep the results of ``cell``'s first pairs (:func:`load_progress` reads them back)."""
    import pandas as pd

    frame = pd.DataFrame({"cell": cell.digest, **result_columns(results),
                          "timed_out": [bool(r.timed_out) for r in results], "wall": list(walls)},
                         columns=list(PROGRESS_COLUMNS))
    cell.folder.mkdir(parents=True, exist_ok=True)
    write_parquet(frame, cell.progress_path)


def register_cells(cells: Sequence[Cell], cfg: DictConfig) -> list[tuple[list[RegistrationResult], float]]:
    """Register the pairs of ``cells`` (all of one registrator): one result list per cell and its share of the
    wall time. A classical method's cells go through :func:`run_pairs` calls (one set of worker processes a call),
    a learned method's through :func:`run_batches`. With ``save_every_s`` the pairs are registered in calls of about
    that long, each followed by the cells' progress files, and the pairs an interrupted run saved are not
    registered again; without it, in one call."""
    clouds = [[(src, ref) for src, ref, _ in cell.test_set.pairs(cell.n_pairs)] for cell in cells]
    saved = [load_progress(cell) for cell in cells]
    results = [list(done) for done, _ in saved]
    walls = [list(shares) for _, shares in saved]
    todo = [(i, k) for i, cell in enumerate(cells) for k in range(len(results[i]), cell.n_pairs)]
    workers = cfg.get("workers")
    save_every_s = cfg.get("save_every_s")
    size = min(FIRST_CHUNK_PAIRS, len(todo)) if save_every_s else len(todo)
    while todo:
        chunk, todo = todo[:size], todo[size:]
        start = time.perf_counter()
        out = register(cells[0].registrator, [clouds[i][k] for i, k in chunk],
                       None if workers is None else int(workers), cfg.get("timeout_s"), bool(cfg.progress))
        per_pair = (time.perf_counter() - start) / len(chunk)
        for (i, _), result in zip(chunk, out):
            results[i].append(result)
            walls[i].append(per_pair)
        if todo:
            for i in sorted({i for i, _ in chunk}):
                save_progress(cells[i], results[i], walls[i])
            size = max(1, int(float(save_every_s) / max(per_pair, 1e-9)))
    return [(cell_results, float(sum(shares))) for cell_results, shares in zip(results, walls)]


def finish_cell(cell: Cell, results: Sequence[RegistrationResult], wall: float) -> dict[str, Any]:
    """Score a registered cell, write its parquet, then its JSON (the commit marker, with the parquet's sha256 and
    a checksum of its own numbers: :meth:`Cell.load` reuses the cell only while both match); return the summary."""
    import pandas as pd

    t = cell.test_set
    pairs = t.pairs(cell.n_pairs)
    euler_seq = euler_seq_for(t.partial)
    metrics, errors = cell_metrics(results, pairs, euler_seq, t.raw(cell.n_pairs))
    columns = result_columns(results)
    frame = pd.DataFrame({
        "method": cell.method,
        "experiment": t.experiment,
        "sampling": t.sampling.upper(),
        "partial": t.partial,
        "dataset": t.dataset_name,
        "cell": cell.digest,
        "pair": range(len(results)),
        "transform": columns["transform"],
        "transform_gt": [gt.reshape(-1).tolist() for _, _, gt in pairs],
        "seconds": columns["seconds"],
        "failed": columns["failed"],
        "reason": columns["reason"],
        **{name: errors[name] for name in PAIR_ERRORS},
    })
    cell.folder.mkdir(parents=True, exist_ok=True)
    write_parquet(frame, cell.pairs_path)
    n_failed = int(frame["failed"].sum())
    summary = {
        "digest": cell.digest,
        "method": cell.method,
        "label": getattr(cell.registrator, "label", display_name(cell.method)),
        "experiment": t.experiment,
        "sampling": t.sampling,
        "partial": t.partial,
        "dataset": t.dataset_name,
        "noise_sigma": t.noise_sigma,
        "euler_seq": euler_seq,
        "n_pairs": len(results),
        "n_failed": n_failed,
        "failure_reasons": {k: int(v) for k, v in frame.loc[frame["failed"], "reason"].value_counts().items()},
        "seconds": float(frame["seconds"].sum()),
        "wall_seconds": wall,
        "metrics": metrics,
        "definition": cell.definition,
        "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "complete": True,
        "pairs_sha256": file_sha256(cell.pairs_path),
    }
    summary = json.loads(json.dumps(summary, default=str))  # checksummed as it reads back
    summary["checksum"] = numbers_digest(summary)
    write_text_atomic(cell.summary_path, json.dumps(summary, indent=2))
    cell.progress_path.unlink(missing_ok=True)
    return summary


def _calls(cells: Sequence[Cell], pairs_per_call: int | None) -> list[list[Cell]]:
    """Pending cells grouped by registrator (in grid order), each group cut into calls of at most
    ``pairs_per_call`` pairs (a cell is never split)."""
    groups: dict[int, list[Cell]] = {}
    for cell in cells:
        groups.setdefault(id(cell.registrator), []).append(cell)
    calls = []
    for group in groups.values():
        current: list[Cell] = []
        for cell in group:
            if current and pairs_per_call and sum(c.n_pairs for c in current) + cell.n_pairs > pairs_per_call:
                calls.append(current)
                current = []
            current.append(cell)
        calls.append(current)
    return calls


def tidy_rows(summary: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The rows of the tidy table (:data:`TIDY_COLUMNS`) of one cell's summary: one per metric."""
    from src.metrics import METRIC_NAMES

    n = int(summary["n_pairs"])
    common = {
        "method": summary.get("label") or display_name(summary["method"]),
        "method_id": summary["method"],
        "experiment": summary["experiment"],
        "sampling": str(summary["sampling"]).upper(),
        "partial": summary["partial"],
        "dataset": summary["dataset"],
        "noise_sigma": float(summary["noise_sigma"]),
    }
    tail = {"n_pairs": n, "n_failed": int(summary["n_failed"]), "seconds": float(summary["seconds"]),
            "seconds_per_pair": float(summary["seconds"]) / max(n, 1), "cell": summary["digest"]}
    return [{**common, "metric": name, "value": float(summary["metrics"][name]), **tail}
            for name in METRIC_NAMES if name in summary["metrics"]]


@dataclass
class GridResult:
    """A run of the grid: its tidy table, per-pair rows, cell summaries and what was reused or skipped."""

    tidy: Any  # pandas.DataFrame, see TIDY_COLUMNS
    pairs: Any  # pandas.DataFrame, one row per pair
    cells: list[dict[str, Any]]
    reused: int = 0
    computed: int = 0
    skipped: list[str] = field(default_factory=list)
    output_dir: Path | None = None


def run_grid(cfg: DictConfig) -> GridResult:
    """Plan, run (or reuse) every cell, write the tidy table and the per-pair rows."""
    import pandas as pd
    from tqdm.auto import tqdm

    output_dir = Path(str(cfg.output_dir))
    cells, notes = plan(cfg)
    output_dir.mkdir(parents=True, exist_ok=True)
    done = {cell.digest: loaded for cell in cells if (loaded := cell.load()) is not None}
    pending = [cell for cell in cells if cell.digest not in done]
    with tqdm(total=len(cells), initial=len(done), disable=not cfg.progress, desc="grid", unit="cell", dynamic_ncols=True) as bar:
        for call in _calls(pending, cfg.get("pairs_per_call")):
            bar.set_postfix_str(f"{call[0].method}: {len(call)} cell(s)", refresh=True)
            for cell, (results, wall) in zip(call, register_cells(call, cfg)):
                done[cell.digest] = finish_cell(cell, results, wall)
                bar.update(1)
    summaries = [done[cell.digest] for cell in cells]
    tidy = pd.DataFrame([row for s in summaries for row in tidy_rows(s)], columns=list(TIDY_COLUMNS))
    pairs = pd.concat([read_parquet(cell.pairs_path) for cell in cells], ignore_index=True)
    write_parquet(tidy, output_dir / "results.parquet")
    write_atomic(output_dir / "results.csv", lambda path: tidy.to_csv(path, index=False))
    write_parquet(pairs, output_dir / "pairs.parquet")
    return GridResult(tidy, pairs, summaries, len(cells) - len(pending), len(pending), notes, output_dir)
