"""Accuracy and per-pair runtime of a classical baseline on the benchmark's real ModelNet40 airplane pairs.

A small check used to choose and document the baselines' defaults, not the evaluation pipeline. Its
pairs are the benchmark's: the first ``--pairs`` pairs of the fixed test set of ``+exp=real_airplane``
(the carve-out of the last ``test_size`` = 100 airplane train ids, the official test split being withheld),
built as the grid builds it (:func:`benchmarks.grid_plan.build_test_set`: the experiment composed with
``sampling``, ``partial`` and ``data.pair.noise_sigma``, then :mod:`src.data`'s cache, splits and
:func:`~src.data.transforms.build_pair_transforms`). Pair k of a sweep is therefore pair k of the grid's
cell ``real_airplane/<sampling>/<partial>`` run with the same noise (``python -m benchmarks.grid
+benchmark=real_airplane benchmark.partials=[rpmnet] 'benchmark.overrides=[data.pair.noise_sigma=0.01]'``)
and of ``python -m src.eval +exp=real_airplane`` with those overrides.

Defaults: the RPMNet manner (independent half-space crops keeping 70 %, the transform moves the source,
717 points), twice-sampled (two disjoint subsets of each 10,000-point file), noise N(0, 0.01²) clipped
to ±0.05. ``--os``: once-sampled; ``--clean``: no noise; ``--partial prnet``: the PRNet manner (the
real-airplane grid's); ``--override KEY=VALUE``: any other override of the experiment (e.g.
``data.pair.rot_mag=90``, or ``test_size=200`` for up to 200 pairs, on other shapes than the grid's).

Prepare the data once, as for the grid::

    python -m src.data.prepare modelnet40_resampled --source ../shared/data/modelnet40_normal_resampled_airplane.zip

Usage::

    python -m baselines.classical.sweep icp --pairs 40 --set max_correspondence_distance=0.5
    python -m baselines.classical.sweep goicp --pairs 12 --timeout 120 --workers 2

The figures quoted in the classical methods' docstrings were measured by this command's earlier,
self-contained pair generator: the same RPMNet-manner protocol (the reference moved instead of the
source) on the last 20 airplane train ids read from the archive, i.e. other pairs than today's.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time

import numpy as np

from baselines.base import get_registrator
from baselines.runner import run_pairs
from baselines.testing import rotation_error_deg, translation_error
from src.errors import UserError

EXPERIMENT = "real_airplane"
NOISE_SIGMA = 0.01


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


def benchmark_pairs(count: int, sampling: str, partial: str, overrides: list[str]) -> tuple[str, list]:
    """(the test set's key, its first ``count`` pairs ``(src, ref, transform_gt)``), as the grid builds them."""
    from benchmarks.grid_plan import build_test_set  # hydra and the data stack: not in the worker processes

    test_set = build_test_set(EXPERIMENT, sampling, partial, None, overrides)
    available = len(test_set.dataset)
    if not 1 <= count <= available:
        raise UserError(f"--pairs {count}: the {test_set.key} test set has {available} pairs "
                        "(--override test_size=N carves out more shapes)")
    return test_set.key, test_set.pairs(count)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method")
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--partial", choices=("rpmnet", "prnet"), default="rpmnet")
    parser.add_argument("--os", action="store_true", help="once-sampled instead of twice-sampled")
    parser.add_argument("--clean", action="store_true", help=f"no Gaussian noise (default: sigma {NOISE_SIGMA})")
    parser.add_argument("--override", nargs="*", default=[], metavar="KEY=VALUE", help="experiment overrides")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--timeout", type=float, default=None)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="method config overrides")
    args = parser.parse_args(argv)
    noise = 0.0 if args.clean else NOISE_SIGMA
    try:
        registrator = get_registrator(args.method, **_parse_set(args.set))
        key, pairs = benchmark_pairs(args.pairs, "os" if args.os else "ts", args.partial,
                                     [f"data.pair.noise_sigma={noise}", *args.override])
        start = time.perf_counter()
        results = run_pairs(registrator, [(src, ref) for src, ref, _ in pairs], workers=args.workers,
                            timeout_s=args.timeout, progress=False)
        wall = time.perf_counter() - start
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rot = np.array([rotation_error_deg(r.transform, gt) for r, (_, _, gt) in zip(results, pairs)])
    tra = np.array([translation_error(r.transform, gt) for r, (_, _, gt) in zip(results, pairs)])
    secs = np.array([r.seconds for r in results])
    failed = [(i, r) for i, r in enumerate(results) if r.failed]
    print(f"{registrator!r}")
    for i, r in failed[:5]:
        print(f"  pair {i}: {r.reason}")
    print(
        f"{len(results)} pairs of {key} (noise {noise:g}), {len(pairs[0][0])} points: "
        f"rot err mean {rot.mean():.2f} median {np.median(rot):.2f} deg, "
        f"<5deg {np.mean(rot < 5) * 100:.0f}%; trans err mean {tra.mean():.3f} median {np.median(tra):.3f}; "
        f"seconds/pair mean {secs.mean():.3f} median {np.median(secs):.3f} max {secs.max():.3f}; "
        f"wall {wall:.1f} s; failed {len(failed)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
