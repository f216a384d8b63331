"""A tiny generated set of range scans with a known Stanford-style .conf (tests of src/data/scans.py and
of the figures drawn from scan pairs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

# A wavy 40 x 10 grid (spacing 0.05) in the common frame; scan a = columns 0-29, b = 10-39, c = 35-39.
COLUMNS = {"a": range(0, 30), "b": range(10, 40), "c": range(35, 40)}
POSES = {  # (translation, quaternion qx qy qz qw)
    "a": ([0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]),
    "b": ([0.3, -0.2, 0.1], Rotation.from_euler("xyz", [20, -35, 60], degrees=True).as_quat()),
    "c": ([-0.1, 0.4, 0.2], Rotation.from_euler("xyz", [-50, 10, 120], degrees=True).as_quat()),
}


def surface(columns: range) -> np.ndarray:
    """The grid points of ``columns`` (10 rows each) in the common frame."""
    x, y = np.meshgrid(np.asarray(columns) * 0.05, np.arange(10) * 0.05, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel()) * np.cos(2 * y.ravel())], axis=1)


def ply_text(points: np.ndarray) -> str:
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    return header + "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist())


def write_scan_set(root: Path) -> Path:
    """``root``: scans a, b, c (300, 300 and 50 points), each in its own frame (p_own = R(q)·(p_common - t)),
    and ``scans.conf`` (a camera line, then one bmesh line per scan)."""
    root.mkdir(parents=True)
    lines = ["camera 0 0 -1 0 0 0 1"]
    for name, (translation, quaternion) in POSES.items():
        own = (surface(COLUMNS[name]) - translation) @ Rotation.from_quat(quaternion).as_matrix().T
        (root / f"{name}.ply").write_text(ply_text(own))
        lines.append(f"bmesh {name}.ply " + " ".join(repr(float(v)) for v in [*translation, *quaternion]))
    (root / "scans.conf").write_text("\n".join(lines) + "\n")
    return root
