"""Readers for the archive layouts of :mod:`src.data.datasets`, each from a folder or straight from its .zip.

* ``princeton_off``: the Princeton mesh archive ``ModelNet40/<category>/{train,test}/<name>.off``.
* ``pointnet_h5``: PointNet's ``modelnet40_ply_hdf5_2048`` (``ply_data_{train,test}*.h5``).
* ``pointnet2_resampled``: PointNet++'s ``modelnet40_normal_resampled`` (the full archive or any
  subset of its category folders).
* ``per_shape_npy``: one ``.npy`` a shape, ``<category>/{train,test}/<category>_NNNN.npy``.
* ``scan_meshes``: any folder of ``.off`` / ``.ply`` scans.

A reader lists its shapes as :class:`ShapeEntry` per split (``entries``), reports the splits it
cannot build (``missing``) and loads one entry at a time (``load``). Readers are picklable, so
process-pool workers can load entries themselves. :class:`MergedReader` reads several archives of
one layout (e.g. one zip per category) as one.
"""

from __future__ import annotations

import io
import json
from collections import Counter
import os
import re
import zipfile
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath

import h5py
import numpy as np

from src.data.categories import MODELNET40_CATEGORIES
from src.data.datasets import read_sources
from src.data.mesh import MeshShape
from src.utils.errors import DatasetError

LAYOUTS: tuple[str, ...] = tuple(s.layout for s in read_sources())
SPLITS: tuple[str, ...] = ("train", "test")
MISSING_EXAMPLES = 10
"""How many missing shape ids a :class:`MissingSplit` keeps per category (the message shows the first 5)."""
SHAPE_ID = re.compile(r"(.+)_\d+")
"""A ModelNet40 shape id, ``<category>_<number>``."""
ZIP_SIGNATURES: tuple[bytes, ...] = (b"PK\x03\x04", b"PK\x05\x06")
"""How a .zip file starts (a local file header, or the end record of an empty archive)."""


@dataclass(frozen=True)
class PointShape:
    """A shape given as points (no mesh): ``points`` and optional ``normals`` are ``(N, 3)`` float32."""

    name: str
    category: str
    split: str
    points: np.ndarray
    normals: np.ndarray | None


@dataclass(frozen=True)
class ShapeEntry:
    """Where one shape lives: archive member (and row ``index`` inside it, for h5 files)."""

    name: str
    category: str
    split: str
    member: str
    index: int = 0
    source: int = 0
    """Which archive of a :class:`MergedReader` holds it."""


@dataclass(frozen=True)
class MissingSplit:
    """A split that cannot be built. ``by_category`` maps each category whose listed shape ids lack
    a file to ``{"missing": n, "listed": m, "examples": first ids}`` (``listed``: shapes the split
    lists in all); both are empty for a split without any shape (``message`` says which)."""

    split: str
    message: str
    by_category: dict[str, dict] = field(default_factory=dict)
    listed: int = 0

    @classmethod
    def of_files(cls, split: str, listed: int, by_category: dict[str, dict], sources: list[str]) -> MissingSplit:
        """Listed shapes without a file in ``sources``."""
        count = sum(gap["missing"] for gap in by_category.values())
        details = "; ".join(
            f"{category}: {gap['missing']} of {gap['listed']}, first: {_shown(gap['examples'])}"
            for category, gap in by_category.items()
        )
        message = (
            f"split '{split}' is not built: {count} of {listed} shapes listed in its split list are missing "
            f"from {', '.join(sources)} ({details})"
        )
        return cls(split, message, by_category, listed)

    @property
    def count(self) -> int:
        return sum(gap["missing"] for gap in self.by_category.values())

    def to_json(self) -> dict:
        examples = [name for gap in self.by_category.values() for name in gap["examples"]][:MISSING_EXAMPLES]
        return {"count": self.count, "examples": examples, "by_category": self.by_category, "message": self.message}


def _shown(ids: list[str], limit: int = 5) -> str:
    return ", ".join(ids[:limit]) + (", ..." if len(ids) > limit else "")


