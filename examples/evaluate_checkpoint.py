"""Evaluate a shipped checkpoint on its experiment's fixed test set, next to ICP, from Python.

Shows the pieces ``src.eval`` and the grid are made of: a checkpoint's card (``checkpoints/<name>.json``) names its
experiment; ``src.pair_sets.build_test_set`` gives that experiment's fixed test pairs (the ones
``python -m src.eval +exp=<experiment>`` evaluates); ``get_registrator(<method>, checkpoint=...)`` registers them;
``src.metrics.RegistrationMetrics`` scores them with the paper's metrics. The default checkpoint was trained on the
embedded synthetic data, which is built on first use (a few seconds, under $OMNET_CACHE_DIR).

    python examples/evaluate_checkpoint.py                     # the shipped synthetic OMNet, 32 pairs
    python examples/evaluate_checkpoint.py --pairs 8           # fewer pairs
    python -m src.eval +exp=unseen_categories data=synthetic   # the same checkpoint on the whole test set
"""

import argparse
import json
from pathlib import Path

import torch

from baselines import get_registrator, run_pairs
from baselines.learned.adapter import run_batches
from src.pair_sets import build_test_set
from src.metrics import RegistrationMetrics

CHECKPOINTS = Path(__file__).resolve().parents[1] / "checkpoints"
parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("--checkpoint", type=Path, default=CHECKPOINTS / "omnet_unseen_categories_synthetic_ts_prnet.ckpt")
parser.add_argument("--pairs", type=int, default=32, help="the first N pairs of the test set")
args = parser.parse_args()

card = json.loads(args.checkpoint.with_suffix(".json").read_text())
exp = card["experiment"]
test_set = build_test_set(exp["task"], exp["sampling"], exp["partial"], exp["dataset"], [])
pairs = test_set.pairs(min(args.pairs, len(test_set.dataset)))
print(f"{card['name']}: {exp['task']} on {exp['dataset']} ({exp['sampling']}, {exp['partial']}), {len(pairs)} test pairs")

omnet = get_registrator(card.get("method", "omnet"), checkpoint=str(args.checkpoint), device="cpu")
clouds = [(src, ref) for src, ref, _ in pairs]
for label, results in [("ICP", run_pairs(get_registrator("icp"), clouds, workers=0, progress=False)),
                       (omnet.label, run_batches(omnet, clouds, progress=False))]:
    metrics = RegistrationMetrics(test_set.cfg.model.euler_seq)
    for result, (src, ref, gt) in zip(results, pairs):
        metrics.update(torch.tensor(result.transform)[None], torch.as_tensor(gt)[None],
                       torch.as_tensor(src)[None], torch.as_tensor(ref)[None])
    values = metrics.compute()
    print(f"{label}: Error(R) {values['Error(R)']:.3f} deg, Error(t) {values['Error(t)']:.4f}, "
          f"RMSE(R) {values['RMSE(R)']:.3f} deg, {1000 * sum(r.seconds for r in results) / len(results):.1f} ms/pair")
