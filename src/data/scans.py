"""Real range scans with ground-truth poses (Stanford 3D Scanning Repository style) and their pairs.

A scan set is a ``.conf`` file and the PLY range scans it names, in a folder or a .zip (several scan
sets may sit in one source, each in its own folder). The ``.conf`` gives each scan's pose in the
set's common frame, one line per scan::

    bmesh <file> tx ty tz qx qy qz qw

(other lines, e.g. ``camera ...``, are ignored). With R(q) the rotation of the unit quaternion as
written (SciPy's ``Rotation.from_quat`` order), a point p of the scan maps to the common frame as
``R(q)ᵀ·p + t`` (measured on the Stanford Bunny: then 91 % of bun045's points lie within 1 mm of
bun000's; with ``R(q)·p + t`` almost none do). Every PLY beside a ``.conf`` must have a line in it.

Pairs (:func:`scan_pairs`): every ordered pair of scans of one set whose overlap exceeds a threshold.
The overlap of a pair is computed under the ground-truth poses: the smaller of the fractions of each
scan's points within ``overlap_spacing`` × (the larger median point spacing of the two) of the other
scan, so both orders of a pair share it.
"""

from __future__ import annotations

import hashlib
import io
import itertools
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
from scipy.spatial.transform import Rotation

from src.data.readers import Archive
from src.data.transforms import median_spacing, overlap_fraction
from src.utils.errors import DatasetError
from src.geometry.numpy_rigid import apply_transform, inverse_transform, rigid_transform

BMESH_FORMAT = "'bmesh <file> tx ty tz qx qy qz qw'"
UNIT_QUATERNION_TOL = 1e-3
"""Largest accepted | |q| - 1 | (the bunny's are within 4e-7; a typo is far off)."""


@dataclass(frozen=True)
class Scan:
    """One range scan: ``points`` (N, 3) float64 in the scan's own frame; ``pose`` (4, 4) maps them to
    the scan set's common frame."""

    name: str
    points: np.ndarray
    pose: np.ndarray

    def in_common_frame(self) -> np.ndarray:
        return apply_transform(self.pose, self.points)


@dataclass(frozen=True)
class ScanSet:
    """The scans named by one ``.conf`` (``name``: its path inside the source)."""

    name: str
    scans: list[Scan]


@dataclass(frozen=True)
class ScanPair:
    """An ordered pair of scans of ``scan_set``: ``transform`` (4, 4) maps the source scan's frame to the
    reference scan's (``ref ≈ R·src + t``); ``overlap`` as in the module docstring."""

    scan_set: int
    source: int
    reference: int
    overlap: float
    transform: np.ndarray


@dataclass(frozen=True)
class ScanSource:
    """Every scan set of a folder or .zip, with the sha256 of the files read (``content_hash``)."""

    path: Path
    scan_sets: list[ScanSet]
    content_hash: str

    @property
    def manifest(self) -> dict:
        """What the source holds (the grid records ``content_hash`` as it does a dataset cache's)."""
        return {"content_hash": self.content_hash,
                "scan_sets": {s.name: [scan.name for scan in s.scans] for s in self.scan_sets}}


# --- poses ---------------------------------------------------------------------------------------


def conf_pose(translation: np.ndarray, quaternion: np.ndarray, where: str) -> np.ndarray:
    """Scan → common frame from a ``.conf`` line: rotation R(q)ᵀ (q = qx qy qz qw), then + t."""
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > UNIT_QUATERNION_TOL:
        raise DatasetError(f"{where}: the quaternion (qx qy qz qw) {' '.join(f'{v:g}' for v in quaternion)} "
                           f"has norm {norm:.6g}, not a unit quaternion")
    return rigid_transform(Rotation.from_quat(quaternion).as_matrix().T, translation)


def relative_pose(pose_src: np.ndarray, pose_ref: np.ndarray) -> np.ndarray:
    """Source-scan frame → reference-scan frame, from the two scans' poses."""
    return inverse_transform(pose_ref) @ pose_src


# --- reading -------------------------------------------------------------------------------------


