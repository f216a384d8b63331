"""Where an iterative network's error stops falling: mean and median Error(R) and Error(t) after each of its
iterations (the poses its forward pass returns, ``outputs["transforms"]``) on an experiment's fixed validation and
test pairs, the pairs training and ``src.eval`` see (``benchmarks.studies.diagnostics.split_gap.split_pairs``).

    python -m benchmarks.studies.diagnostics.iteration_errors --exp real_airplane --checkpoint checkpoints/omnet_real_airplane_ts_prnet.ckpt
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from benchmarks.studies.diagnostics.split_gap import split_pairs
from src.config import euler_seq_for
from src.utils.errors import ConfigError, exit_code_of
from src.metrics import ERROR_R, ERROR_T, pair_errors

BATCH = 25


def iteration_errors(network: torch.nn.Module, pairs: list, partial: str, batch: int = BATCH) -> pd.DataFrame:
    """One row per iteration: mean and median Error(R) [deg] and Error(t) of ``network``'s pose after it."""
    rotations, translations = [], []
    with torch.no_grad():
        for start in range(0, len(pairs), batch):
            chunk = pairs[start:start + batch]
            src, ref, gt = (torch.from_numpy(np.stack(column)) for column in zip(*chunk))
            transforms = network(src, ref)["transforms"]
            errors = [pair_errors(t.float(), gt, euler_seq_for(partial)) for t in transforms]
            rotations.append(torch.stack([e["rot_deg"] for e in errors], dim=1))
            translations.append(torch.stack([e["trans_norm"] for e in errors], dim=1))
    rotation, translation = torch.cat(rotations).numpy(), torch.cat(translations).numpy()
    return pd.DataFrame({"iteration": np.arange(1, rotation.shape[1] + 1), ERROR_R: rotation.mean(0),
                         f"{ERROR_R} median": np.median(rotation, 0), ERROR_T: translation.mean(0),
                         f"{ERROR_T} median": np.median(translation, 0)})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.diagnostics.iteration_errors", description=__doc__.split("\n\n")[0])
    parser.add_argument("--exp", default="real_airplane", help="an experiment with a val and a test split")
    parser.add_argument("--checkpoint", type=Path, required=True, help="a src.train checkpoint of an iterative network")
    parser.add_argument("--sampling", default="ts", choices=("os", "ts"))
    parser.add_argument("--partial", default="prnet", choices=("prnet", "rpmnet"))
    args = parser.parse_args(argv)

    def action() -> None:
        from src.run.checkpoint_io import read_checkpoint
        from src.models.module import RegistrationModule

        read_checkpoint(args.checkpoint)  # a missing or unreadable file: one line
        network = RegistrationModule.load_from_checkpoint(args.checkpoint, map_location="cpu").network.eval()
        for split, pairs in split_pairs(args.exp, args.sampling, args.partial).items():
            table = iteration_errors(network, pairs, args.partial)
            if len(table) < 2:
                raise ConfigError(f"{args.checkpoint} is not an iterative network (one pose per pair)")
            print(f"\n{split} ({len(pairs)} pairs of +exp={args.exp}, {args.sampling}, {args.partial}):")
            print(table.to_markdown(index=False, floatfmt=("d",) + (".3f",) * 4))

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
