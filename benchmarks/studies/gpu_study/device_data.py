"""A prepared dataset cache, packed losslessly to travel to a GPU machine with little room for data.

    python -m benchmarks.studies.gpu_study.device_data pack --dataset modelnet40_resampled --out .device_data   # here
    python -m benchmarks.studies.gpu_study.device_data unpack --packed .device_data --cache-root /tmp/cache      # there

The real airplanes' cache is 144 MB (points and normals, float32); the GPU runs read points only, and the
points are the source files' 6-decimal values, so each is an integer number of micro-units. ``pack`` keeps
the points as those integers (refusing a cache whose points are not), their four bytes as separate planes, and
a bit per point for the sign of a zero (``-0.000000``), LZMA-compressed (75 MB of points -> 46.6 MB), with the
labels and a manifest without normals. ``unpack`` rebuilds the same ``.npy`` files byte for byte: the cache's
own sha256 check (``open_cache``) proves it.
"""

from __future__ import annotations

import argparse
import json
import lzma
import shutil
import sys
from pathlib import Path

import numpy as np

from src.data.cache import default_cache_root, manifest_without_normals, open_cache
from src.utils.errors import DatasetError, exit_code_of

#: Points are stored as integers of this many units per coordinate unit (the source files' 6 decimals).
UNITS = 1_000_000


def pack(cache_dir: Path, out: Path, preset: int = 6) -> Path:
    """Write ``out/manifest.json``, the labels and each split's points as ``<split>_points.xz``."""
    cache = open_cache(cache_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in cache.available_splits:
        split = cache.split(name)
        points = np.asarray(split.points)
        integers = np.round(points.astype(np.float64) * UNITS)
        if np.abs(integers).max() >= 2**31 or not np.array_equal((integers / UNITS).astype(np.float32), points):
            raise DatasetError(f"the {name} points of {cache_dir} are not {UNITS}ths of a unit: they cannot be packed "
                               "losslessly (pack a cache prepared from the 6-decimal resampled text files)")
        planes = integers.astype("<i4").view(np.uint8).reshape(-1, 4).T.copy()
        negative_zeros = np.packbits((points == 0) & np.signbit(points))  # "-0.000000" in a source file
        (out / f"{name}_points.xz").write_bytes(lzma.compress(planes.tobytes() + negative_zeros.tobytes(), preset=preset))
        info = cache.manifest["splits"][name]["files"]["labels"]
        shutil.copyfile(cache_dir / info["name"], out / info["name"])
    (out / "manifest.json").write_text(json.dumps(manifest_without_normals(cache.manifest), indent=1))
    return out


def unpack(packed: Path, cache_root: Path) -> Path:
    """Rebuild the cache at ``cache_root/<dataset>`` from :func:`pack`'s folder; its files are verified."""
    manifest = json.loads((packed / "manifest.json").read_text())
    target = cache_root / manifest["dataset"]
    target.mkdir(parents=True, exist_ok=True)
    for name, info in manifest["splits"].items():
        shape = tuple(info["shape"])
        data = np.frombuffer(lzma.decompress((packed / f"{name}_points.xz").read_bytes()), np.uint8)
        count = int(np.prod(shape))
        integers = data[:4 * count].reshape(4, -1).T.copy().view("<i4").reshape(shape)
        points = (integers / UNITS).astype(np.float32)
        negative_zeros = np.unpackbits(data[4 * count:], count=count).reshape(shape).astype(bool)
        points[negative_zeros] = -0.0
        np.save(target / info["files"]["points"]["name"], points)
        shutil.copyfile(packed / info["files"]["labels"]["name"], target / info["files"]["labels"]["name"])
    (target / "manifest.json").write_text(json.dumps(manifest, indent=1))
    open_cache(target)  # sizes and sha256 of every file: a corrupt transfer stops here
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    pack_parser = sub.add_parser("pack", help="pack a prepared cache (points and labels only)")
    pack_parser.add_argument("--dataset", default="modelnet40_resampled")
    pack_parser.add_argument("--cache-root", type=Path, default=None, help="default: $OMNET_CACHE_DIR or ~/.cache/...")
    pack_parser.add_argument("--out", type=Path, required=True)
    unpack_parser = sub.add_parser("unpack", help="rebuild the cache from a packed folder")
    unpack_parser.add_argument("--packed", type=Path, required=True)
    unpack_parser.add_argument("--cache-root", type=Path, required=True)
    args = parser.parse_args(argv)

    def action() -> None:
        if args.command == "pack":
            print(f"packed into {pack((args.cache_root or default_cache_root()) / args.dataset, args.out)}")
        else:
            print(f"unpacked {unpack(args.packed, args.cache_root)}")

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
