"""Are an experiment's validation and test pairs equally hard? Each method's mean Error(R) and Error(t) on both
splits, with bootstrap 95 % intervals of the mean (pairs resampled), so that a gap between a model's validation and
test numbers can be told apart from a difference between the sets or from the spread of a 100-pair mean. With
``--train-shapes N``, also on fixed pairs of the first N training shapes (drawn as the evaluation sets draw theirs):
a model as wrong on the shapes it trained on as on new ones underfits; one far better there overfits.

    python -m benchmarks.studies.diagnostics.split_gap --exp real_airplane --methods identity,icp,fgr
    python -m benchmarks.studies.diagnostics.split_gap --exp real_airplane --methods icp,idam --checkpoint idam=PATH.ckpt --out GAP.md
    python -m benchmarks.studies.diagnostics.split_gap --exp real_airplane --methods omnet --checkpoint omnet=PATH.ckpt --train-shapes 100
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from baselines.registry import resolve_registrator
from benchmarks.grid.run import cell_metrics, register
from src.config import euler_seq_for
from src.data.dataset import EVAL_STREAM, PairDataset
from src.utils.errors import ConfigError, exit_code_of
from src.metrics import ERROR_R, ERROR_T

SPLITS = ("val", "test")


def fixed_training_pairs(train: PairDataset, shapes: int) -> PairDataset:
    """Fixed pairs of the first ``shapes`` training shapes, one each, drawn by the evaluation stream (the pairs of
    one evaluation, not of a training epoch) with the training set's transforms."""
    if not 0 < shapes <= len(train):
        raise ConfigError(f"--train-shapes must be between 1 and the {len(train)} training shapes, got {shapes}")
    return PairDataset(train.points, train.labels, train.shape_indices[:shapes], train.transforms, train.seed,
                       EVAL_STREAM, normals=train.normals)


def split_pairs(experiment: str, sampling: str, partial: str, overrides: Sequence[str] = (),
                train_shapes: int = 0) -> dict[str, list]:
    """The fixed validation and test pairs ``(src, ref, transform_gt)`` of an experiment, as training and
    ``src.eval`` see them, and with ``train_shapes`` first those of :func:`fixed_training_pairs`."""
    import hydra

    from src.compose import compose_experiment
    from src.pair_sets import TestSet

    cfg = compose_experiment([f"+exp={experiment}", f"sampling={sampling}", f"partial={partial}", *overrides])
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    datamodule.setup("test")
    missing = [s for s in SPLITS if s not in datamodule.datasets]
    if missing:
        raise ConfigError(f"experiment {experiment} has no {' or '.join(missing)} split (data.splits)")
    datasets = {split: datamodule.datasets[split] for split in SPLITS}
    if train_shapes:
        datasets = {"train": fixed_training_pairs(datamodule.datasets["train"], train_shapes), **datasets}
    out = {}
    for split, dataset in datasets.items():
        pair_set = TestSet(experiment, sampling, partial, cfg, dataset, {})
        out[split] = pair_set.pairs(len(dataset))
    return out


def bootstrap_mean(values: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """The 2.5 % and 97.5 % quantiles of the mean of ``values`` resampled with replacement."""
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, len(values), size=(draws, len(values)))].mean(axis=1)
    low, high = np.quantile(means, [0.025, 0.975])
    return float(low), float(high)


def gap_table(methods: Sequence[str], pairs: dict[str, list], partial: str,
              checkpoints: dict[str, str] | None = None, workers: int | None = 1) -> list[dict]:
    """One row per method and split: pairs, mean, median and 95 % interval of Error(R) and Error(t)."""
    rows = []
    for method in methods:
        options = {"checkpoint": checkpoints[method]} if checkpoints and method in checkpoints else {}
        registrator = resolve_registrator(method)(None, **options)
        for split, split_pairs_ in pairs.items():
            results = register(registrator, [(s, r) for s, r, _ in split_pairs_], workers=workers, progress=False)
            _, errors = cell_metrics(results, split_pairs_, euler_seq_for(partial))
            row = {"method": method, "split": split, "pairs": len(split_pairs_)}
            for name in (ERROR_R, ERROR_T):
                low, high = bootstrap_mean(errors[name])
                digits = 1 if name == ERROR_R else 3
                row |= {name: float(errors[name].mean()), f"{name} median": float(np.median(errors[name])),
                        f"{name} 95%": f"{low:.{digits}f}–{high:.{digits}f}"}
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--exp", default="real_airplane", help="an experiment with a val and a test split")
    parser.add_argument("--methods", default="identity,icp", help="comma-separated method names")
    parser.add_argument("--checkpoint", action="append", default=[], metavar="METHOD=PATH",
                        help="a learned method's checkpoint (repeatable)")
    parser.add_argument("--sampling", choices=("os", "ts"), default="ts")
    parser.add_argument("--partial", choices=("prnet", "rpmnet"), default="prnet")
    parser.add_argument("--train-shapes", type=int, default=0, metavar="N",
                        help="also fixed pairs of the first N training shapes (underfitting or overfitting?)")
    parser.add_argument("--override", action="append", default=[], help="a Hydra override of the experiment")
    parser.add_argument("--workers", type=int, default=1, help="a classical method's worker processes (0: in this one)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table here (Markdown)")
    args = parser.parse_args(argv)

    def action() -> None:
        import pandas as pd

        checkpoints = {}
        for item in args.checkpoint:
            method, sep, path = item.partition("=")
            if not sep:
                raise ConfigError(f"--checkpoint expects METHOD=PATH, got '{item}'")
            checkpoints[method] = path
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        pairs = split_pairs(args.exp, args.sampling, args.partial, args.override, args.train_shapes)
        table = pd.DataFrame(gap_table(methods, pairs, args.partial, checkpoints, args.workers)).to_markdown(index=False,
                                                                                                floatfmt=".3f")
        print(table)
        if args.out:
            args.out.write_text(f"`python -m benchmarks.studies.diagnostics.split_gap {' '.join(sys.argv[1:] if argv is None else argv)}`\n\n{table}\n")

    return exit_code_of(action)


if __name__ == "__main__":
    raise SystemExit(main())
