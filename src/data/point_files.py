"""A user's own point clouds on disk: read PLY, PCD or XYZ text; write PLY.

* ``.ply``: ASCII or binary vertices (:func:`src.data.scans.parse_ply_points`; faces are ignored).
* ``.pcd``: Point Cloud Library files, ``DATA ascii`` or ``DATA binary`` (``binary_compressed`` is
  refused with the fix), fields ``x y z`` among any others.
* ``.xyz``, ``.txt``, ``.csv``, ``.pts``: text, one point per line, the first three numbers of a line
  (spaces or commas) are x y z; lines starting with ``#`` and non-numeric header lines are skipped.

Every reader returns ``(N, 3)`` float64 and raises one-line :class:`~src.utils.errors.DatasetError` for what
it cannot read.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from src.data.scans import parse_ply_points
from src.utils.errors import DatasetError

TEXT_SUFFIXES = (".xyz", ".txt", ".csv", ".pts")
SUFFIXES = (".ply", ".pcd", *TEXT_SUFFIXES)
_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
              ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def parse_pcd(data: bytes, name: str) -> np.ndarray:
    """The x, y, z columns of a PCD file (ASCII or binary)."""
    header: dict[str, list[str]] = {}
    offset = 0
    for line in data.splitlines(keepends=True):
        offset += len(line)
        tokens = line.decode("ascii", errors="replace").split()
        if not tokens or tokens[0].startswith("#"):
            continue
        header[tokens[0].upper()] = tokens[1:]
        if tokens[0].upper() == "DATA":
            break
    fields, kind = header.get("FIELDS", []), (header.get("DATA") or ["?"])[0].lower()
    if not {"x", "y", "z"} <= set(fields) or "POINTS" not in header:
        raise DatasetError(f"{name}: not a PCD file with x y z fields (FIELDS {' '.join(fields) or 'missing'})")
    count = int(header["POINTS"][0])
    if kind == "ascii":
        values = np.loadtxt(data[offset:].decode("ascii", errors="replace").splitlines(), ndmin=2, max_rows=count)
        points = values[:, [fields.index(axis) for axis in "xyz"]]
    elif kind == "binary":
        sizes, types = [int(s) for s in header["SIZE"]], header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        dtype = np.dtype([(f"{field}{k}" if n > 1 else field, "<" + _PCD_TYPES[(t, s)])
                          for field, t, s, n in zip(fields, types, sizes, counts) for k in range(n)])
        if len(data) - offset < count * dtype.itemsize:
            raise DatasetError(f"{name}: truncated, shorter than the {count} points its header announces")
        rows = np.frombuffer(data, dtype, count=count, offset=offset)
        points = np.stack([rows[axis] for axis in "xyz"], axis=1)
    else:
        raise DatasetError(f"{name}: PCD DATA {kind} is not supported: save it as ascii or binary "
                           "(e.g. pcl_convert_pcd_ascii_binary in.pcd out.pcd 1)")
    return points.astype(np.float64)


def parse_xyz(data: bytes, name: str) -> np.ndarray:
    """The first three numbers of every numeric line of a text file."""
    rows = []
    for line in data.decode("utf-8-sig", errors="replace").splitlines():
        tokens = [t for t in re.split(r"[\s,;]+", line.strip()) if t]
        if not tokens or tokens[0].startswith("#"):
            continue
        try:
            rows.append([float(t) for t in tokens[:3]])
        except ValueError:
            if rows:
                raise DatasetError(f"{name}: line {line.strip()[:60]!r} is not 'x y z ...'") from None
            continue  # a header line before the first point
        if len(rows[-1]) < 3:
            raise DatasetError(f"{name}: line {line.strip()[:60]!r} has fewer than 3 numbers")
    if not rows:
        raise DatasetError(f"{name}: no 'x y z' lines")
    return np.asarray(rows, dtype=np.float64)


def read_points(path: str | Path) -> np.ndarray:
    """The points (N, 3) float64 of a PLY, PCD or XYZ-text file, finite."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path} does not exist: give a {', '.join(SUFFIXES)} file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise DatasetError(f"{path}: unknown point-cloud format {suffix or '(no suffix)'}; expected one of "
                           f"{', '.join(SUFFIXES)}")
    data = path.read_bytes()
    parse = {".ply": parse_ply_points, ".pcd": parse_pcd}.get(suffix, parse_xyz)
    points = parse(data, str(path))
    if not np.isfinite(points).all():
        raise DatasetError(f"{path}: points with NaN or infinite coordinates")
    return points


def write_ply(path: Path, points: np.ndarray) -> None:
    """``points`` (N, 3) as a binary little-endian PLY of float32 vertices."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + np.ascontiguousarray(points, dtype="<f4").tobytes())