def parse_conf(text: str, name: str) -> dict[str, np.ndarray]:
    """``{file: pose}`` from the ``bmesh`` lines of a ``.conf`` (in file order)."""
    poses: dict[str, np.ndarray] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens or tokens[0] != "bmesh":
            continue
        where = f"{name} line {number}"
        try:
            values = np.array(tokens[2:], dtype=np.float64)
        except ValueError:
            values = np.array([])
        if len(tokens) != 9 or not np.isfinite(values).all():
            raise DatasetError(f"{where}: expected {BMESH_FORMAT}, got {line.strip()!r}")
        if tokens[1] in poses:
            raise DatasetError(f"{where}: {tokens[1]} has a second bmesh line")
        poses[tokens[1]] = conf_pose(values[:3], values[3:], where)
    if not poses:
        raise DatasetError(f"{name} has no {BMESH_FORMAT} line")
    return poses


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def _ply_vertex_header(data: bytes, name: str) -> tuple[str, int, list[tuple[str, str]], int]:
    """(format, vertex count, vertex properties [(name, type)], offset of the body) of a PLY file whose
    first element is ``vertex``."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise DatasetError(f"{name}: not a PLY file (expected a 'ply' ... 'end_header' header)")
    fmt, elements = None, []
    for tokens in (line.split() for line in data[:end].decode("ascii", errors="replace").splitlines()):
        if tokens[:1] == ["format"] and len(tokens) > 1:
            fmt = tokens[1]
        elif tokens[:1] == ["element"]:
            if len(tokens) != 3 or not tokens[2].isdigit():
                raise DatasetError(f"{name}: malformed PLY header line {' '.join(tokens)!r}: expected 'element <name> "
                                   "<count>' (e.g. 'element face 0')")
            elements.append((tokens[1], int(tokens[2]), []))
        elif tokens[:1] == ["property"] and elements and len(tokens) >= 3:
            elements[-1][2].append((tokens[-1], "list" if tokens[1] == "list" else tokens[1]))
    if fmt not in _PLY_FORMATS:
        raise DatasetError(f"{name}: unknown PLY format {fmt!r}; expected one of {list(_PLY_FORMATS)}")
    if not elements or elements[0][0] != "vertex" or elements[0][1] == 0:
        raise DatasetError(f"{name}: no vertices (a scan needs 'element vertex <count>' first, with x, y, z properties)")
    _, count, properties = elements[0]
    bad = [t for _, t in properties if t not in _PLY_TYPES]
    if bad or not {"x", "y", "z"} <= {p for p, _ in properties}:
        raise DatasetError(f"{name}: vertex properties must be scalars including x, y, z, got {properties}")
    return fmt, count, properties, data.index(b"\n", end) + 1


def parse_ply_points(data: bytes, name: str) -> np.ndarray:
    """The vertices (N, 3) float64 of a PLY file, ASCII or binary (faces, range grids and any other element
    after the vertices are ignored)."""
    fmt, count, properties, offset = _ply_vertex_header(data, name)
    names = [p for p, _ in properties]
    columns = [names.index(axis) for axis in "xyz"]
    try:
        if fmt == "ascii":
            values = np.loadtxt(io.BytesIO(data[offset:]), max_rows=count, usecols=columns, ndmin=2)
        else:
            dtype = np.dtype([(p, _PLY_FORMATS[fmt] + _PLY_TYPES[t]) for p, t in properties])
            rows = np.frombuffer(data, dtype, count=count, offset=offset)
            values = np.stack([rows[axis] for axis in "xyz"], axis=1).astype(np.float64)
    except ValueError as err:
        raise DatasetError(f"{name}: malformed vertex data ({str(err).splitlines()[0]})") from None
    if len(values) != count:
        raise DatasetError(f"{name}: truncated, {len(values)} of the {count} vertices the header announces")
    if not np.isfinite(values).all():
        raise DatasetError(f"{name}: vertices with NaN or inf coordinates")
    return values


def _members(conf: str, poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``{archive member: pose}``: the ``.conf``'s file names are relative to its folder."""
    folder = PurePosixPath(conf).parent
    return {(folder / file).as_posix(): pose for file, pose in poses.items()}


