"""A learned method's point budget: a batch it cannot hold in memory is refused before it runs.

The (B, N, M) matrices of a batch of pairs grow with the square of the points per cloud: OMNet's close pairs behind its
mask labels, the Chamfer metric's distances at validation and test. Clouds beyond the memory stopped a run at its
first step with PyTorch's ``can't allocate memory`` traceback (or, nearer the limit, by the kernel's out-of-memory
killer, without a word). :func:`refuse_beyond_memory` compares a lower bound of what one step holds (the network's
own, where it states it: ``step_bytes``, and the metric's distances) with the memory the process has, before the run
trains or tests, and names the point budget: the most points per cloud that fit.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path

import lightning as L
import torch

from src.utils.errors import ConfigError

#: The setting that sizes the clouds a network sees, by partial manner (``data.pair.partial``).
CLOUD_SIZE = {"prnet": "data.pair.prnet_num_keep", "rpmnet": "data.pair.rpmnet_num_points"}
BATCH_SIZE = {"train": "data.batch_size", "val": "data.eval_batch_size", "test": "data.eval_batch_size"}
STAGE_NAMES = {"train": "training", "val": "validation", "test": "test"}


def step_bytes(network: torch.nn.Module, stage: str, batch: int, n: int, m: int) -> int:
    """A lower bound of the bytes one ``stage`` step on ``batch`` pairs of ``n`` and ``m`` points holds: the network's
    own (its ``step_bytes``, where it states one) and, at validation and test, after its pass, the (B,N,M) float32
    distances of the Chamfer metric (:func:`src.metrics.chamfer_distance`)."""
    own = network.step_bytes(batch, n, m, training=stage == "train") if hasattr(network, "step_bytes") else 0
    return own if stage == "train" else max(own, 4 * batch * n * m)


def point_budget(network: torch.nn.Module, stage: str, batch: int, n: int, m: int, available: int) -> int:
    """The most points per cloud (the source's; the reference's in proportion) whose ``stage`` step fits ``available``
    bytes at this batch size."""
    low, high = 0, n
    while low < high:
        middle = (low + high + 1) // 2
        if step_bytes(network, stage, batch, middle, math.ceil(middle * m / n)) <= available:
            low = middle
        else:
            high = middle - 1
    return low


def _cpu_available() -> int | None:
    """What the kernel estimates can be allocated without swapping (``MemAvailable``), within the cgroup's limit."""
    known = []
    try:
        found = re.search(r"^MemAvailable:\s+(\d+) kB", Path("/proc/meminfo").read_text(), re.M)
        known += [int(found[1]) * 1024] if found else []
    except OSError:
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            known.append(int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text()))
    except (OSError, ValueError):
        pass
    return min(known) if known else None


def available_bytes(device: torch.device) -> int | None:
    """The memory free for tensors on ``device`` (a GPU's free memory, or the CPU's); None where it is not known."""
    if device.type == "cuda":
        return torch.cuda.mem_get_info(device)[0]
    return _cpu_available() if device.type == "cpu" else None


def _size(size: int) -> str:
    return f"{size / 2**30:.1f} GiB" if size >= 2**30 else f"{size / 2**20:.0f} MiB"


def refuse_beyond_memory(network: torch.nn.Module, datamodule: L.LightningDataModule, trainer: L.Trainer,
                         stages: Sequence[str]) -> None:
    """ConfigError when a batch of one of ``stages`` (train, val, test) with the data module's clouds (the sizes of its
    first pair) needs more memory than the trainer's device has (on the CPU, shared by its processes): the sizes, the
    bytes, and the point budget with the setting that lowers the points per cloud."""
    device = trainer.strategy.root_device
    available = available_bytes(device)
    if available is None:
        return
    if device.type == "cpu":
        available //= trainer.num_devices
    for stage in stages:
        dataset = datamodule.datasets.get(stage)
        if not dataset:
            continue
        pair = dataset[0]
        n, m = len(pair["points_src"]), len(pair["points_ref"])
        batch = datamodule.batch_size if stage == "train" else min(datamodule.eval_batch_size, len(dataset))
        need = step_bytes(network, stage, batch, n, m)
        if need <= available:
            continue
        budget = point_budget(network, stage, batch, n, m, available)
        cloud_size = CLOUD_SIZE.get(getattr(datamodule, "pair", {}).get("partial"), "data.pair.num_points")
        raise ConfigError(
            f"{type(network).__name__} cannot hold a {STAGE_NAMES[stage]} batch in memory: {batch} pairs of {n} and {m} "
            f"points need at least {_size(need)} ((B, N, M) pairwise matrices and per-point activations), more than the "
            f"{_size(available)} available on {device.type}; its point budget there is at most {budget} points per cloud at "
            f"{BATCH_SIZE[stage]}={batch}: use fewer points per cloud ({cloud_size}), or a smaller {BATCH_SIZE[stage]}"
        )
