"""Accuracy and per-pair runtime of a classical baseline on real ModelNet40 airplanes.

A small, self-contained check used to choose and document the baselines' defaults; it is
*not* the evaluation pipeline (that uses ``src.data`` and the experiment configs). Pairs
follow the RPMNet partial manner described in the OMNet supplementary: 1,024 points per
cloud (twice-sampled: two disjoint random subsets of the 10,000-point file; once-sampled:
the same subset), each cropped by a random half-space to the 70% of points farthest along a
random direction (717 points), a rigid motion with Euler angles uniform in [0°, 45°] and a
translation uniform in [-0.5, 0.5] per axis applied to the source to give the reference,
and optional Gaussian noise N(0, 0.01²) clipped to ±0.05.

Usage::

    python -m baselines.classical.sweep icp --pairs 40 --set max_correspondence_distance=0.5
    python -m baselines.classical.sweep goicp --pairs 12 --timeout 120 --workers 2

The archive is read from ``../shared/data/modelnet40_normal_resampled_airplane.zip``
(``--zip`` to override); shapes are taken from the end of the train split (a validation
subset), never from the withheld test split.
"""

from __future__ import annotations

import argparse
import ast
import io
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

from baselines.base import get_registrator
from baselines.runner import run_pairs
from baselines.testing import rotation_error_deg, translation_error
from src.errors import DatasetError, UserError
from src.paths import shared_path

DEFAULT_ZIP = shared_path("data", "modelnet40_normal_resampled_airplane.zip")
ROOT = "modelnet40_normal_resampled"


def load_airplanes(zip_path: Path, count: int) -> list[np.ndarray]:
    """The last ``count`` shapes of the airplane train split, as (10000, 3) arrays."""
    if not zip_path.is_file():
        raise DatasetError(f"airplane archive not found at {zip_path}; pass --zip PATH")
    with zipfile.ZipFile(zip_path) as archive:
        names = archive.read(f"{ROOT}/modelnet40_train.txt").decode().split()
        ids = [n for n in names if n.startswith("airplane_")][-count:]
        shapes = []
        for shape_id in ids:
            raw = archive.read(f"{ROOT}/airplane/{shape_id}.txt")
            shapes.append(np.loadtxt(io.BytesIO(raw), delimiter=",", dtype=np.float64)[:, :3])
    return shapes


def _crop(points: np.ndarray, rng: np.random.Generator, keep: float) -> np.ndarray:
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    dist = points @ direction
    return points[dist > np.percentile(dist, (1.0 - keep) * 100.0)]


def _euler(angles_deg: np.ndarray) -> np.ndarray:
    ax, ay, az = np.radians(angles_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def rpmnet_pairs(
    shapes: list[np.ndarray], pairs: int, seed: int = 0, twice_sampled: bool = True, noise: bool = True
) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """``pairs`` (src, ref) pairs in the RPMNet partial manner and their true transforms."""
    rng = np.random.default_rng(seed)
    out, truths = [], []
    for k in range(pairs):
        pts = shapes[k % len(shapes)]
        perm = rng.permutation(len(pts))
        src = pts[perm[:1024]]
        ref = pts[perm[1024:2048]] if twice_sampled else src.copy()
        src, ref = _crop(src, rng, 0.7), _crop(ref, rng, 0.7)
        src, ref = src[rng.permutation(len(src))[:717]], ref[rng.permutation(len(ref))[:717]]
        rot = _euler(rng.uniform(0.0, 45.0, 3))
        trans = rng.uniform(-0.5, 0.5, 3)
        ref = ref @ rot.T + trans
        if noise:
            src = src + np.clip(rng.normal(0.0, 0.01, src.shape), -0.05, 0.05)
            ref = ref + np.clip(rng.normal(0.0, 0.01, ref.shape), -0.05, 0.05)
        truth = np.eye(4)
        truth[:3, :3], truth[:3, 3] = rot, trans
        out.append((src, ref))
        truths.append(truth)
    return out, truths


def _parse_set(items: list[str]) -> dict:
    cfg = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise UserError(f"--set expects key=value, got '{item}'")
        try:
            cfg[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            cfg[key] = value
    return cfg


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method")
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--shapes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--os", action="store_true", help="once-sampled instead of twice-sampled")
    parser.add_argument("--clean", action="store_true", help="no Gaussian noise")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--timeout", type=float, default=None)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides")
    parser.add_argument("--zip", type=Path, default=DEFAULT_ZIP)
    args = parser.parse_args(argv)
    try:
        registrator = get_registrator(args.method, **_parse_set(args.set))
        shapes = load_airplanes(args.zip, args.shapes)
        pairs, truths = rpmnet_pairs(shapes, args.pairs, args.seed, not args.os, not args.clean)
        start = time.perf_counter()
        results = run_pairs(registrator, pairs, workers=args.workers, timeout_s=args.timeout, progress=False)
        wall = time.perf_counter() - start
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rot = np.array([rotation_error_deg(r.transform, t) for r, t in zip(results, truths)])
    tra = np.array([translation_error(r.transform, t) for r, t in zip(results, truths)])
    secs = np.array([r.seconds for r in results])
    failed = [(i, r) for i, r in enumerate(results) if r.failed]
    print(f"{registrator!r}")
    for i, r in failed[:5]:
        print(f"  pair {i}: {r.reason}")
    print(
        f"{len(results)} pairs ({'OS' if args.os else 'TS'}, {'clean' if args.clean else 'noisy'}), "
        f"{len(pairs[0][0])} points: rot err mean {rot.mean():.2f} median {np.median(rot):.2f} deg, "
        f"<5deg {np.mean(rot < 5) * 100:.0f}%; trans err mean {tra.mean():.3f} median {np.median(tra):.3f}; "
        f"seconds/pair mean {secs.mean():.3f} median {np.median(secs):.3f} max {secs.max():.3f}; "
        f"wall {wall:.1f} s; failed {len(failed)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