def check_split_identities(entries: dict[str, list[ShapeEntry]], lists: dict[str, str]) -> None:
    """DatasetError when a shape id is listed twice in one split, or in two splits (a train/test leak
    the index-based guard of the datamodule cannot see); ``lists`` names each split's list or folder."""
    seen: dict[str, str] = {}
    for split, split_entries in entries.items():
        counts = Counter(entry.name for entry in split_entries)
        twice = [name for name, count in counts.items() if count > 1]
        if twice:
            raise DatasetError(f"{lists[split]} lists {len(twice)} shape ids more than once (first: {_shown(twice)}): "
                               "list each shape once")
        both = [name for name in counts if name in seen]
        if both:
            raise DatasetError(
                f"{len(both)} shapes are listed in both {lists[seen[both[0]]]} and {lists[split]} (first: {_shown(both)}): "
                "a shape in two splits leaks the test set into training; list each shape in one split"
            )
        seen.update((name, split) for name in counts)


class Archive:
    """A folder or a .zip file, read by POSIX paths relative to it (no extraction to disk)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        if not self.path.exists():
            raise DatasetError(f"source {self.path} does not exist")
        single = self.path.is_file() and self.path.suffix.lower() in (".off", ".ply")
        self.is_zip = self.path.is_file() and not single
        if self.is_zip and not zipfile.is_zipfile(self.path):
            if _starts_like_zip(self.path):
                raise self._damaged("its end-of-archive record is missing: truncated?")
            raise DatasetError(f"source {self.path} is neither a folder, a .zip archive nor an .off/.ply scan")
        if single:  # one scan file: an archive of that file alone, read from its folder
            names, self.path = [self.path.name], self.path.parent
        else:
            names = self._zip().namelist() if self.is_zip else self._walk()
        self.files: list[str] = sorted(n for n in names if not n.endswith("/") and not _is_junk(n))
        self.file_set = frozenset(self.files)

    def _walk(self) -> list[str]:
        """Every file under the folder (anything that is no regular file refused: :meth:`_refuse_irregular`)."""
        names = [Path(folder, f).relative_to(self.path).as_posix()
                 for folder, _, files in os.walk(self.path) for f in files]
        for name in names:
            self._refuse_irregular(name)
        return names

    def _refuse_irregular(self, name: str) -> None:
        """DatasetError when ``name`` in the folder is there but no regular file (links followed): a FIFO, a socket or
        a device, which reading could block on or never finish, a folder, or a link to nothing."""
        path = self.path / name
        if path.is_file() or not (path.exists() or path.is_symlink()):
            return
        kinds = (("a FIFO", path.is_fifo), ("a socket", path.is_socket), ("a device", path.is_char_device),
                 ("a device", path.is_block_device), ("a folder", path.is_dir))
        kind = next((kind for kind, test in kinds if test()), "a link to nothing")
        raise DatasetError(f"source {self.path}: {name} is {kind}, not a regular file: remove it from the folder")

    def _zip(self) -> zipfile.ZipFile:
        if getattr(self, "_handle", None) is None:
            try:
                self._handle = zipfile.ZipFile(self.path)
            except zipfile.BadZipFile as e:
                raise self._damaged(str(e)) from e
        return self._handle

    def read(self, name: str) -> bytes:
        if not self.is_zip:
            self._refuse_irregular(name)
        try:
            return self._zip().read(name) if self.is_zip else (self.path / name).read_bytes()
        except (zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise self._damaged(f"{name}: {e}") from e
        except (RuntimeError, NotImplementedError) as e:  # zipfile: a password needed, a method it cannot decompress
            if not self.is_zip:
                raise
            info = self._zip().getinfo(name)
            if info.flag_bits & 0x1:
                problem = "is encrypted: unpack the archive with its password and pass the folder, or zip it again without one"
            else:
                method = zipfile.compressor_names.get(info.compress_type, "unknown")
                problem = (f"is compressed with method {info.compress_type} ({method}), which Python's zipfile cannot "
                           "read: unpack the archive with a tool that can (7z x) and pass the folder, or zip it again "
                           "with deflate")
            raise DatasetError(f"{name} in {self.path} {problem}") from e
        except (KeyError, OSError) as e:
            raise DatasetError(f"cannot read {name} from {self.path}: {e}") from e

    def _damaged(self, detail: str) -> DatasetError:
        return DatasetError(f"source {self.path} is a damaged .zip archive ({detail}); download or copy it again")

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_handle"}


def _starts_like_zip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(4) in ZIP_SIGNATURES


def _is_junk(name: str) -> bool:
    """macOS metadata that zip tools add (``__MACOSX/``, ``._file``)."""
    return any(part == "__MACOSX" or part.startswith("._") for part in name.split("/"))


def _join(root: str, *parts: str) -> str:
    return str(PurePosixPath(root, *parts)) if root else str(PurePosixPath(*parts))


def _parent(name: str) -> str:
    """The folder of an archive path, ``""`` at the top level."""
    return name.rpartition("/")[0]


def _lines(data: bytes, name: str) -> list[str]:
    """The non-blank lines of a UTF-8 list (a byte-order mark ignored); DatasetError naming ``name`` if it is not UTF-8."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise DatasetError(f"{name} is not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start}): save it as "
                           "UTF-8") from None
    return [s for line in text.splitlines() if (s := line.strip())]


