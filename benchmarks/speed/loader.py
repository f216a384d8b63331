"""Training pairs an experiment's loader makes per CPU-second: how many loader workers keep a training step fed.

    python -m benchmarks.speed.loader +exp=real_airplane                                # one process, process CPU time
    python -m benchmarks.speed.loader +exp=unseen_shapes data=synthetic partial=rpmnet --batches 40
    python -m benchmarks.speed.loader +exp=real_airplane --workers 8                    # wall clock, 8 worker processes

The experiment's train loader (the datamodule of ``conf/`` composed with the overrides, ``data.batch_size``
pairs a batch) is iterated for ``--batches`` batches after one untimed batch. With ``--workers 0`` (default) the
pairs are made in this process, with one torch thread: the rate is pairs per second of this process's CPU time
(``time.process_time``), what one loader worker process makes per second of a core it has to itself, and does
not depend on other jobs sharing the machine. With ``--workers N`` the rate is wall-clock pairs per second of N
worker processes (persistent, as in training: started once), plus their CPU time (read when they exit,
``RUSAGE_CHILDREN``) and the rate per CPU-second.
Each result is printed as one Markdown row, with the command.
"""

from __future__ import annotations

import argparse
import gc
import resource
import sys
import time
from dataclasses import dataclass

from src.utils.errors import ConfigError, exit_code_of


@dataclass(frozen=True)
class LoaderRate:
    """Pairs made by a loader, with the wall time and the CPU time of the processes that made them."""

    pairs: int
    wall_s: float
    cpu_s: float
    workers: int

    @property
    def pairs_per_cpu_s(self) -> float:
        return self.pairs / self.cpu_s

    @property
    def pairs_per_s(self) -> float:
        return self.pairs / self.wall_s


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def measure(overrides: list[str], batches: int, workers: int = 0) -> LoaderRate:
    """The train loader of ``conf/`` composed with ``overrides`` and ``workers`` loader processes, timed over
    ``batches`` batches (its epochs repeated as needed); in-process, after a first untimed batch; with workers
    (persistent, as in training), their start-up is timed too, and their CPU time counted when they exit."""
    import hydra
    import torch

    from src.compose import compose_conf

    if batches < 1 or workers < 0:
        raise ConfigError(f"--batches must be at least 1 and --workers at least 0 (got {batches}, {workers})")
    torch.set_num_threads(1)
    cfg = compose_conf([*overrides, f"data.num_workers={workers}", "data.pin_memory=false",
                        f"data.persistent_workers={workers > 0}", "output_dir=unused"])
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("fit")
    loader = datamodule.train_dataloader()
    if len(loader) == 0:
        raise ConfigError("the train loader gives no batch (a training set smaller than data.batch_size)")
    if workers == 0:
        next(iter(loader))  # lazy imports and caches, untimed
    children, cpu, wall = _children_cpu_s(), time.process_time(), time.perf_counter()
    pairs = 0
    while pairs < batches * datamodule.batch_size:  # epochs again as needed (a small training set has few batches)
        for _, batch in zip(range(batches - pairs // datamodule.batch_size), loader):
            pairs += batch["points_src"].shape[0]
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    if workers:
        del loader, datamodule  # the persistent workers exit: their CPU time is counted once they are reaped
        gc.collect()
    return LoaderRate(pairs, wall, cpu + _children_cpu_s() - children, workers)


def describe(rate: LoaderRate) -> str:
    """One Markdown row: pairs, workers, wall and CPU seconds, pairs per wall second and per CPU-second."""
    return (f"| {rate.pairs:,} | {rate.workers} | {rate.wall_s:.2f} | {rate.cpu_s:.2f} | {rate.pairs_per_s:,.0f} | "
            f"{rate.pairs_per_cpu_s:,.0f} |")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed.loader", description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="Hydra overrides of conf/ (e.g. +exp=real_airplane partial=rpmnet)")
    parser.add_argument("--batches", type=int, default=20, help="timed batches (default 20)")
    parser.add_argument("--workers", type=int, default=0, help="loader worker processes (default 0: this process)")
    args = parser.parse_args(argv)

    def action() -> None:
        rate = measure(args.overrides, args.batches, args.workers)
        print("| pairs | workers | wall s | CPU s | pairs/s | pairs/CPU-s |\n|---:|---:|---:|---:|---:|---:|")
        print(describe(rate))
        print(f"\ncommand: `python -m benchmarks.speed.loader {' '.join(argv if argv is not None else sys.argv[1:])}`")

    return exit_code_of(action)


if __name__ == "__main__":
    sys.exit(main())
