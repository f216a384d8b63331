"""Build the dataset cache: ``python -m src.data.prepare DATASET`` (a record of :mod:`src.data.datasets`).

* ``modelnet40 --source PATH``: the Princeton mesh archive (S=40 samplings x 2048 points per mesh,
  ``independent_samplings``) or PointNet's h5 archive (S=1, ``single_sampling``), folder or .zip.
* ``modelnet40_resampled --source PATH``: PointNet++'s ``modelnet40_normal_resampled`` (S=1 dense
  points + normals, ``disjoint_subsets``); a split whose listed files are absent is not built and
  reported (per category: count + first ids).
* ``modelnet40_npy --source PATH``: one ``.npy`` a shape (S=1 as provided, ``single_sampling``: OS, or
  the two disjoint halves of ``data.sampling=halves``); a withheld test split is reported by count.
* ``stanford --source PATH``: a folder (or .zip) of .off/.ply scan meshes, sampled as meshes.
* ``synthetic``: the embedded procedural default (also built on first use by :func:`ensure_cache`).

The layouts, URLs and sampling defaults of each dataset are its record's (:mod:`src.data.datasets`).

``--source`` may be repeated: archives of one layout (e.g. one .zip per category) are merged into one
cache (their categories, splits and fingerprints in one manifest; the order given does not matter).
``--download [LAYOUT]`` fetches the dataset's archive (its first layout with hosts, or LAYOUT) into
``<cache_root>/downloads/`` first, from the first of its hosts that serves it intact
(:mod:`src.data.mirrors`); ``--url URL`` names another host. Re-running with
the same parameters and sources only verifies the cache; a corrupt, partial or differently built one
is rebuilt.
"""

from __future__ import annotations

import argparse
import ctypes
import fcntl
import importlib
import itertools
import json
import logging
import os
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import get_context
from pathlib import Path
from types import ModuleType
from typing import NamedTuple

import numpy as np
from tqdm import tqdm

from src.data.cache import (
    Cache,
    CacheWriter,
    check_cache,
    default_cache_root,
    file_sha256,
    open_cache,
    prepare_hint,
)
from src.data.categories import half_categories
from src.data.datasets import DATASET_NAMES, DATASETS, get_dataset, source_of
from src.data.mesh import MeshShape
from src.data.mirrors import download_archive
from src.data.readers import (
    READERS,
    Archive,
    MergedReader,
    PointShape,
    Reader,
    ShapeEntry,
    check_split_identities,
    layout_of,
)
from src.data.sampling import METHOD, NORMALIZATION, sample_shape
from src.geometry.clouds import check_cloud
from src.utils.errors import DatasetError, exit_code_of
from src.utils.files import disk_errors

log = logging.getLogger(__name__)

AS_PROVIDED = "as_provided"
SYNTHETIC = get_dataset("synthetic")
"""The generated dataset (:func:`build_synthetic_cache`); its defaults are its record's."""

Shape = MeshShape | PointShape
Sampled = tuple[np.ndarray, np.ndarray | None]
Compute = Callable[[Shape, int, dict], Sampled]


# --- per-shape work (module level so that process-pool workers can run it) --------------------


def _sample_mesh(shape: MeshShape, index: int, params: dict) -> Sampled:
    """Mesh samplings, with the sampled faces' normals only when ``params["normals"]`` (``--normals``):
    the paper estimates normals after pre-processing (FGR, RPMNet), and storing them doubles the
    cache (12 GB for ModelNet40); RPMNet's own protocol uses them (``model.network.normals=given``)."""
    points, normals = sample_shape(shape, params["num_samplings"], params["num_points"], params["seed"], index)
    return _in_axes(points, normals if params.get("normals") else None, params)


def _as_provided(shape: PointShape, index: int, params: dict) -> Sampled:
    return _in_axes(shape.points[None], None if shape.normals is None else shape.normals[None], params)


def _in_axes(points: np.ndarray, normals: np.ndarray | None, params: dict) -> Sampled:
    """The arrays with y and z swapped when ``params["swap_yz"]`` (``--swap-yz``), else as given."""
    if not params.get("swap_yz"):
        return points, normals
    swap = [0, 2, 1]
    return points[..., swap], None if normals is None else normals[..., swap]


_worker: tuple[Reader, Compute, dict] | None = None
PR_SET_PDEATHSIG = 1
"""prctl(2)'s option that signals a process when the thread that started it ends (linux/prctl.h)."""


