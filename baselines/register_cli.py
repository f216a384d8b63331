"""Register two point clouds of one's own from the command line.

    python -m baselines register scan_a.ply scan_b.ply --method fgr
    python -m baselines register a.pcd b.xyz --method icp --option max_iterations=60
    python -m baselines register a.ply b.ply --method omnet                      # the shipped checkpoint
    python -m baselines register a.ply b.ply --method omnet --checkpoint outputs/.../best-3000.ckpt

Estimates ``T`` with ``B ≈ T·A`` (the source ``A`` moved onto the reference ``B``) with any method of
``python -m baselines`` and writes into ``--out`` (default ``outputs/register/<A>_to_<B>/``):
``transform.txt`` (4x4), ``result.json`` (transform, rotation angle, translation, fitness and inlier
RMSE, time, method and checkpoint, normalisation), ``<A>_aligned.ply`` (the whole source moved by ``T``)
and ``before_after.png`` (the pair as given, then aligned).

Files: PLY, PCD or XYZ text (:mod:`src.data.point_files`). The pair is registered as
:meth:`~baselines.base.Registrator.register` registers any pair: one that does not lie in the frame the method
is tuned for (e.g. scans in millimetres) is registered after one similarity and ``T`` mapped back (a classical
method's working frame, a network's training frame: :mod:`baselines.conditioning`), and ``result.json`` records
that similarity. Learned methods register a seeded random subset of ``--points`` points of each cloud (their
training clouds' size; the estimate applies to the whole clouds) and take a shipped checkpoint unless
``--checkpoint`` or ``--weights`` is given. Fitness and inlier RMSE are measured on the whole clouds in
their own units: the share of moved source points within ``--threshold`` of a reference point (default
5 % of the pair's radius) and the RMS distance of those.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from baselines.cloud_panels import REFERENCE, SOURCE, centre, half_size, panel
from baselines.conditioning import deduplicated, pair_radius
from baselines.methods import display_name
from baselines.registry import get_registrator
from baselines.result import FIT_THRESHOLD, check_threshold, inlier_fit
from src.data.point_files import read_points, write_ply
from src.geometry.numpy_rigid import apply_transform
from src.utils.errors import ConfigError, UserError
from src.utils.files import disk_errors

#: Points per cloud a learned method registers (the shipped models' training clouds: PRNet-manner crops of 768).
LEARNED_POINTS = 768
#: Points per cloud drawn in the picture.
PICTURE_POINTS = 4000


def _subset(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return points if len(points) <= n else points[np.sort(rng.choice(len(points), n, replace=False))]


def _options(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` items as method options (values read as YAML scalars: 60, 0.5, true, [1, 2])."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--option takes KEY=VALUE, got {item!r}")
        options[key] = yaml.safe_load(value)
    return options


def register_files(src_path: Path, ref_path: Path, method: str, options: dict[str, Any], points: int,
                   threshold: float | None, seed: int = 0) -> dict[str, Any]:
    """Read, register and measure a pair of files: the ``result.json`` record plus the clouds (``src``,
    ``ref``, ``aligned``) and the registrator's ``label``."""
    src, ref = read_points(src_path), read_points(ref_path)
    registrator = get_registrator(method, **options)
    src_in, ref_in = src, ref
    if registrator.needs_training:
        rng = np.random.default_rng(seed)
        src_in, ref_in = _subset(src, points, rng), _subset(ref, points, rng)
    result = registrator.register_result(src_in, ref_in, threshold=None)
    if result.failed:
        raise UserError(f"{registrator.name} failed on this pair: {result.reason}")
    transform = result.transform
    frame = registrator.frame(deduplicated(src_in), deduplicated(ref_in))
    threshold = FIT_THRESHOLD * pair_radius(src, ref) if threshold is None else threshold
    fitness, rmse = inlier_fit(src, ref, transform, threshold)
    cos = (np.trace(transform[:3, :3]) - 1) / 2
    checkpoint = getattr(registrator.config, "checkpoint", None)
    return {
        "source": str(src_path), "reference": str(ref_path), "points": [len(src), len(ref)],
        "method": registrator.name, "label": getattr(registrator, "label", display_name(registrator.name)),
        "checkpoint": None if checkpoint is None else str(checkpoint),
        "registered_points": [len(src_in), len(ref_in)],
        "normalisation": None if frame is None else {"centre": frame.centre.tolist(), "scale": frame.scale},
        "transform": transform.tolist(),
        "rotation_deg": math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0)))),
        "translation": float(np.linalg.norm(transform[:3, 3])),
        "fitness": fitness, "inlier_rmse": rmse, "threshold": threshold, "seconds": result.seconds,
        "clouds": {"src": src, "ref": ref, "aligned": apply_transform(transform, src)},
    }