class Reader:
    """Common interface: ``categories`` present (label = index), ``entries`` per buildable split,
    ``missing`` splits and ``load``."""

    layout: str
    """Its layout, as :data:`READERS` (from :mod:`src.data.datasets`) names it."""

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        """Whether ``archive`` is in this reader's layout."""
        raise NotImplementedError

    def __init__(self, archive: Archive):
        self.archive = archive
        self.categories: list[str] = []
        self.entries: dict[str, list[ShapeEntry]] = {}
        self.missing: dict[str, MissingSplit] = {}

    @property
    def where(self) -> str:
        """The source(s) read, for messages."""
        return str(self.archive.path)

    def split_list(self, split: str) -> str:
        """Where ``split`` is listed, for messages."""
        return f"the {split} split of {self.where}"

    def _set_splits(self, entries: dict[str, list[ShapeEntry]]) -> None:
        """Keep non-empty splits; an empty split is reported as missing, never dropped silently."""
        for split in SPLITS:
            if entries.get(split):
                self.entries[split] = entries[split]
            elif split not in self.missing:
                message = f"split '{split}' is not available: {self.where} has no {split} shapes"
                self.missing[split] = MissingSplit(split, message)

    def load(self, entry: ShapeEntry) -> MeshShape | PointShape:
        raise NotImplementedError

    def iter_shapes(self, split: str, limit: int | None = None) -> Iterator[MeshShape | PointShape]:
        """Load the shapes of a buildable split in order (the first ``limit`` only, if given)."""
        if split in self.missing:
            raise DatasetError(self.missing[split].message)
        for entry in self.entries[split][:limit]:
            yield self.load(entry)


# --- Princeton OFF meshes -------------------------------------------------------------------

_OFF_HEADER = re.compile(r"\s*OFF\s*(\d+)\s+(\d+)\s+(\d+)")