def _die_with_parent(parent: int) -> None:
    """End this process as soon as ``parent`` (the process that started it) ends, however it ends (``kill -9``
    included): Linux's parent-death signal, elsewhere a thread that watches the parent."""
    prctl = getattr(ctypes.CDLL(None, use_errno=True), "prctl", None)
    if prctl is None or prctl(PR_SET_PDEATHSIG, signal.SIGKILL) != 0:
        threading.Thread(target=_exit_when_orphaned, args=(parent,), daemon=True).start()
    elif os.getppid() != parent:  # it ended before the signal was asked for
        os._exit(1)


def _exit_when_orphaned(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(1)
    os._exit(1)


def _init_worker(parent: int, reader: Reader, compute: Compute, params: dict) -> None:
    """A pool worker's start: it dies with ``parent`` (no worker outlives an interrupted ``prepare``) and keeps what
    :func:`_run_task` computes with."""
    _die_with_parent(parent)
    global _worker
    _worker = (reader, compute, params)


def _run_task(task: tuple[int, object]) -> Sampled:
    reader, compute, params = _worker
    index, entry = task
    return compute(reader.load(entry), index, params)


@contextmanager
def _shape_mapper(reader: Reader, compute: Compute, params: dict, workers: int) -> Iterator[Callable]:
    """Yield ``map_tasks([(index, entry), ...]) -> results in order``, in a process pool when workers > 1. The
    pool's workers die with this process, whatever ends it, and are killed when the block ends by an exception
    (Ctrl+C, a shape refused): nothing waits for the shapes they were computing."""
    if workers <= 1:
        yield lambda tasks: (compute(reader.load(entry), index, params) for index, entry in tasks)
        return
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=_init_worker,
                               initargs=(os.getpid(), reader, compute, params))
    try:
        yield lambda tasks: pool.map(_run_task, tasks, chunksize=4)
    except BaseException:
        for process in list((getattr(pool, "_processes", None) or {}).values()):  # (no public way before 3.14)
            process.kill()
        raise
    finally:
        pool.shutdown(cancel_futures=True)


def _write_split(
    writer: CacheWriter, split: str, names: list[str], labels: list[int], results: Iterable[Sampled], desc: str
) -> None:
    """Stream per-shape ``(points, normals)`` of ``(S, P, 3)`` into a new split of the cache; a shape that is no
    registrable cloud (:func:`~src.geometry.clouds.check_cloud`: its points identical or on one line, too large) is
    refused, naming it."""
    results = iter(tqdm(results, total=len(names), desc=desc, unit="shape", disable=None))
    first = next(results)
    shape = (len(names), *first[0].shape)
    out_points, out_normals = writer.add_split(split, shape, labels, names, normals=first[1] is not None)
    for i, (points, normals) in enumerate(itertools.chain([first], results)):
        check_cloud(points.reshape(-1, 3), f"shape {names[i]}")  # identical points, on one line, or too large
        if points.shape != out_points.shape[1:] or (normals is None) != (out_normals is None):
            raise DatasetError(
                f"shape {names[i]}: points {points.shape} (normals: {normals is not None}) differ from the "
                f"first shape's {out_points.shape[1:]} (normals: {out_normals is not None})"
            )
        out_points[i] = points
        if out_normals is not None:
            out_normals[i] = normals


def _log_summary(cache: Cache) -> None:
    for name, info in cache.manifest["splits"].items():
        n, s, p, _ = info["shape"]
        log.info(f"  {name}: {n} shapes x {s} sampling(s) x {p} points")
    log.info(f"wrote {cache.root} ({cache.pair_sampling}, {len(cache.categories)} categories)")


@contextmanager
def _build_lock(out: Path) -> Iterator[None]:
    """Serialise check-and-build of one cache across processes (e.g. DDP ranks building synthetic)."""
    with disk_errors(f"locking the cache {out.name} to build it", out.parent):
        out.parent.mkdir(parents=True, exist_ok=True)
        lock = open(out.parent / f".{out.name}.lock", "w")
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield


def _reuse_or_build(out: Path, expected: dict, force: bool, build: Callable[[], Cache]) -> Cache:
    """The cache at ``out`` when valid for ``expected``, checked without the lock first (a valid cache
    on a read-only mount is read with no write access), else ``build()`` under :func:`_build_lock`."""
    cache = _reuse(out, expected, force, say_why=False)
    if cache is not None:
        return cache
    with _build_lock(out):
        return _reuse(out, expected, force) or build()


#: Caches this process already said were up to date.
_REPORTED_UP_TO_DATE: set[Path] = set()


