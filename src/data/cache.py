"""The on-disk dataset cache: one compact format for every source.

Layout of ``<cache_root>/<dataset>/``::

    manifest.json
    {split}_points.npy    float32 (N, S, P, 3)   S samplings of P points per shape
    {split}_normals.npy   float32 (N, S, P, 3)   optional
    {split}_labels.npy    int64   (N,)           index into manifest["categories"]

The manifest records ``format_version``, ``dataset`` and ``source_layout`` (a record of
:mod:`src.data.datasets` and one of its layouts), ``pair_sampling``,
``categories``, ``halves``, ``splits`` (count, shape, shape_names, per-file name/bytes/sha256),
``missing_splits`` (count, examples, by_category, message), ``sampling``, ``source`` (paths and
fingerprints), ``content_hash`` (sha256 of every other field, the file hashes included) and, last,
``complete: true``. A cache is written into a temporary sibling folder and renamed into place, so
an interrupted build never leaves a valid-looking cache. Opening a cache verifies its content
(manifest and file hashes) once per process while its files stay unchanged.
"""

from __future__ import annotations

import hashlib
import json
import logging
import mmap
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from src.data.datasets import DATASET_NAMES, get_dataset
from src.utils.errors import DatasetError
from src.utils.files import disk_error, disk_errors, owned_prefix, preallocate, remove_stale_folders

log = logging.getLogger(__name__)

FORMAT_VERSION = 2
"""2: ``content_hash`` covers the whole manifest; ``source`` holds ``paths`` and ``fingerprints``."""
PAIR_SAMPLINGS: tuple[str, ...] = ("independent_samplings", "single_sampling", "disjoint_subsets")
"""``independent_samplings``: S >= 2 mesh samplings, TS picks 2 of S, OS uses one.
``single_sampling``: S = 1, only OS possible. ``disjoint_subsets``: S = 1 dense points, TS = two
disjoint random subsets, OS = one subset for both clouds."""
REQUIRED_FIELDS: tuple[str, ...] = (
    "dataset", "source_layout", "pair_sampling", "categories", "halves", "sampling", "source",
)
_ARRAYS: tuple[str, ...] = ("points", "normals", "labels")
_verified: set[tuple] = set()
"""Caches whose files were hashed in this process: (folder, content hash, (inode, size, mtime) per file)."""