def parse_off(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse an OFF file into ``(vertices (V,3) float64, faces (F,3) int64)``.

    Handles the header glued to the counts (``OFF490 518 0``), comments and blank lines, and
    polygons with more than 3 vertices (fan-triangulated). Triangle meshes are parsed in one
    vectorised pass.
    """
    text = data.decode("latin-1")
    if "#" in text:
        text = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    header = _OFF_HEADER.match(text)
    if header is None:
        raise DatasetError(f"{name}: not an OFF file (expected 'OFF' and the vertex/face/edge counts)")
    num_vertices, num_faces = int(header[1]), int(header[2])
    body = text[header.end():]
    try:
        values = np.fromstring(body, sep=" ")
    except ValueError as e:
        raise DatasetError(f"{name}: malformed OFF body ({e})") from e
    if values.size < 3 * num_vertices + 4 * num_faces:
        raise DatasetError(f"{name}: truncated OFF file (header announces {num_vertices} vertices, {num_faces} faces)")
    vertices = values[: 3 * num_vertices].reshape(-1, 3)
    face_values = values[3 * num_vertices:]
    if face_values.size == 4 * num_faces and np.all(face_values[::4] == 3):
        faces = face_values.reshape(-1, 4)[:, 1:].astype(np.int64)
    else:
        faces = _polygon_faces(body, num_vertices, num_faces, name)
    if faces.size and (faces.min() < 0 or faces.max() >= num_vertices):
        raise DatasetError(f"{name}: face index out of range for {num_vertices} vertices")
    return vertices, faces


def _polygon_faces(body: str, num_vertices: int, num_faces: int, name: str) -> np.ndarray:
    """Fan-triangulate general polygon lines ``n i1 ... in [colour...]`` (one face per line)."""
    lines = [line.split() for line in body.splitlines() if line.strip()]
    face_lines = lines[num_vertices: num_vertices + num_faces]
    if len(face_lines) != num_faces:
        raise DatasetError(f"{name}: expected {num_faces} face lines, found {len(face_lines)}")
    triangles = []
    for tokens in face_lines:
        n = int(tokens[0])
        if n < 3 or len(tokens) < n + 1:
            raise DatasetError(f"{name}: malformed face line {' '.join(tokens)!r}")
        poly = np.asarray(tokens[1: n + 1], dtype=np.int64)
        triangles.append(np.stack([np.full(n - 2, poly[0]), poly[1:-1], poly[2:]], axis=1))
    return np.concatenate(triangles)


class PrincetonOffReader(Reader):
    """``<...>/<category>/{train,test}/<name>.off`` meshes; yields :class:`MeshShape`."""

    PATTERN = re.compile(r"(?:^|/)([^/]+)/(train|test)/([^/]+)\.off$", re.IGNORECASE)

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        return any(cls.PATTERN.search(f) for f in archive.files)

    def __init__(self, archive: Archive):
        super().__init__(archive)
        self.categories, entries, _ = _entries_by_folder(archive, self.PATTERN)
        self._set_splits(entries)

    def load(self, entry: ShapeEntry) -> MeshShape:
        vertices, faces = parse_off(self.archive.read(entry.member), entry.member)
        return MeshShape(entry.name, entry.category, entry.split, vertices, faces)


def _entries_by_folder(archive: Archive, pattern: re.Pattern) -> tuple[list[str], dict[str, list[ShapeEntry]], set[str]]:
    """The categories, per split the entries (category, then name order) and the roots (the folders holding the
    category folders) of the files ``pattern`` matches as ``<category>/<split>/<name>.<suffix>``."""
    matches = [(m, f) for f in archive.files if (m := pattern.search(f))]
    categories = _ordered({m[1] for m, _ in matches})
    entries: dict[str, list[ShapeEntry]] = {s: [] for s in SPLITS}
    for m, f in sorted(matches, key=lambda mf: (categories.index(mf[0][1]), mf[0][3])):
        entries[m[2].lower()].append(ShapeEntry(m[3], m[1], m[2].lower(), f))
    return categories, entries, {_parent(_parent(_parent(f))) for _, f in matches}


def _ordered(categories: set[str]) -> list[str]:
    """ModelNet40 order first, then any other category names sorted."""
    known = [c for c in MODELNET40_CATEGORIES if c in categories]
    return known + sorted(categories - set(known))


# --- PointNet h5 ----------------------------------------------------------------------------


class PointNetH5Reader(Reader):
    """``ply_data_{train,test}<k>.h5`` (``data`` (B,2048,3), ``label`` (B,1), optional ``normal``)
    plus ``shape_names.txt``; shape ids come from ``ply_data_<split>_<k>_id2file.json`` when present."""

    PATTERN = re.compile(r"(?:^|/)ply_data_(train|test)(\d*)\.h5$")

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        return any(cls.PATTERN.search(f) for f in archive.files)

    def __init__(self, archive: Archive):
        super().__init__(archive)
        files = sorted(
            ((m[1], int(m[2] or 0), f) for f in archive.files if (m := self.PATTERN.search(f))),
        )
        root = _parent(files[0][2])
        names_file = _join(root, "shape_names.txt")
        if names_file not in archive.file_set:
            raise DatasetError(f"{archive.path}: {names_file} not found next to the ply_data_*.h5 files")
        shape_names = _lines(archive.read(names_file), names_file)
        self._cached: tuple[str, dict[str, np.ndarray]] | None = None
        entries: dict[str, list[ShapeEntry]] = {s: [] for s in SPLITS}
        for split, k, member in files:
            labels = self._arrays(member)["label"].reshape(-1)
            if labels.size and (labels.min() < 0 or labels.max() >= len(shape_names)):
                raise DatasetError(f"{member}: labels outside the {len(shape_names)} names of {names_file}")
            ids = self._shape_ids(_join(root, f"ply_data_{split}_{k}_id2file.json"), len(labels))
            for i, label in enumerate(labels):
                category = shape_names[label]
                name = ids[i] if ids else f"{category}_{split}{k}_{i:04d}"
                entries[split].append(ShapeEntry(name, category, split, member, i))
        present = {e.category for split_entries in entries.values() for e in split_entries}
        self.categories = [c for c in shape_names if c in present]
        self._set_splits(entries)

    def _shape_ids(self, json_file: str, count: int) -> list[str] | None:
        if json_file not in self.archive.file_set:
            return None
        ids = json.loads(self.archive.read(json_file))
        if not isinstance(ids, list) or len(ids) != count:
            raise DatasetError(f"{json_file}: expected a list of {count} file names")
        return [PurePosixPath(i).stem for i in ids]

    def _arrays(self, member: str) -> dict[str, np.ndarray]:
        """All datasets of one h5 file (the last file read stays cached)."""
        if self._cached is None or self._cached[0] != member:
            source = io.BytesIO(self.archive.read(member)) if self.archive.is_zip else self.archive.path / member
            try:
                with h5py.File(source, "r") as f:
                    arrays = {k: f[k][()] for k in ("data", "label", "normal") if k in f}
            except OSError as e:
                raise DatasetError(f"{member}: unreadable h5 file ({e})") from e
            if "data" not in arrays or "label" not in arrays:
                raise DatasetError(f"{member}: expected h5 datasets 'data' and 'label'")
            self._cached = (member, arrays)
        return self._cached[1]

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_cached": None}

    def load(self, entry: ShapeEntry) -> PointShape:
        arrays = self._arrays(entry.member)
        points = arrays["data"][entry.index].astype(np.float32)
        normals = arrays["normal"][entry.index].astype(np.float32) if "normal" in arrays else None
        return PointShape(entry.name, entry.category, entry.split, points, normals)


# --- PointNet++ normal_resampled ------------------------------------------------------------


def parse_resampled(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse ``x,y,z,nx,ny,nz`` lines into ``(points, normals)``, both ``(N, 3)`` float32.

    A malformed or non-finite line raises :class:`DatasetError` naming the file and line number.
    """
    try:
        values = np.loadtxt(io.BytesIO(data), delimiter=",", dtype=np.float32, ndmin=2)
        ok = values.shape[1] == 6 and np.isfinite(values).all()
    except ValueError:
        ok = False
    if not ok or len(values) == 0:
        raise DatasetError(f"{name}: {_first_bad_line(data)}")
    return values[:, :3], values[:, 3:]


FLOAT32_MAX = float(np.finfo(np.float32).max)


def _first_bad_line(data: bytes) -> str:
    """Describe the first line that is not 6 comma-separated numbers finite in float32 (error path only)."""
    for number, line in enumerate(data.decode("utf-8-sig", errors="replace").splitlines(), start=1):
        if line.strip() and (problem := _line_problem(line.strip())):
            return f"line {number} {problem}: {line.strip()[:80]!r}"
    return "no points (empty file)"


def _line_problem(line: str) -> str | None:
    """Why one ``x,y,z,nx,ny,nz`` line cannot be stored as float32, or ``None``."""
    fields = [v.strip() for v in line.split(",")]
    try:
        values = [float(v) for v in fields]
    except ValueError:
        values = []
    if len(values) != 6:
        return "is malformed, expected 'x,y,z,nx,ny,nz'"
    for text, value in zip(fields, values):
        if not np.isfinite(value):
            return f"has the non-finite value {text}"
        if abs(value) > FLOAT32_MAX:
            return f"has the value {text}, beyond float32's range (|v| <= {FLOAT32_MAX:.3g})"
    return None


class ResampledReader(Reader):
    """``modelnet40_shape_names.txt``, ``modelnet40_{train,test}.txt`` and ``<category>/<id>.txt``.

    Categories whose folder is absent are not part of the archive; a split whose list names
    absent files of present categories is reported in ``missing`` (per category: count + first ids).
    """

    NAMES_FILE = "modelnet40_shape_names.txt"

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        return any(PurePosixPath(f).name == cls.NAMES_FILE for f in archive.files)

    def __init__(self, archive: Archive):
        super().__init__(archive)
        names_file = min((f for f in archive.files if PurePosixPath(f).name == self.NAMES_FILE), key=len)
        root = _parent(names_file)
        self.root = root
        named = _lines(archive.read(names_file), names_file)
        folders = {_parent(f).removeprefix(f"{root}/" if root else "") for f in archive.files if f.endswith(".txt")}
        unknown = sorted(f for f in folders - set(named) if f and f != root and "/" not in f)
        if unknown:
            raise DatasetError(f"{archive.path}: the folders {', '.join(unknown)} hold shapes of categories that {names_file} "
                               "does not name: add them to it, or remove the folders")
        self.categories = [c for c in named if c in folders]
        if not self.categories:
            raise DatasetError(f"{archive.path}: none of the categories of {names_file} has a folder")
        entries: dict[str, list[ShapeEntry]] = {}
        for split in SPLITS:
            list_file = _join(root, f"modelnet40_{split}.txt")
            if list_file not in archive.file_set:
                continue
            listed = [(shape_id, self._category(shape_id, list_file))
                      for shape_id in _lines(archive.read(list_file), list_file)]
            strays = sorted({category for _, category in listed} - set(named))
            if strays:
                raise DatasetError(f"{archive.path}: {list_file} lists shapes of categories that {names_file} does not "
                                   f"name ({', '.join(strays)}): a list of another dataset?")
            entries[split] = [
                ShapeEntry(shape_id, category, split, _join(root, category, f"{shape_id}.txt"))
                for shape_id, category in listed
                if category in self.categories
            ]
            gaps = _missing_files(entries[split], archive.file_set)
            if gaps:
                self.missing[split] = MissingSplit.of_files(split, len(entries[split]), gaps, [self.where])
                del entries[split]
        self._set_splits(entries)

    def split_list(self, split: str) -> str:
        return f"{_join(self.root, f'modelnet40_{split}.txt')} of {self.where}"

    def _category(self, shape_id: str, list_file: str) -> str:
        match = SHAPE_ID.fullmatch(shape_id)
        if match is None:
            raise DatasetError(f"{list_file}: shape id {shape_id!r} is not '<category>_<number>'")
        return match[1]

    def load(self, entry: ShapeEntry) -> PointShape:
        points, normals = parse_resampled(self.archive.read(entry.member), entry.member)
        return PointShape(entry.name, entry.category, entry.split, points, normals)


# --- one NumPy file a shape -----------------------------------------------------------------


def parse_npy(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """An ``(N, 3)`` (points) or ``(N, 6)`` (points, normals) ``.npy`` array as float32 ``(points, normals)``.

    Anything else (not a .npy file, pickled objects, another shape, a non-numeric or non-finite value)
    raises :class:`DatasetError` naming the file.
    """
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise DatasetError(f"{name}: not a readable .npy array ({e}); replace the file or remove it") from None
    if not isinstance(array, np.ndarray) or array.ndim != 2 or array.shape[1] not in (3, 6) or len(array) == 0:
        raise DatasetError(f"{name}: holds an array of shape {getattr(array, 'shape', '?')}, expected (N, 3) points "
                           "or (N, 6) points and normals")
    if array.dtype.kind not in "fiu":
        raise DatasetError(f"{name}: holds {array.dtype} values, expected numbers")
    values = array.astype(np.float32)
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if bad.size:
        raise DatasetError(f"{name}: {bad.size} rows hold non-finite values (first: row {bad[0]}: {array[bad[0]]}); "
                           "replace the file")
    return values[:, :3], values[:, 3:] if values.shape[1] == 6 else None


class NumpyShapeReader(Reader):
    """``<...>/<category>/{train,test}/<category>_NNNN.npy``, one shape a file; yields :class:`PointShape`.

    ``withheld_test_ids.txt`` beside the category folders, when present, lists test ids left out of
    the archive: a split whose listed ids lack a file is not built and is reported (per category: count
    and first ids).
    """

    PATTERN = re.compile(r"(?:^|/)([^/]+)/(train|test)/([^/]+)\.npy$", re.IGNORECASE)
    WITHHELD = "withheld_test_ids.txt"

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        return any(cls.PATTERN.search(f) for f in archive.files)

    def __init__(self, archive: Archive):
        super().__init__(archive)
        self.categories, entries, roots = _entries_by_folder(archive, self.PATTERN)
        if len(roots) > 1:
            raise DatasetError(f"{archive.path}: .npy shapes under several roots ({', '.join(sorted(roots))}): "
                               "give one dataset folder")
        self.root = roots.pop()
        withheld = self._withheld()
        if withheld:
            present = {e.name for e in entries["test"]}
            listed = entries["test"] + [
                ShapeEntry(name, category, "test", _join(self.root, category, "test", f"{name}.npy"))
                for name, category in withheld if name not in present and category in self.categories
            ]
            gaps = _missing_files(listed, archive.file_set)
            if gaps:
                self.missing["test"] = MissingSplit.of_files("test", len(listed), gaps, [self.where])
                del entries["test"]
        self._set_splits(entries)

    def _withheld(self) -> list[tuple[str, str]]:
        """``(id, category)`` of the ids ``withheld_test_ids.txt`` lists (none without the file)."""
        list_file = _join(self.root, self.WITHHELD)
        if list_file not in self.archive.file_set:
            return []
        ids = _lines(self.archive.read(list_file), list_file)
        malformed = [i for i in ids if not SHAPE_ID.fullmatch(i)]
        if malformed:
            raise DatasetError(f"{list_file}: shape id {malformed[0]!r} is not '<category>_<number>'")
        return [(i, SHAPE_ID.fullmatch(i)[1]) for i in ids]

    def split_list(self, split: str) -> str:
        return f"the {split} folders of {self.where}"

    def load(self, entry: ShapeEntry) -> PointShape:
        points, normals = parse_npy(self.archive.read(entry.member), entry.member)
        return PointShape(entry.name, entry.category, entry.split, points, normals)


def _missing_files(entries: list[ShapeEntry], files: frozenset[str]) -> dict[str, dict]:
    """Per category of ``entries`` with absent members: ``{"missing", "listed", "examples"}``."""
    gaps: dict[str, dict] = {}
    for entry in entries:
        gap = gaps.setdefault(entry.category, {"missing": 0, "listed": 0, "examples": []})
        gap["listed"] += 1
        if entry.member not in files:
            gap["missing"] += 1
            if len(gap["examples"]) < MISSING_EXAMPLES:
                gap["examples"].append(entry.name)
    return {category: gap for category, gap in gaps.items() if gap["missing"]}


# --- real scans (Stanford 3D Scanning Repository style) --------------------------------------


class ScanMeshReader(Reader):
    """Any folder (or .zip) of ``.off`` / ``.ply`` scan meshes, or one such file; each scan is its own
    category and everything is the ``test`` split (scans are for evaluation without fine-tuning)."""

    SUFFIXES = (".off", ".ply")

    @classmethod
    def detects(cls, archive: Archive) -> bool:
        return any(f.lower().endswith(cls.SUFFIXES) for f in archive.files)

    def __init__(self, archive: Archive):
        super().__init__(archive)
        members = [f for f in archive.files if f.lower().endswith(self.SUFFIXES)]
        if not members:
            raise DatasetError(f"{archive.path} holds no .off or .ply scan")
        names = [PurePosixPath(f).stem for f in members]
        if len(set(names)) != len(names):
            raise DatasetError(f"{archive.path}: two scans share a file name: {sorted(names)}")
        self.categories = sorted(names)
        self._set_splits({"test": [ShapeEntry(n, n, "test", f) for n, f in sorted(zip(names, members))]})
        self.missing.pop("train", None)  # scans have no train split by design

    def load(self, entry: ShapeEntry) -> MeshShape:
        data = self.archive.read(entry.member)
        if entry.member.lower().endswith(".off"):
            vertices, faces = parse_off(data, entry.member)
        else:
            vertices, faces = _parse_ply(data, entry.member)
        return MeshShape(entry.name, entry.category, entry.split, vertices, faces)


def _parse_ply(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray]:
    """A triangle mesh from PLY bytes (ASCII or binary), through Open3D."""
    import tempfile

    import open3d as o3d

    with tempfile.NamedTemporaryFile(suffix=".ply") as handle:
        handle.write(data)
        handle.flush()
        mesh = o3d.io.read_triangle_mesh(handle.name)
    vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)
    if len(vertices) == 0 or len(faces) == 0:
        raise DatasetError(f"{name}: no triangle mesh found (point-only PLY files are not supported)")
    return vertices, faces


# --- several archives as one ------------------------------------------------------------------


class MergedReader(Reader):
    """Several readers of one layout (e.g. one .zip per category) as one: the categories of all in
    ModelNet40 order, each split their shapes by category. A split that misses listed files in any
    source is not built and is reported per category; a shape id in two sources is refused."""

    def __init__(self, readers: list[Reader]):
        self.readers = readers
        self.layout = readers[0].layout
        self.categories = _ordered({c for r in readers for c in r.categories})
        self.entries, self.missing = {}, {}
        for split in SPLITS:
            gaps = [r.missing[split] for r in readers if split in r.missing and r.missing[split].count]
            if gaps:
                self.missing[split] = self._merged_gaps(split, gaps)
            elif any(split in r.entries for r in readers):
                self.entries[split] = self._merged_entries(split)
            elif any(split in r.missing for r in readers):
                message = f"split '{split}' is not available: none of {self.where} has {split} shapes"
                self.missing[split] = MissingSplit(split, message)

    @property
    def where(self) -> str:
        return ", ".join(r.where for r in self.readers)

    def split_list(self, split: str) -> str:
        return " and ".join(r.split_list(split) for r in self.readers if split in r.entries)

    def _merged_entries(self, split: str) -> list[ShapeEntry]:
        entries = [replace(e, source=i) for i, r in enumerate(self.readers) for e in r.entries.get(split, [])]
        entries.sort(key=lambda e: self.categories.index(e.category))  # stable: each source's order kept
        seen: dict[str, int] = {}
        for entry in entries:
            if seen.setdefault(entry.name, entry.source) != entry.source:
                where = (self.readers[seen[entry.name]].where, self.readers[entry.source].where)
                raise DatasetError(f"shape {entry.name} ({split}) is in two sources: {where[0]} and {where[1]}")
        return entries

    def _merged_gaps(self, split: str, gaps: list[MissingSplit]) -> MissingSplit:
        by_category: dict[str, dict] = {}
        for category in self.categories:
            parts = [g.by_category[category] for g in gaps if category in g.by_category]
            if parts:
                examples = [name for part in parts for name in part["examples"]][:MISSING_EXAMPLES]
                by_category[category] = {
                    "missing": sum(p["missing"] for p in parts), "listed": sum(p["listed"] for p in parts),
                    "examples": examples,
                }
        sources = [r.where for r in self.readers if split in r.missing and r.missing[split].count]
        listed = sum(len(r.entries.get(split, [])) for r in self.readers) + sum(g.listed for g in gaps)
        return MissingSplit.of_files(split, listed, by_category, sources)

    def load(self, entry: ShapeEntry) -> MeshShape | PointShape:
        return self.readers[entry.source].load(entry)


_READER_CLASSES = {cls.__name__: cls for cls in Reader.__subclasses__()}
READERS: dict[str, type[Reader]] = {s.layout: _READER_CLASSES[s.reader] for s in read_sources()}
"""The reader of each layout, as :mod:`src.data.datasets` names them (detection order)."""
for _layout, _reader in READERS.items():
    _reader.layout = _layout


# --- layout detection -----------------------------------------------------------------------


def layout_of(archive: Archive) -> str:
    """The layout of an opened archive: the first of :data:`READERS` that detects it."""
    layout = next((layout for layout, reader in READERS.items() if reader.detects(archive)), None)
    if layout is None:
        archives = ", ".join(s.archive for s in read_sources())
        raise DatasetError(
            f"{archive.path} matches no known ModelNet40 layout; expected one of: {archives}, as a folder or .zip"
        )
    return layout


def detect_layout(source: Path) -> str:
    """The layout (one of :data:`LAYOUTS`) of a folder or .zip."""
    return layout_of(Archive(source))


def open_reader(source: Path) -> Reader:
    """The reader for ``source`` (folder or .zip), its layout auto-detected."""
    archive = Archive(source)
    return READERS[layout_of(archive)](archive)