def _reuse(out: Path, expected: dict, force: bool, say_why: bool = True) -> Cache | None:
    """The existing cache when valid for ``expected`` (hashes verified) and not ``force``d (``say_why``:
    log why an existing one is not)."""
    if force:
        return None
    problem = check_cache(out, expected)
    if problem is None:
        if out not in _REPORTED_UP_TO_DATE:  # once per process: a grid reads the same cache for every cell
            log.info(f"cache up to date: {out} (hashes verified)")
            _REPORTED_UP_TO_DATE.add(out)
        return open_cache(out)
    _REPORTED_UP_TO_DATE.discard(out)
    if out.exists() and say_why:
        log.info(f"rebuilding: {problem}")
    return None


def _reject_options(options: dict[str, object], target: str) -> None:
    given = [flag for flag, value in options.items() if value]
    if given:
        raise DatasetError(f"{', '.join(given)}: not applicable to {target}")


def _pair_sampling(num_samplings: int) -> str:
    return "independent_samplings" if num_samplings >= 2 else "single_sampling"


# --- ModelNet40 -----------------------------------------------------------------------------


def source_fingerprint(source: Path) -> dict:
    """sha256 of an archive file, or file count / total bytes / newest mtime of a folder."""
    if source.is_file():
        return {"sha256": file_sha256(source)}
    stats = [p.stat() for p in source.rglob("*") if p.is_file()]
    newest = max((s.st_mtime_ns for s in stats), default=0)
    return {"files": len(stats), "bytes": sum(s.st_size for s in stats), "mtime_ns": newest}


def _normals_flag(normals: bool) -> dict:
    """The ``sampling`` entry of ``--normals`` (absent when off, so caches built without it stay valid)."""
    return {"normals": True} if normals else {}


def _axes_flag(swap_yz: bool) -> dict:
    """The ``sampling`` entry of ``--swap-yz`` (absent when off, so caches built without it stay valid)."""
    return {"swap_yz": True} if swap_yz else {}


def _sampling_params(
    layout: str, num_samplings: int | None, num_points: int | None, seed: int, limit: int | None, normals: bool = False,
    swap_yz: bool = False,
) -> dict:
    dataset, source = source_of(layout)
    if source.meshes:
        return {
            "num_samplings": num_samplings or dataset.num_samplings, "num_points": num_points or dataset.num_points,
            "seed": seed,
            "method": METHOD, "normalization": NORMALIZATION, "limit": limit, **_normals_flag(normals),
            **_axes_flag(swap_yz),
        }
    _reject_options(
        {"--num-samplings": num_samplings, "--num-points": num_points, "--normals": normals},
        f"the {layout} layout (its points are stored as provided: one sampling holding all of each shape's points)",
    )
    return {"num_samplings": 1, "method": AS_PROVIDED, "normalization": AS_PROVIDED, "limit": limit,
            **_axes_flag(swap_yz)}


def modelnet_halves(categories: list[str]) -> dict[str, list[str]]:
    """The official halves (axisymmetric categories kept) restricted to ``categories``."""
    return {str(h): [c for c in half_categories(h, remove_axisymmetric=False) if c in categories] for h in (1, 2)}


class _Source(NamedTuple):
    """One archive given to ``prepare``: its path as given, the opened archive and its fingerprint."""

    path: Path
    archive: Archive
    fingerprint: dict


def _open_sources(paths: Sequence[Path]) -> list[_Source]:
    """The archives at ``paths`` in a content-defined order (by fingerprint), so that the order in which
    they are given changes neither the cache nor whether it is up to date."""
    sources = [_Source(Path(p), Archive(Path(p)), source_fingerprint(Path(p))) for p in paths]
    return sorted(sources, key=lambda s: json.dumps(s.fingerprint, sort_keys=True))


def _common_layout(dataset: str, sources: list[_Source]) -> str:
    layouts = [layout_of(s.archive) for s in sources]
    if len(set(layouts)) > 1:
        found = ", ".join(f"{s.path} is {layout}" for s, layout in zip(sources, layouts))
        raise DatasetError(f"sources to merge must share one layout: {found}")
    layout = layouts[0]
    if layout not in get_dataset(dataset).layouts:
        other = source_of(layout)[0].name
        raise DatasetError(
            f"{sources[0].path} is in the {layout} layout, which is prepared as `{other}`, not `{dataset}`"
        )
    return layout


