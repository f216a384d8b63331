"""The paper's published numbers, read at run time from tidy CSVs, and matched to ours.

The CSVs (``table,experiment,method,sampling,metric,value``; default folder
``../shared/reference/paper_tables`` beside the repository root, or ``$OMNET_PAPER_TABLES``, or ``--paper-dir``) are never
copied into this repository. Files with other columns (e.g. the speed table) are skipped.

Matching. A row of ours gets the paper's value when its (method, experiment, sampling, partial,
metric) names the same cell after normalisation (:func:`method_key`, :func:`canonical_experiment`,
upper-case sampling) **and** it ran the paper's protocol for that cell
(:func:`protocol_mismatch`): ModelNet40, noise σ = 0.01 for the ``*_noise`` experiments and 0
otherwise, N = 4 iterations, no overlap-ratio crop. Everything else gets no paper value, with the
reason in ``paper_note``. With ``any_dataset`` (``--paper-any-dataset``) the dataset is not checked and
a real-data experiment is compared with the paper's cell it stands in for (:data:`PAPER_COUNTERPARTS`).
"""

from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path
from typing import Any

import pandas as pd

from baselines.methods import find_method, spelling
from src.utils.paths import shared_path

DEFAULT_PAPER_DIR = shared_path("reference", "paper_tables")
PAPER_COLUMNS = ("table", "experiment", "method", "sampling", "metric", "value")
KEY = ("method_key", "experiment", "sampling", "partial", "metric")

# The paper's experiment names -> ours (ours name each by its data: test set + noise).
EXPERIMENT_ALIASES = {"gaussian_noise": "unseen_shapes_noise"}
EXPERIMENT_LABELS = {
    "unseen_shapes": "Unseen shapes",
    "unseen_categories": "Unseen categories",
    "unseen_shapes_noise": "Gaussian noise (unseen shapes)",
    "unseen_categories_noise": "Unseen categories with Gaussian noise",
    "axisymmetric_z_rotation": "Axisymmetric categories, z rotations",
    "real_airplane": "Real airplanes (the paper: unseen shapes)",
    "real_airplane_noisy": "Real airplanes with Gaussian noise (the paper: Gaussian noise)",
    "real_unseen_category": "Real airplanes to real bathtubs (the paper: unseen categories)",
}
#: Our real-data experiments -> the paper's cell each stands in for (other data: matched only with ``any_dataset``).
PAPER_COUNTERPARTS = {
    "real_airplane": "unseen_shapes",
    "real_airplane_noisy": "unseen_shapes_noise",
    "real_unseen_category": "unseen_categories",
}
PAPER_NOISE_SIGMA = 0.01
PAPER_NUM_ITERS = 4
#: Our datasets of the paper's ModelNet40 shapes. ``modelnet40_npy``: the same shapes, categories and split protocol
#: on 1,024 points a shape, OS only, with carve-outs where the test split is withheld (docs/data.md): its cells stand
#: beside the paper's, not on the same test pairs.
PAPER_DATASETS = ("modelnet40", "modelnet40_npy")


def default_paper_dir() -> Path:
    return Path(os.environ.get("OMNET_PAPER_TABLES", DEFAULT_PAPER_DIR))


def canonical_experiment(name: Any) -> Any:
    """``gaussian_noise`` (the paper's Table 1(c) name) -> ``unseen_shapes_noise``; others unchanged."""
    if not isinstance(name, str):
        return name
    return EXPERIMENT_ALIASES.get(name, name)


def partial_of_table(table: str, file_name: str = "") -> str:
    """The partial manner of a paper table: RPMNet's for the tables/files naming it, else PRNet's
    (Table 1, Table 3 and the PRNet supplementary tables)."""
    return "rpmnet" if "rpmnet" in f"{table} {file_name}".lower() else "prnet"


_LAMBDA = re.compile(r"^\s*(?:\$\\lambda\$|\\lambda|λ|lambda)\s*=\s*([-+0-9.eE]+)\s*$")


def method_key(name: Any) -> str:
    """Matching key of a method name: a registered method's key for any of its names (``Ours`` = ``OMNet``
    = ``omnet``, :func:`baselines.methods.find_method`); ``$\\lambda$=2.0``, ``λ=2`` and ``lambda=2.0``
    are one key; other names without case, spaces and punctuation (``Top-k, k=100`` = ``top-k k=100``)."""
    text = str(name).strip()
    match = _LAMBDA.match(text)
    if match:
        return f"lambda={float(match.group(1)):g}"
    method = find_method(text)
    return method.key if method else spelling(text)


