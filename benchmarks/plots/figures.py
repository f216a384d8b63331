"""Pictures of registrations, as the paper gives them: source, reference and each method's aligned source
side by side, and OMNet's predicted overlap masks of every iteration next to the ground-truth masks.

    python -m benchmarks.plots.figures --experiment scan_pairs --pairs 0,12 --checkpoint checkpoints/<omnet>.ckpt \\
        --out benchmarks/results/figure_scan_pairs.png
    python -m benchmarks.plots.figures --experiment real_airplane --grid outputs/grid/real_airplane \\
        --pick worst,median,best --by icp --methods icp,fgr --out airplanes.png

Test set: ``--experiment`` (with ``--sampling``, ``--partial`` and any Hydra overrides, e.g.
``data.source=PATH``), composed as :mod:`benchmarks.grid` does: the pairs ``src.eval`` evaluates.
Pairs: ``--pairs`` (indices), or ``--pick`` worst / median / best Error(R) of method ``--by`` in a grid run
on the same test set (``--grid``). Methods (``--methods``) register the chosen pairs here with their default
options (``baselines.get_registrator``; classical ones through ``baselines.run_pairs`` with a per-pair
``--timeout``, a failed pair shown as failed); learned ones load ``--checkpoint``. For OMNet two more rows show
the overlap mask it predicts at every iteration on the source and on the reference, then the ground-truth
mask (points within the network's ``overlap_dist`` of the other cloud under the ground truth).

Rendering: matplotlib's 3D scatter on the Agg backend (offscreen, CPU only), one fixed camera (``--view``)
and one axes box for every panel of a pair; source orange, reference blue; masks: overlapping points red,
the rest grey. Bad input stops with one ``error: ...`` line.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from baselines import get_registrator, resolve_registrator, run_pairs  # noqa: E402
from baselines.base import Registrator  # noqa: E402
from baselines.methods import display_name  # noqa: E402
from src.data.scan_pairs import ScanPairDataset  # noqa: E402
from src.data.scans import apply_transform  # noqa: E402
from src.utils.errors import ConfigError, UserError  # noqa: E402
from baselines.cloud_panels import OVERLAP, REFERENCE, REST, SOURCE, centre, half_size, panel  # noqa: E402
from src.metrics import ERROR_R, pair_errors  # noqa: E402

PICKS = ("worst", "median", "best")
PANEL_INCHES = 1.7


@dataclass
class PairPicture:
    """What one pair's rows show: the clouds, each method's estimate and OMNet's masks."""

    title: str
    src: np.ndarray
    ref: np.ndarray
    gt: np.ndarray
    estimates: dict[str, np.ndarray] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)
    """Methods whose registration failed (error, timeout): their estimate is the identity."""
    masks: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    """OMNet's predicted (source, reference) masks per iteration, then the ground truth's."""