def prepare_modelnet(
    dataset: str, sources: Sequence[Path], cache_root: Path, *, num_samplings: int | None = None,
    num_points: int | None = None, seed: int = 0, workers: int = 1, force: bool = False, limit: int | None = None,
    normals: bool = False, swap_yz: bool = False,
) -> Cache:
    """Build (or reuse) ``<cache_root>/<dataset>`` from ModelNet40 archives (folders or .zip files) of
    one layout; several are merged into one cache (:class:`~src.data.readers.MergedReader`). ``swap_yz``
    stores (x, z, y) for (x, y, z): the other axis convention (the layout's record names its own)."""
    opened = _open_sources(sources)
    layout = _common_layout(dataset, opened)
    sampling = _sampling_params(layout, num_samplings, num_points, seed, limit, normals, swap_yz)
    out = cache_root / dataset
    expected = {
        "dataset": dataset, "source_layout": layout, "sampling": sampling,
        "source": {"fingerprints": [s.fingerprint for s in opened]},
    }
    return _reuse_or_build(out, expected, force,
                           lambda: _build_modelnet(out, dataset, opened, layout, sampling, workers, limit))


def _build_modelnet(
    out: Path, dataset: str, sources: list[_Source], layout: str, sampling: dict, workers: int, limit: int | None,
) -> Cache:
    readers = [READERS[layout](s.archive) for s in sources]
    reader = readers[0] if len(readers) == 1 else MergedReader(readers)
    for missing in reader.missing.values():
        log.warning(missing.message)
    if not reader.entries:
        raise DatasetError(f"{reader.where}: no split can be built")
    check_split_identities(reader.entries, {split: reader.split_list(split) for split in reader.entries})
    source = source_of(layout)[1]
    if source.meshes:
        compute, pair_sampling = _sample_mesh, _pair_sampling(sampling["num_samplings"])
    else:
        first = reader.load(next(iter(reader.entries.values()))[0])
        sampling = {**sampling, "num_points": len(first.points)}
        compute, pair_sampling = _as_provided, source.as_provided
    fields = {
        "dataset": dataset, "source_layout": layout, "pair_sampling": pair_sampling,
        "categories": reader.categories, "halves": modelnet_halves(reader.categories), "sampling": sampling,
        "source": {"paths": [str(s.path.resolve()) for s in sources], "fingerprints": [s.fingerprint for s in sources]},
        "missing_splits": {split: missing.to_json() for split, missing in reader.missing.items()},
    }
    workers = 1 if source.one_process else workers  # rows of large files: one process reads each file once
    with CacheWriter(out, fields) as writer, _shape_mapper(reader, compute, sampling, workers) as map_tasks:
        offset = 0  # shape index = position in the full split lists, so --limit keeps the first shapes' samplings
        for split, entries in reader.entries.items():
            tasks = _first_per_category(entries, offset, limit)
            offset += len(entries)
            labels = [reader.categories.index(e.category) for _, e in tasks]
            _write_split(writer, split, [e.name for _, e in tasks], labels, map_tasks(tasks), f"{dataset} {split}")
        cache = writer.commit()
    _log_summary(cache)
    return cache


def _first_per_category(entries: list[ShapeEntry], offset: int, limit: int | None) -> list[tuple[int, ShapeEntry]]:
    """``(offset + position, entry)`` of the first ``limit`` shapes of each category (all without a limit)."""
    taken: Counter[str] = Counter()
    tasks = []
    for index, entry in enumerate(entries, start=offset):
        taken[entry.category] += 1
        if limit is None or taken[entry.category] <= limit:
            tasks.append((index, entry))
    return tasks


# --- synthetic ------------------------------------------------------------------------------


def build_synthetic_cache(
    cache_root: Path | None = None, num_train_per_category: int = SYNTHETIC.build["num_train_per_category"],
    num_test_per_category: int = SYNTHETIC.build["num_test_per_category"], num_samplings: int = SYNTHETIC.num_samplings,
    num_points: int = SYNTHETIC.num_points, seed: int = 0, force: bool = False, normals: bool = False,
) -> Cache:
    """Build (or reuse, when valid) ``<cache_root>/synthetic`` from :mod:`src.data.synthetic` (with the
    sampled faces' normals when ``normals``: ``data.build.normals=true``); the defaults are the record's.

    The generator module's sha256 is part of the source fingerprint, so editing it rebuilds the cache.
    """
    synthetic = importlib.import_module("src.data.synthetic")
    out = Path(cache_root or default_cache_root()) / SYNTHETIC.name
    sampling = {
        "num_samplings": num_samplings, "num_points": num_points, "seed": seed, "method": METHOD,
        "normalization": NORMALIZATION, "num_train_per_category": num_train_per_category,
        "num_test_per_category": num_test_per_category, **_normals_flag(normals),
    }
    module_file = getattr(synthetic, "__file__", None)
    fingerprint = {"sha256": file_sha256(Path(module_file))} if module_file else {}
    categories = list(synthetic.SYNTHETIC_CATEGORIES)
    expected = {
        "dataset": SYNTHETIC.name, "categories": categories, "sampling": sampling,
        "source": {"fingerprints": [fingerprint]},
    }
    return _reuse_or_build(out, expected, force, lambda: _build_synthetic(out, synthetic, sampling, fingerprint))