def load_paper_tables(paper_dir: str | Path | None = None) -> pd.DataFrame:
    """All tidy paper tables in ``paper_dir`` as one frame with ``partial``, ``method_key`` and
    canonical experiment names added; duplicate cells (Table 2 repeats part of a supplementary
    table) are kept once."""
    folder = Path(paper_dir) if paper_dir else default_paper_dir()
    if not folder.is_dir():
        raise FileNotFoundError(f"paper tables folder {folder} does not exist (pass --paper-dir or set OMNET_PAPER_TABLES)")
    frames = []
    for path in sorted(folder.glob("*.csv")):
        frame = pd.read_csv(path)
        if not set(PAPER_COLUMNS) <= set(frame.columns):
            continue
        frame = frame[list(PAPER_COLUMNS)].dropna(subset=["value"]).copy()
        frame["file"] = path.name
        frame["partial"] = [partial_of_table(t, path.name) for t in frame["table"]]
        frames.append(frame)
    if not frames:
        raise FileNotFoundError(f"no paper table (columns {', '.join(PAPER_COLUMNS)}) in {folder}")
    paper = pd.concat(frames, ignore_index=True)
    paper["experiment"] = paper["experiment"].map(canonical_experiment)
    paper["sampling"] = paper["sampling"].str.upper()
    paper["method_key"] = paper["method"].map(method_key)
    paper["value"] = paper["value"].astype(float)
    dup = paper.duplicated(list(KEY), keep=False)
    if dup.any():
        spread = paper[dup].groupby(list(KEY))["value"].agg(lambda v: v.max() - v.min())
        if (spread > 1e-9).any():
            warnings.warn(f"paper tables disagree on {int((spread > 1e-9).sum())} cells; the first file's value is used")
    return paper.drop_duplicates(list(KEY), keep="first").reset_index(drop=True)


def _is_missing(value: Any) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value)) or value is pd.NA


def paper_experiment(name: Any, any_dataset: bool = False) -> Any:
    """The paper's experiment a row of ours is compared with: :func:`canonical_experiment`, and with
    ``any_dataset`` a real-data experiment's counterpart (:data:`PAPER_COUNTERPARTS`)."""
    name = canonical_experiment(name)
    return PAPER_COUNTERPARTS.get(name, name) if any_dataset and isinstance(name, str) else name


def protocol_mismatch(row: pd.Series | dict, any_dataset: bool = False) -> str | None:
    """Why a row of ours is not the paper's setting for its cell (None if it is). Columns that a
    frame does not have are not checked (a frame of the comparison grid need not carry them)."""
    get = row.get
    experiment = str(paper_experiment(get("experiment", ""), any_dataset))
    dataset = get("dataset")
    if not any_dataset and not _is_missing(dataset) and dataset not in PAPER_DATASETS:
        return f"dataset {dataset} (the paper's numbers are ModelNet40)"
    sigma = get("noise_sigma")
    if not _is_missing(sigma):
        want = PAPER_NOISE_SIGMA if experiment.endswith("_noise") else 0.0
        if not math.isclose(float(sigma), want, abs_tol=1e-12):
            return f"noise sigma {float(sigma):g} (the paper's {experiment} uses {want:g})"
    ratio = get("overlap_ratio")
    if not _is_missing(ratio):
        return f"overlap-ratio protocol (ratio {float(ratio):g})"
    iters = get("num_iters")
    if not _is_missing(iters) and int(iters) != PAPER_NUM_ITERS:
        return f"N = {int(iters)} iterations (the paper's tables use {PAPER_NUM_ITERS})"
    return None


def attach_paper(frame: pd.DataFrame, paper: pd.DataFrame, any_dataset: bool = False) -> pd.DataFrame:
    """``frame`` plus ``paper_value``, ``paper_table`` (file), ``ratio`` (ours / paper) and
    ``paper_note`` (why there is no paper value) columns."""
    out = frame.copy()
    keys = pd.DataFrame({
        "method_key": out["method"].map(method_key),
        "experiment": out["experiment"].map(lambda e: paper_experiment(e, any_dataset)),
        "sampling": out["sampling"].astype(str).str.upper(),
        "partial": out["partial"].astype(str).str.lower() if "partial" in out else "prnet",
        "metric": out["metric"],
    }, index=out.index)
    lookup = paper.set_index(list(KEY))[["value", "file"]]
    values, files, notes = [], [], []
    for idx, key in zip(out.index, keys.itertuples(index=False, name=None)):
        mismatch = protocol_mismatch(out.loc[idx], any_dataset=any_dataset)
        if key not in lookup.index:
            values.append(math.nan)
            files.append(None)
            notes.append("not in the paper's tables")
        elif mismatch:
            values.append(math.nan)
            files.append(None)
            notes.append(mismatch)
        else:
            hit = lookup.loc[key]
            values.append(float(hit["value"]))
            files.append(hit["file"])
            notes.append(None)
    out["paper_value"] = values
    out["paper_table"] = files
    out["paper_note"] = notes
    out["ratio"] = out["value"] / out["paper_value"]
    return out