def pick_pairs(errors: dict[int, float], picks: Sequence[str]) -> dict[int, str]:
    """``{pair index: pick}`` for the worst (largest error), median and best (smallest) of ``errors``."""
    order = sorted(errors, key=lambda i: (errors[i], i))
    where = {"worst": -1, "median": len(order) // 2, "best": 0}
    unknown = [p for p in picks if p not in where]
    if unknown:
        raise ConfigError(f"--pick takes {', '.join(PICKS)}, got {', '.join(picks)}")
    chosen: dict[int, str] = {}
    for pick in picks:
        chosen.setdefault(order[where[pick]], pick)
    return chosen


def omnet_masks(registrator: Registrator, src: np.ndarray, ref: np.ndarray, gt: np.ndarray
                ) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """OMNet's estimate, and its masks: the predicted ones of every iteration (the network's own rule,
    argmax or top-k), then the ground truth's (the labels of the first iteration, before any masking);
    no masks for a network without the mask module."""
    network = registrator.module.network

    def batch(points: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(points[None], dtype=torch.float32, device=registrator.device)

    def mask(values: torch.Tensor) -> np.ndarray:
        return values[0].cpu().numpy().astype(bool)

    with torch.inference_mode():
        out = network(batch(src), batch(ref), batch(gt))
        masks = [(mask(network.next_mask(s)), mask(network.next_mask(r))) for s, r in out["mask_logits"]]
    if masks:
        masks.append(tuple(mask(m) for m in out["mask_labels"][0]))
    return out["transforms"][-1][0].double().cpu().numpy(), masks


def build_registrators(methods: Sequence[str], checkpoint: str | None) -> dict[str, Registrator]:
    registrators = {}
    for method in methods:
        learned = getattr(resolve_registrator(method), "needs_training", False)
        registrators[method] = get_registrator(method, **({"checkpoint": checkpoint} if learned else {}))
    return registrators


def pair_title(dataset, index: int) -> str:
    if isinstance(dataset, ScanPairDataset):
        source, reference = dataset.names(index)
        return f"pair {index}: {source} → {reference}, overlap {dataset.pairs[index].overlap:.0%}"
    return f"pair {index}"


def pictures(dataset, indices: dict[int, str], registrators: dict[str, Registrator], workers: int | None,
             timeout_s: float) -> list[PairPicture]:
    """The chosen pairs (``{index: note for its title}``) with every method's estimate: OMNet's (and its
    masks) here, the others' through :func:`baselines.run_pairs` (worker processes, per-pair timeout; a
    failed pair counts as the identity)."""
    pics = []
    for index, note in indices.items():
        sample = dataset[index]
        pics.append(PairPicture(pair_title(dataset, index) + note, sample["points_src"].double().numpy(),
                                sample["points_ref"].double().numpy(), sample["transform_gt"].double().numpy()))
    for method, registrator in registrators.items():
        if method == "omnet":
            for pic in pics:
                pic.estimates[method], pic.masks = omnet_masks(registrator, pic.src, pic.ref, pic.gt)
            continue
        results = run_pairs(registrator, [(pic.src, pic.ref) for pic in pics], workers=workers, timeout_s=timeout_s,
                            progress=False)
        for pic, result in zip(pics, results):
            pic.estimates[method] = result.transform
            if result.failed:
                pic.failures[method] = result.reason.split(":")[0]
    return pics


# --- drawing ------------------------------------------------------------------------------------------


def _error(estimate: np.ndarray, gt: np.ndarray) -> str:
    err = pair_errors(torch.as_tensor(estimate[None]), torch.as_tensor(gt[None]), "zyx")
    return f"{float(err['rot_deg'][0]):.1f}°, {float(err['trans_norm'][0]):.3f}"


def draw_pair(fig, pic: PairPicture, labels: dict[str, str], view: tuple[float, float], columns: int) -> list[str]:
    """One pair on a (sub)figure: the alignment row, then OMNet's two mask rows; the panel titles."""
    grid = (3 if pic.masks else 1, columns)
    truth = apply_transform(pic.gt, pic.src)
    aligned = np.concatenate([pic.ref, truth])  # every aligned panel shows the reference's frame around these
    half = half_size(pic.src, aligned)
    top = [([(pic.src, SOURCE)], pic.src, "source"), ([(pic.ref, REFERENCE)], aligned, "reference"),
           ([(pic.ref, REFERENCE), (truth, SOURCE)], aligned, "ground truth")]
    top += [([(pic.ref, REFERENCE), (apply_transform(estimate, pic.src), SOURCE)], aligned,
             f"{labels[m]}\n" + (f"failed ({pic.failures[m]})" if m in pic.failures else _error(estimate, pic.gt)))
            for m, estimate in pic.estimates.items()]
    panels = [(slot, *spec) for slot, spec in enumerate(top, start=1)]
    for row, (cloud, anchor, name) in enumerate(((pic.src, pic.src, "source"), (pic.ref, aligned, "reference")), start=1):
        for k, mask in enumerate(pic.masks):
            stage = "truth" if k == len(pic.masks) - 1 else f"iter. {k + 1}"
            colours = np.where(mask[row - 1], OVERLAP, REST)
            panels.append((row * columns + k + 1, [(cloud, colours)], anchor, f"OMNet mask, {stage}\n({name})"))
    for slot, clouds, anchor, title in panels:
        panel(fig, grid, slot, clouds, centre(anchor), half, view, title)
    fig.suptitle(pic.title, fontsize=8)
    return [title for *_, title in panels]


def render(pictures: Sequence[PairPicture], labels: dict[str, str], path: Path, view: tuple[float, float] = (20.0, -60.0),
           dpi: int = 80) -> list[str]:
    """Write the PNG: one block of rows per pair (a subfigure titled with the pair); the panel titles."""
    columns = max(max(3 + len(p.estimates), len(p.masks)) for p in pictures)
    rows = [3 if p.masks else 1 for p in pictures]
    fig = plt.figure(figsize=(PANEL_INCHES * columns, PANEL_INCHES * sum(rows) + 0.3 * len(pictures)))
    subfigures = fig.subfigures(len(pictures), 1, height_ratios=rows, squeeze=False)[:, 0]
    titles = [t for sub, pic in zip(subfigures, pictures) for t in draw_pair(sub, pic, labels, view, columns)]
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return titles


# --- command line -------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.plots.figures", description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of the test set, e.g. data.source=PATH")
    parser.add_argument("--experiment", default="scan_pairs", help="conf/exp/<name>.yaml (default scan_pairs)")
    parser.add_argument("--sampling", default="ts")
    parser.add_argument("--partial", default="prnet")
    parser.add_argument("--pairs", default=None, help="comma-separated pair indices")
    parser.add_argument("--grid", type=Path, default=None, help="a benchmarks.grid output folder, for --pick")
    parser.add_argument("--pick", default="worst,median,best", help=f"with --grid: from {', '.join(PICKS)}")
    parser.add_argument("--by", default="omnet", help="with --grid: the method whose Error(R) picks the pairs")
    parser.add_argument("--methods", default="icp,fgr,symmetric_icp,goicp,omnet")
    parser.add_argument("--checkpoint", default=None, help="the learned methods' checkpoint (a src.train .ckpt)")
    parser.add_argument("--workers", type=int, default=1, help="processes for the classical methods")
    parser.add_argument("--timeout", type=float, default=60.0, help="per pair and classical method, in seconds")
    parser.add_argument("--view", default="20,-60", help="camera elevation,azimuth in degrees (y is up)")
    parser.add_argument("--dpi", type=int, default=80)
    parser.add_argument("--out", type=Path, default=Path("outputs/figures/pairs.png"))
    return parser


def _chosen_pairs(args: argparse.Namespace, test_set) -> dict[int, str]:
    """``{pair index: note for its title}`` from ``--pairs`` or ``--grid``/``--pick``/``--by``."""
    if args.pairs is not None:
        indices = [int(i) for i in args.pairs.split(",") if i.strip()]
        bad = [i for i in indices if not 0 <= i < len(test_set.dataset)]
        if bad or not indices:
            raise ConfigError(f"--pairs {args.pairs}: the test set {test_set.key} has pairs 0..{len(test_set.dataset) - 1}")
        return dict.fromkeys(indices, "")
    if args.grid is None:
        raise ConfigError("choose the pairs: --pairs i,j,... or --grid DIR (with --pick and --by)")
    from benchmarks.plots.sweep import grid_pairs

    rows = grid_pairs(args.grid, test_set)
    rows = rows[rows["method"] == args.by]
    if rows.empty:
        raise ConfigError(f"{args.grid} has no {args.by} cell on {test_set.key}: choose --by among its methods")
    picked = pick_pairs(dict(zip(rows["pair"], rows[ERROR_R])), [p.strip() for p in args.pick.split(",")])
    return {i: f" ({pick} Error(R) of {display_name(args.by)} in the grid)" for i, pick in picked.items()}


def run(args: argparse.Namespace) -> list[str]:
    """Draw the chosen pairs into ``args.out``; the panel titles."""
    from src.pair_sets import build_test_set

    view = tuple(float(v) for v in args.view.split(","))
    if len(view) != 2:
        raise ConfigError(f"--view takes elevation,azimuth, got {args.view!r}")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    registrators = build_registrators(methods, args.checkpoint)
    test_set = build_test_set(args.experiment, args.sampling, args.partial, None, args.overrides)
    pics = pictures(test_set.dataset, _chosen_pairs(args, test_set), registrators, args.workers, args.timeout)
    labels = {m: getattr(r, "label", None) or display_name(m) for m, r in registrators.items()}
    return render(pics, labels, args.out, view, args.dpi)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        titles = run(args)
    except (UserError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({len(titles)} panels, {args.out.stat().st_size / 1e6:.2f} MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