def _build_synthetic(out: Path, synthetic: ModuleType, sampling: dict, fingerprint: dict) -> Cache:
    categories = list(synthetic.SYNTHETIC_CATEGORIES)
    num_train, num_test = sampling["num_train_per_category"], sampling["num_test_per_category"]
    by_split: dict[str, list[MeshShape]] = {}
    for shape in synthetic.generate_shapes(num_train, num_test, sampling["seed"]):
        by_split.setdefault(shape.split, []).append(shape)
    fields = {
        "dataset": SYNTHETIC.name, "source_layout": SYNTHETIC.layouts[0],
        "pair_sampling": _pair_sampling(sampling["num_samplings"]), "categories": categories,
        "halves": {k: list(v) for k, v in synthetic.SYNTHETIC_HALVES.items()},
        "sampling": sampling, "source": {"paths": [synthetic.__name__], "fingerprints": [fingerprint]},
    }
    with CacheWriter(out, fields) as writer:
        offset = 0
        for split, shapes in by_split.items():
            results = (_sample_mesh(shape, offset + i, sampling) for i, shape in enumerate(shapes))
            labels = [categories.index(shape.category) for shape in shapes]
            _write_split(writer, split, [s.name for s in shapes], labels, results, f"synthetic {split}")
            offset += len(shapes)
        cache = writer.commit()
    _log_summary(cache)
    return cache


def ensure_cache(dataset: str, cache_root: Path | None = None, **params) -> Cache:
    """The cache of ``dataset``, its content verified (once per process): synthetic is built on
    first use (``params`` go to :func:`build_synthetic_cache`); a real dataset must have been
    prepared (a damaged cache is rebuilt from the sources its manifest names when they still exist,
    else refused), and any ``params`` (e.g. ``num_points=2048``) must match its manifest's ``sampling``."""
    root = Path(cache_root or default_cache_root())
    if get_dataset(dataset).generated:
        return build_synthetic_cache(root, **params)
    cache = _open_or_rebuild(dataset, root / dataset)
    for key, value in params.items():
        if cache.manifest["sampling"].get(key) != value:
            raise DatasetError(
                f"the cache at {cache.root} has {key}={cache.manifest['sampling'].get(key)}, requested {value}; "
                f"{prepare_hint(dataset)} with matching options"
            )
    return cache


def _open_or_rebuild(dataset: str, path: Path) -> Cache:
    """The verified cache at ``path``; a damaged one whose sources are known is rebuilt from them."""
    problem = check_cache(path, {})
    build = None if problem is None else _recorded_build(path)
    if build is None:
        return open_cache(path)  # the cache, or the one-line cause and fix
    log.warning(f"{problem}: rebuilding it from {', '.join(map(str, build['sources']))}")
    return prepare_modelnet(dataset, cache_root=path.parent, **build)


def _recorded_build(path: Path) -> dict | None:
    """:func:`prepare_modelnet`'s arguments as the manifest at ``path`` records them, when it is
    readable and names sources that all still exist."""
    try:
        manifest = json.loads((path / "manifest.json").read_text())
        source, sampling = manifest["source"], manifest["sampling"]
        sources = [Path(p) for p in source.get("paths") or [source["path"]]]  # format 1 recorded one "path"
        build = {"sources": sources, "seed": sampling.get("seed", 0), "limit": sampling.get("limit"),
                 "swap_yz": bool(sampling.get("swap_yz"))}
        if sampling["method"] != AS_PROVIDED:
            build |= {"num_samplings": sampling["num_samplings"], "num_points": sampling["num_points"],
                      "normals": bool(sampling.get("normals"))}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    return build if sources and all(p.exists() for p in sources) else None


# --- command line ---------------------------------------------------------------------------


