"""Accuracy and per-pair runtime of a classical baseline on real ModelNet40 airplane pairs, to tune its defaults.

A small check used to choose and document the baselines' defaults, not the evaluation pipeline. ``--split train``
(the default, the one to tune on): the first ``--pairs`` fixed pairs of the *training* stage of
``+exp=real_airplane`` (the training shapes, never a validation or test shape; the datamodule refuses any
overlap), as the datamodule draws them at epoch 0. ``--split test`` (**reporting only, never tuning**): the
first pairs of its fixed test set, the grid's cell ``real_airplane/<sampling>/<partial>``. Pairs are built by
:mod:`src.data` from the experiment composed with ``sampling``, ``partial``, ``data.pair.noise_sigma`` and
``--override`` (e.g. ``data.pair.rot_mag=90``). Defaults: RPMNet manner, twice-sampled, noise σ = 0.01;
``--os``, ``--clean``, ``--partial prnet``. Prepare the data as for the grid; tuning records: ``docs/methods/``
(the older methods' docstrings quote earlier versions' pairs: a self-contained generator, then the test set).

    python -m baselines.classical.sweep icp --pairs 40 --set max_correspondence_distance=0.5
"""

from __future__ import annotations

import argparse
import ast
import sys
import time

import numpy as np

from baselines.registry import get_registrator
from baselines.runner import run_pairs
from baselines.testing import rotation_error_deg, translation_error
from src.utils.errors import UserError

EXPERIMENT = "real_airplane"
NOISE_SIGMA = 0.01
#: The experiment's stages the sweep may draw its pairs from: the training shapes (to tune on) or the test set.
SPLITS = ("train", "test")


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


def sweep_pairs(count: int, sampling: str, partial: str, overrides: list[str],
                split: str = "train") -> tuple[str, list]:
    """(the pair set's key, its first ``count`` pairs ``(src, ref, transform_gt)``): the fixed test set as the grid
    builds it (``split="test"``), or the training stage's pairs at epoch 0 (``split="train"``)."""
    import hydra  # hydra and the data stack: not in the worker processes

    from src.compose import compose_experiment
    from src.pair_sets import TestSet, build_test_set

    if split == "test":
        pair_set = build_test_set(EXPERIMENT, sampling, partial, None, overrides)
    else:
        cfg = compose_experiment([f"+exp={EXPERIMENT}", f"sampling={sampling}", f"partial={partial}", *overrides])
        datamodule = hydra.utils.instantiate(cfg.data)
        datamodule.setup("fit")  # refuses a training shape that is also a validation or test shape
        pair_set = TestSet(EXPERIMENT, sampling, partial, cfg, datamodule.datasets["train"], {})
    key = f"{pair_set.key} ({split})"
    available = len(pair_set.dataset)
    if not 1 <= count <= available:
        raise UserError(f"--pairs {count}: {key} has {available} pairs"
                        + (" (--override test_size=N carves out more shapes)" if split == "test" else ""))
    return key, pair_set.pairs(count)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("method")
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--split", choices=SPLITS, default="train",
                        help="train: the training shapes (tune here); test: the test set (report only, never tune)")
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
        key, pairs = sweep_pairs(args.pairs, "os" if args.os else "ts", args.partial,
                                 [f"data.pair.noise_sigma={noise}", *args.override], args.split)
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
    if args.split == "test":
        print("note: test-set pairs: for reporting only, never tune on them (--split train)")
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
