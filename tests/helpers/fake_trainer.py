"""A stand-in for ``python -m src.train`` in the chain's tests (``python -m tests.helpers.fake_trainer KEY=VALUE ...``):
it "trains" ``steps=N`` steps of ``step_s=S`` seconds in ``hydra.run.dir``, continuing the step of ``ckpt_path`` (``last``: the folder's ``last.ckpt`` when there is one),
and on SIGTERM writes ``checkpoints/last.ckpt`` at the end of the step and exits 143, as src.train does;
``fail=1`` exits 1 at once. Each call appends its arguments to ``calls.txt`` in the run folder."""

from __future__ import annotations

import signal
import sys
import time
from pathlib import Path


def _torch():
    """torch, imported only to read or write a checkpoint: a first call starts "training" at once."""
    import torch

    return torch


def main(argv: list[str]) -> int:
    args = dict(a.split("=", 1) for a in argv)
    run = Path(args["hydra.run.dir"])
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    with (run / "calls.txt").open("a") as calls:
        calls.write(" ".join(argv) + "\n")
    if args.get("fail") == "1":
        return 1
    steps = int(args["steps"])
    (run / "config_resolved.yaml").write_text(f"trainer:\n  max_steps: {steps}\n")
    stop: list[bool] = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    checkpoint = run / "checkpoints" / "last.ckpt" if args.get("ckpt_path") == "last" else args.get("ckpt_path")
    step = _torch().load(checkpoint, weights_only=False)["global_step"] if checkpoint and Path(checkpoint).is_file() else 0
    (run / "training").touch()
    while step < steps and not stop:
        time.sleep(float(args.get("step_s", "0.05")))
        step += 1
    _torch().save({"global_step": step}, run / "checkpoints" / "last.ckpt")
    return 143 if stop else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