def _check_members(archive: Archive, entries: dict[str, dict[str, np.ndarray]]) -> None:
    """Every scan a ``.conf`` names exists, and every PLY in a ``.conf``'s folder has a pose in one of
    that folder's ``.conf`` files."""
    listed: dict[PurePosixPath, set[str]] = {}
    for conf, members in entries.items():
        absent = [m for m in members if m not in archive.file_set]
        if absent:
            raise DatasetError(f"{conf} names scans missing from {archive.path}: {', '.join(absent)}")
        if len(members) < 2:
            raise DatasetError(f"{conf} names one scan: a scan set needs two or more to make pairs")
        listed.setdefault(PurePosixPath(conf).parent, set()).update(members)
    unlisted = [f for f in archive.files if f.lower().endswith(".ply")
                and PurePosixPath(f).parent in listed and f not in listed[PurePosixPath(f).parent]]
    if unlisted:
        raise DatasetError(f"{', '.join(unlisted)}: no bmesh line in the .conf of its folder "
                           f"(add {BMESH_FORMAT} or move the file out)")


def read_scans(source: str | Path) -> ScanSource:
    """Every scan set (a ``.conf`` and its PLY scans) of a folder or .zip."""
    archive = Archive(source)
    confs = [f for f in archive.files if f.lower().endswith(".conf")]
    if not confs:
        raise DatasetError(f"{source} holds no .conf file: expected PLY range scans with a Stanford-style .conf "
                           f"({BMESH_FORMAT} per scan)")
    digest = hashlib.sha256()
    entries = {}
    for conf in confs:
        data = archive.read(conf)
        digest.update(data)
        entries[conf] = _members(conf, parse_conf(data.decode("utf-8-sig", errors="replace"), conf))
    _check_members(archive, entries)
    scan_sets = []
    for conf, members in entries.items():
        scans = []
        for member, pose in members.items():
            data = archive.read(member)
            digest.update(data)
            scans.append(Scan(PurePosixPath(member).stem, parse_ply_points(data, member), pose))
        scan_sets.append(ScanSet(conf, scans))
    return ScanSource(Path(source), scan_sets, digest.hexdigest())


# --- pairs ---------------------------------------------------------------------------------------


def scan_pairs(scan_sets: list[ScanSet], min_overlap: float, overlap_spacing: float) -> list[ScanPair]:
    """Every ordered pair of scans of one set whose overlap exceeds ``min_overlap``, ordered by scan set,
    source, reference (the order of the ``.conf`` lines)."""
    pairs = []
    for k, scan_set in enumerate(scan_sets):
        scans = scan_set.scans
        common = [scan.in_common_frame() for scan in scans]
        spacing = [median_spacing(scan.points) for scan in scans]
        overlaps = {}
        for i, j in itertools.combinations(range(len(scans)), 2):
            radius = overlap_spacing * max(spacing[i], spacing[j])
            overlaps[i, j] = overlaps[j, i] = min(overlap_fraction(common[i], common[j], radius),
                                                  overlap_fraction(common[j], common[i], radius))
        pairs += [ScanPair(k, i, j, overlaps[i, j], relative_pose(scans[i].pose, scans[j].pose))
                  for i, j in itertools.permutations(range(len(scans)), 2) if overlaps[i, j] > min_overlap]
    return pairs


def shared_similarity(src: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, float]:
    """One centre and scale for both clouds: the centroid of their union and its largest distance from it
    (the union then fits the unit sphere)."""
    union = np.concatenate([src, ref])
    centre = union.mean(axis=0)
    return centre, float(np.linalg.norm(union - centre, axis=1).max())


def normalise_pair(src: np.ndarray, ref: np.ndarray, transform: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both clouds mapped by the same similarity ``x → (x - c) / s`` (:func:`shared_similarity`), and the
    source → reference transform in the new coordinates: the same rotation, translation (R·c + t - c) / s."""
    centre, scale = shared_similarity(src, ref)
    if scale <= 0:
        raise DatasetError("a scan pair whose points all coincide cannot be normalised")
    normalised = transform.copy()
    normalised[:3, 3] = (transform[:3, :3] @ centre + transform[:3, 3] - centre) / scale
    return (src - centre) / scale, (ref - centre) / scale, normalised