def prepare(
    dataset: str, *, source: Path | Sequence[Path] | None = None, cache_root: Path | None = None,
    num_samplings: int | None = None, num_points: int | None = None, seed: int = 0, workers: int = 1,
    download: bool | str = False, url: str | None = None, force: bool = False, limit: int | None = None,
    normals: bool = False, swap_yz: bool = False,
) -> Cache:
    """What the command line does; see the module docstring. ``download``: True, or the layout to download."""
    cache_root = Path(cache_root or default_cache_root())
    record = get_dataset(dataset)
    if record.generated:
        _reject_options(
            {"--source": source, "--download": download, "--url": url, "--limit": limit, "--swap-yz": swap_yz},
            f"{dataset} (it is generated procedurally)",
        )
        return build_synthetic_cache(
            cache_root, num_samplings=num_samplings or record.num_samplings,
            num_points=num_points or record.num_points, seed=seed, force=force, normals=normals,
        )
    sources = [source] if isinstance(source, (str, os.PathLike)) else list(source or [])
    if url and not download:
        raise DatasetError("--url is only used with --download")
    if download and sources:
        raise DatasetError("use either --source PATH or --download, not both")
    if url and isinstance(download, str):
        raise DatasetError(f"--download {download} --url: the layout of an archive given by --url is detected; drop {download}")
    if download:
        layout = download if isinstance(download, str) else None
        sources = [download_archive(record, cache_root / "downloads", layout=layout, url=url)]
    if not sources:
        archives = " or ".join(record.layouts)
        raise DatasetError(f"{dataset} needs --source PATH (a {archives} folder or .zip) or --download")
    return prepare_modelnet(
        dataset, sources, cache_root, num_samplings=num_samplings, num_points=num_points,
        seed=seed, workers=workers, force=force, limit=limit, normals=normals, swap_yz=swap_yz,
    )


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text}")
    return value


def _defaults(key: str) -> str:
    """A sampling default of every dataset with meshes, from its record: ``modelnet40 40, synthetic 10``."""
    return ", ".join(f"{d.name} {getattr(d, key)}" for d in DATASETS if getattr(d, key) is not None)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m src.data.prepare", description=__doc__.split("\n\n")[0])
    p.add_argument("dataset", choices=DATASET_NAMES, help="; ".join(f"{d.name}: {d.description}" for d in DATASETS))
    p.add_argument(
        "--source", type=Path, action="append",
        help="archive folder or .zip (layout auto-detected); repeat to merge several of one layout into one cache",
    )
    p.add_argument("--cache-root", type=Path, help="default: $OMNET_CACHE_DIR or ~/.cache/omnet-registration")
    p.add_argument("--num-samplings", type=_positive_int, help=f"mesh samplings per shape (default {_defaults('num_samplings')})")
    p.add_argument("--num-points", type=_positive_int, help=f"points per mesh sampling (default {_defaults('num_points')})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=_positive_int, default=os.cpu_count() or 1, help="sampling processes")
    layouts = [s.layout for d in DATASETS for s in d.downloads]
    p.add_argument(
        "--download", nargs="?", const=True, default=False, choices=layouts, metavar="LAYOUT",
        help="fetch the archive into <cache-root>/downloads/ from the first of its hosts that serves it intact "
             f"(the dataset's first layout, or LAYOUT: one of {', '.join(layouts)})",
    )
    p.add_argument("--url", help="archive URL for --download (instead of the dataset's hosts)")
    p.add_argument("--force", action="store_true", help="rebuild even when the cache is up to date")
    p.add_argument("--normals", action="store_true",
                   help="mesh samplings: keep the sampled faces' normals (RPMNet's protocol; doubles the cache)")
    p.add_argument("--swap-yz", action="store_true",
                   help="store (x, z, y) for each (x, y, z): from one axis convention to the other (" +
                        "; ".join(f"{s.layout}: {s.axes}" for d in DATASETS for s in d.sources if s.axes) + ")")
    p.add_argument(
        "--limit", type=_positive_int, help="only the first N shapes of each category per split (smoke tests)"
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s", stream=sys.stdout)
    return exit_code_of(lambda: prepare(
        args.dataset, source=args.source, cache_root=args.cache_root, num_samplings=args.num_samplings,
        num_points=args.num_points, seed=args.seed, workers=args.workers, download=args.download,
        url=args.url, force=args.force, limit=args.limit, normals=args.normals, swap_yz=args.swap_yz,
    ))


if __name__ == "__main__":
    sys.exit(main())