def draw(path: Path, clouds: dict[str, np.ndarray], title: str) -> None:
    """``before_after.png``: source and reference as given, then the aligned source on the reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    src, ref, aligned = (_subset(clouds[k], PICTURE_POINTS, rng) for k in ("src", "ref", "aligned"))
    fig = plt.figure(figsize=(7, 3.6))
    for slot, (moving, name) in enumerate(((src, "before"), (aligned, "after")), start=1):
        both = np.concatenate([moving, ref])
        panel(fig, (1, 2), slot, [(ref, REFERENCE), (moving, SOURCE)], centre(both), half_size(both), (20.0, -60.0),
              f"{name}: source (orange), reference (blue)")
    fig.suptitle(title, fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(record: dict[str, Any], out: Path) -> list[Path]:
    """transform.txt, result.json, the aligned source (PLY) and the picture, in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    clouds = record.pop("clouds")
    files = [out / "transform.txt", out / "result.json", out / f"{Path(record['source']).stem}_aligned.ply",
             out / "before_after.png"]
    np.savetxt(files[0], np.asarray(record["transform"]), fmt="%.9f")
    files[1].write_text(json.dumps(record, indent=2) + "\n")
    write_ply(files[2], clouds["aligned"])
    draw(files[3], clouds, f"{record['label']}: {Path(record['source']).name} -> {Path(record['reference']).name}, "
                           f"fitness {record['fitness']:.2f}")
    return files


def summary(record: dict[str, Any]) -> str:
    """What the command prints first: the method, the transform, its size and the fit."""
    rows = "\n".join("  " + " ".join(f"{v:12.6f}" for v in row) for row in record["transform"])
    normalised = ("" if record["normalisation"] is None else
                  f" (registered in the method's frame: scale {record['normalisation']['scale']:.4g}, mapped back)")
    used = "" if record["checkpoint"] is None else f"\ncheckpoint: {record['checkpoint']}"
    return (f"{record['label']}: {record['source']} ({record['points'][0]:,} points) -> {record['reference']} "
            f"({record['points'][1]:,} points){normalised}{used}\n"
            f"transform (reference ≈ T · source):\n{rows}\n"
            f"rotation {record['rotation_deg']:.2f}°, translation {record['translation']:.4g}; fitness "
            f"{record['fitness']:.3f}, inlier RMSE {record['inlier_rmse']:.4g} (inliers within {record['threshold']:.4g}); "
            f"{record['seconds']:.2f} s")


def add_parser(sub: Any) -> None:
    """The ``register`` subcommand of ``python -m baselines``."""
    parser = sub.add_parser("register", help="register two point-cloud files (PLY, PCD, XYZ)",
                            description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="the cloud to move (PLY, PCD or XYZ text)")
    parser.add_argument("reference", type=Path, help="the cloud to align it to")
    parser.add_argument("--method", default="fgr", help="any key of `python -m baselines` (default fgr)")
    parser.add_argument("--checkpoint", default=None, help="learned methods: a src.train checkpoint (default: shipped)")
    parser.add_argument("--weights", default=None, help="learned methods: published weights, official:<name>")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE", help="a method option")
    parser.add_argument("--points", type=int, default=LEARNED_POINTS,
                        help=f"learned methods: points per cloud (default {LEARNED_POINTS})")
    parser.add_argument("--threshold", type=float, default=None,
                        help="inlier distance of fitness / RMSE in the clouds' units (default 5%% of the pair's radius)")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default outputs/register/<A>_to_<B>)")
    parser.set_defaults(action=run)


def run(args: argparse.Namespace) -> None:
    if args.points < 3:
        raise ConfigError(f"--points must be >= 3, got {args.points}")
    check_threshold(args.threshold)
    options = _options(args.option) | {k: v for k, v in (("checkpoint", args.checkpoint), ("weights", args.weights)) if v}
    record = register_files(args.source, args.reference, args.method, options, args.points, args.threshold)
    out = args.out or Path("outputs") / "register" / f"{args.source.stem}_to_{args.reference.stem}"
    print(summary(record), flush=True)  # before writing: a folder that cannot be written loses no computed result
    with disk_errors("writing the registration's files", out):
        files = write_outputs(record, out)
    print("wrote " + ", ".join(map(str, files)))