def default_cache_root() -> Path:
    """``$OMNET_CACHE_DIR``, else ``~/.cache/omnet-registration``."""
    env = os.environ.get("OMNET_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "omnet-registration"


def prepare_hint(dataset: str) -> str:
    """How to (re)build the cache of ``dataset``."""
    if dataset in DATASET_NAMES and get_dataset(dataset).generated:
        return f"run `python -m src.data.prepare {dataset}`"
    return (
        f"run `python -m src.data.prepare {dataset} --source PATH` "
        "(or use data=synthetic for the embedded synthetic default)"
    )


@dataclass(frozen=True)
class CacheSplit:
    """One split: ``points``/``normals`` ``(N, S, P, 3)`` float32, ``labels`` ``(N,)`` int64."""

    name: str
    points: np.ndarray
    normals: np.ndarray | None
    labels: np.ndarray
    shape_names: list[str]


class Cache:
    """A validated cache folder; splits are memory-mapped on access."""

    def __init__(self, root: Path, manifest: dict):
        self.root = Path(root)
        self.manifest = manifest

    @property
    def dataset(self) -> str:
        return self.manifest["dataset"]

    @property
    def categories(self) -> list[str]:
        return self.manifest["categories"]

    @property
    def halves(self) -> dict[str, list[str]]:
        return self.manifest["halves"]

    @property
    def pair_sampling(self) -> str:
        return self.manifest["pair_sampling"]

    @property
    def available_splits(self) -> list[str]:
        return list(self.manifest["splits"])

    def category_counts(self, name: str) -> dict[str, int]:
        """Shapes per category of split ``name``: of the built split, or, for a split the source withheld, the
        counts its manifest records (``missing_splits.<name>.by_category``)."""
        missing = self.manifest.get("missing_splits", {}).get(name)
        if missing is not None:
            return {category: int(entry["missing"]) for category, entry in missing.get("by_category", {}).items()}
        labels, counts = np.unique(np.asarray(self.split(name).labels), return_counts=True)
        return {self.categories[int(label)]: int(count) for label, count in zip(labels, counts)}

    def split(self, name: str) -> CacheSplit:
        """Memory-mapped arrays of a built split; an unbuilt split raises its missing-files message."""
        missing = self.manifest.get("missing_splits", {})
        if name in missing:
            raise DatasetError(missing[name]["message"])
        if name not in self.manifest["splits"]:
            raise DatasetError(
                f"split '{name}' is not in the cache at {self.root} (available: {', '.join(self.available_splits)})"
            )
        info = self.manifest["splits"][name]
        arrays = {key: np.load(self.root / f["name"], mmap_mode="r") for key, f in info["files"].items()}
        return CacheSplit(name, arrays["points"], arrays.get("normals"), arrays["labels"], info["shape_names"])


def file_sha256(path: Path, chunk_size: int = 1 << 22) -> str:
    """Hex sha256 of a file, streamed from a read-only memory map."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        if os.fstat(f.fileno()).st_size:
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data, memoryview(data) as view:
                for start in range(0, len(view), chunk_size):
                    digest.update(view[start:start + chunk_size])
    return digest.hexdigest()


def _content_hash(manifest: Mapping) -> str:
    """sha256 of the canonical JSON of every manifest field but ``content_hash``."""
    fields = {key: value for key, value in manifest.items() if key != "content_hash"}
    return hashlib.sha256(json.dumps(fields, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def manifest_without_normals(manifest: Mapping) -> dict:
    """A copy of ``manifest`` that lists no normals file in any split, its content hash recomputed: the manifest
    of the same cache with its optional normals left out (a smaller copy to carry elsewhere)."""
    fields = json.loads(json.dumps(manifest))
    for info in fields["splits"].values():
        info["files"].pop("normals", None)
    fields.pop("content_hash", None)
    return {**fields, "content_hash": _content_hash(fields)}


def _read_manifest(path: Path) -> dict:
    """The manifest of a complete, intact cache (content verified); otherwise DatasetError naming the cause."""
    manifest_file = path / "manifest.json"
    if not path.is_dir():
        raise DatasetError(f"no dataset cache at {path}")
    if not manifest_file.is_file():
        raise DatasetError(f"{path} has no manifest.json (not a dataset cache)")
    try:
        manifest = json.loads(manifest_file.read_text())
    except (OSError, ValueError) as e:
        raise DatasetError(f"{manifest_file} is unreadable ({e})") from e
    if not isinstance(manifest, dict):
        raise DatasetError(f"{manifest_file} is unreadable (not a JSON object)")
    if manifest.get("complete") is not True:
        raise DatasetError(f"the cache at {path} is incomplete (interrupted build)")
    if manifest.get("format_version") != FORMAT_VERSION:
        version = manifest.get("format_version")
        raise DatasetError(f"the cache at {path} has format_version {version}, expected {FORMAT_VERSION}")
    if _content_hash(manifest) != manifest.get("content_hash"):
        raise DatasetError(f"{manifest_file} is corrupt (its content_hash does not match its fields)")
    _verify_files(path, manifest)
    return manifest


def _verify_files(path: Path, manifest: dict) -> None:
    """Every file present with its recorded size, and its sha256 (hashed once per process while the
    files keep their inode, size and mtime)."""
    files = [(path / f["name"], f) for info in manifest["splits"].values() for f in info["files"].values()]
    stats = []
    for file, f in files:
        if not file.is_file():
            raise DatasetError(f"cache file {file} is missing")
        stat = file.stat()
        if stat.st_size != f["bytes"]:
            raise DatasetError(
                f"cache file {file} has {stat.st_size} bytes, expected {f['bytes']} (truncated or corrupt)"
            )
        stats.append((stat.st_ino, stat.st_size, stat.st_mtime_ns))
    key = (str(path.resolve()), manifest["content_hash"], tuple(stats))
    if key in _verified:
        return
    for file, f in files:
        if file_sha256(file) != f["sha256"]:
            raise DatasetError(f"cache file {file} is corrupt (sha256 mismatch)")
    _verified.add(key)


def open_cache(path: Path) -> Cache:
    """Open a cache folder, its content verified (once per process while its files are unchanged).

    Raises one-line :class:`DatasetError` naming the cause and how to prepare the dataset.
    """
    path = Path(path)
    try:
        return Cache(path, _read_manifest(path))
    except DatasetError as e:
        raise DatasetError(f"{e}; {prepare_hint(path.name)}") from None


def _matches(actual: object, expected: object) -> bool:
    """``expected`` is contained in ``actual``: dicts compare key by key, other values by equality."""
    if isinstance(expected, Mapping):
        return isinstance(actual, Mapping) and all(k in actual and _matches(actual[k], v) for k, v in expected.items())
    return actual == expected


def check_cache(path: Path, expected: Mapping) -> str | None:
    """``None`` when the cache at ``path`` is complete, its hashes verify and its manifest contains
    ``expected`` (a nested sub-dict, e.g. ``{"sampling": {...}}``); else the reason it is not."""
    try:
        manifest = _read_manifest(Path(path))
    except DatasetError as e:
        return str(e)
    differing = [key for key, value in expected.items() if not _matches(manifest.get(key), value)]
    return f"the cache at {path} was built with different {', '.join(differing)}" if differing else None


def is_cache_valid(path: Path, expected: Mapping) -> bool:
    """Complete, hashes verified and the manifest contains ``expected`` (see :func:`check_cache`)."""
    return check_cache(path, expected) is None


class CacheWriter:
    """Streams splits into a temporary sibling folder; :meth:`commit` renames it into place.

    ``manifest_fields`` holds :data:`REQUIRED_FIELDS` and optionally ``missing_splits``.
    Use as a context manager: an exception discards the temporary folder (a full disk or a folder
    without write permission then raises one :class:`~src.utils.errors.DiskError` line); the folders that a
    writer killed before its clean-up (``kill -9``) left beside the cache are deleted by the next writer. The
    memory-mapped arrays are preallocated, so a full disk fails when a split is added, never by ``SIGBUS`` mid-write.
    """

    def __init__(self, out_dir: Path, manifest_fields: Mapping):
        absent = [k for k in REQUIRED_FIELDS if k not in manifest_fields]
        if absent:
            raise ValueError(f"manifest_fields lacks {absent}")
        self.out_dir = Path(out_dir)
        with disk_errors(self._what, self.out_dir.parent):
            self.out_dir.parent.mkdir(parents=True, exist_ok=True)
            self._remove_stale()
            self.tmp_dir = Path(tempfile.mkdtemp(prefix=owned_prefix(self._prefix("tmp")), dir=self.out_dir.parent))
        self.tmp_dir.chmod(0o755)  # mkdtemp makes it private
        self.fields = dict(manifest_fields)
        self._splits: dict[str, dict] = {}
        self._arrays: dict[str, dict[str, np.ndarray]] = {}

    def add_split(
        self, name: str, shape: tuple[int, int, int, int], labels: np.ndarray, shape_names: list[str], normals: bool
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Create a split of ``shape`` ``(N, S, P, 3)``; returns writable memmaps ``(points, normals)``
        for the caller to fill (``normals`` is ``None`` unless requested)."""
        labels = np.asarray(labels, dtype=np.int64)
        if len(shape) != 4 or shape[3] != 3 or labels.shape != (shape[0],) or len(shape_names) != shape[0]:
            raise ValueError(f"split {name}: shape {shape}, {labels.shape} labels, {len(shape_names)} names disagree")
        np.save(self.tmp_dir / f"{name}_labels.npy", labels)
        keys = ("points", "normals") if normals else ("points",)
        self._arrays[name] = {}
        for key in keys:
            path = self.tmp_dir / f"{name}_{key}.npy"
            self._arrays[name][key] = np.lib.format.open_memmap(path, "w+", np.float32, shape)
            preallocate(path)
        self._splits[name] = {"count": shape[0], "shape": list(shape), "shape_names": list(shape_names)}
        return self._arrays[name]["points"], self._arrays[name].get("normals")

    def commit(self) -> Cache:
        """Hash the files, write the manifest (``complete`` last) and move the cache into place."""
        for name, arrays in self._arrays.items():
            for array in arrays.values():
                array.flush()
            files = [f"{name}_{key}.npy" for key in _ARRAYS]
            self._splits[name]["files"] = {
                key: self._describe(file) for key, file in zip(_ARRAYS, files) if (self.tmp_dir / file).exists()
            }
        self._arrays.clear()
        fields = {
            "format_version": FORMAT_VERSION,
            **self.fields,
            "missing_splits": self.fields.get("missing_splits", {}),
            "splits": self._splits,
        }
        fields = json.loads(json.dumps(fields))  # hashed exactly as it will be read back
        manifest = {**fields, "content_hash": _content_hash({**fields, "complete": True}), "complete": True}
        (self.tmp_dir / "manifest.json").write_text(json.dumps(manifest, indent=1))
        old = None
        if self.out_dir.exists():
            old = Path(tempfile.mkdtemp(prefix=owned_prefix(self._prefix("old")), dir=self.out_dir.parent))
            os.replace(self.out_dir, old / "cache")
        os.replace(self.tmp_dir, self.out_dir)
        if old is not None:
            shutil.rmtree(old)
        return Cache(self.out_dir, manifest)

    def _prefix(self, kind: str) -> str:
        """The start of a working folder's name beside the cache: ``tmp`` (being written), ``old`` (being replaced)."""
        return f".{self.out_dir.name}.{kind}-"

    def _remove_stale(self) -> None:
        """Delete the working folders that a writer of this cache killed before it cleaned up left beside it."""
        removed = [p for kind in ("tmp", "old") for p in remove_stale_folders(self.out_dir.parent, self._prefix(kind))]
        if removed:
            log.info(f"removed {len(removed)} folder(s) left by an interrupted build of {self.out_dir}: "
                     f"{', '.join(p.name for p in removed)}")

    def _describe(self, file_name: str) -> dict:
        path = self.tmp_dir / file_name
        return {"name": file_name, "bytes": path.stat().st_size, "sha256": file_sha256(path)}

    def abort(self) -> None:
        self._arrays.clear()
        shutil.rmtree(self.tmp_dir, ignore_errors=True)

    def __enter__(self) -> CacheWriter:
        return self

    @property
    def _what(self) -> str:
        return f"writing the cache {self.out_dir.name}"

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            return
        problem = disk_error(exc, self._what, self.out_dir.parent) if isinstance(exc, Exception) else None
        self.abort()
        if problem is not None:
            raise problem from exc


def write_cache(out_dir: Path, manifest_fields: Mapping, splits: Mapping[str, CacheSplit]) -> Cache:
    """Write in-memory splits (``{split name: CacheSplit}``) as a cache; see :class:`CacheWriter`
    for ``manifest_fields``. Large datasets should stream through :class:`CacheWriter` instead."""
    with CacheWriter(out_dir, manifest_fields) as writer:
        for name, split in splits.items():
            points, normals = writer.add_split(
                name, split.points.shape, split.labels, split.shape_names, normals=split.normals is not None
            )
            points[:] = split.points
            if normals is not None:
                normals[:] = split.normals
        return writer.commit()
