"""Pairs of point clouds drawn from a cache split, with per-sample seeded randomness."""

from __future__ import annotations

import math
from typing import Iterator

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import Dataset, Sampler

from src.data.transforms import CLOUDS, Compose
from src.utils.errors import ConfigError, PointCloudError
from src.geometry.clouds import check_cloud

TRAIN_STREAM, EVAL_STREAM = 1, 0


def float_tensor(array: np.ndarray) -> torch.Tensor:
    """A sample's array as a contiguous float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


class PairDataset(Dataset):
    """One registration pair per index.

    Index ``k`` maps to shape ``shape_indices[k % len(self)]``; its randomness comes from
    ``default_rng([seed, stream, k])``. Evaluation uses ``k < len(self)`` (a fixed set); training
    uses the virtual indices ``epoch * len(self) + i`` of :class:`EpochSampler`, so every epoch
    draws new pairs yet any run, worker count or resume reproduces them.

    With ``normals`` (the split's ``(N, S, P, 3)`` array) every item also holds ``normals_src`` and
    ``normals_ref``, unit, row for row with the points (see :mod:`src.data.transforms`); the points
    and ground truth are the same as without them. Every item also holds ``points_raw`` when the pipeline
    keeps it (the reference's clean full cloud, :mod:`src.data.transforms`).
    """

    def __init__(
        self,
        points: np.ndarray,
        labels: np.ndarray,
        shape_indices: np.ndarray,
        transforms: Compose,
        seed: int,
        stream: int = EVAL_STREAM,
        normals: np.ndarray | None = None,
    ) -> None:
        if len(shape_indices) == 0:
            raise PointCloudError("the selected split has no shapes: check data.splits (categories, slice)")
        if normals is not None and normals.shape != points.shape:
            raise PointCloudError(f"normals of shape {normals.shape} do not match the points' {points.shape}")
        self.points, self.normals, self.labels = points, normals, labels
        self.shape_indices = np.asarray(shape_indices)
        self.transforms, self.seed, self.stream = transforms, seed, stream

    def __len__(self) -> int:
        return len(self.shape_indices)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        shape = int(self.shape_indices[index % len(self)])
        rng = np.random.default_rng([self.seed, self.stream, int(index)])
        start = {"shape_points": self.points[shape]}
        if self.normals is not None:
            start["shape_normals"] = self.normals[shape]
        sample = self.transforms(start, rng)
        kinds = ("points",) if self.normals is None else ("points", "normals")
        item = {f"{kind}_{cloud}": sample[f"{kind}_{cloud}"] for kind in kinds for cloud in CLOUDS}
        if "points_raw" in sample:
            item["points_raw"] = sample["points_raw"]
        for key, array in item.items():
            try:
                check_cloud(array, key, allow_degenerate=True)
            except PointCloudError as err:
                raise PointCloudError(f"pair {index} (shape {shape}): {err}: check the dataset cache (rebuild it with "
                                      "`python -m src.data.prepare`) and the crop settings (data.pair)") from None
        return {
            **{key: float_tensor(array) for key, array in item.items()},
            "transform_gt": float_tensor(sample["transform_gt"]),
            "label": torch.tensor(int(self.labels[shape])),
            "idx": torch.tensor(int(index)),
        }


def _world_and_rank() -> tuple[int, int]:
    initialized = dist.is_available() and dist.is_initialized()
    return (dist.get_world_size(), dist.get_rank()) if initialized else (1, 0)


class EpochSampler(Sampler[int]):
    """Shuffled virtual indices ``epoch * n + perm[i]`` (see :class:`PairDataset`), split across DDP ranks.

    The permutation depends only on (seed, epoch), so training order and pairs are reproducible.
    :meth:`resume_at` makes the next pass start mid-epoch, where a checkpoint left off.
    """

    def __init__(self, size: int, seed: int, shuffle: bool = True) -> None:
        self.size, self.seed, self.shuffle, self.epoch = size, seed, shuffle, 0
        self.world, self.rank = _world_and_rank()
        self.per_rank = math.ceil(size / self.world)
        self._skip = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def resume_at(self, epoch: int, samples_done: int) -> None:
        """The next iteration is epoch ``epoch`` without its first ``samples_done`` samples (this rank's)."""
        if not 0 <= samples_done <= self.per_rank:
            raise ValueError(f"cannot resume {samples_done} samples into an epoch of {self.per_rank}")
        self.epoch, self._skip = epoch, samples_done

    def __len__(self) -> int:
        return self.per_rank

    def __iter__(self) -> Iterator[int]:
        skip, self._skip = self._skip, 0  # a resume position applies to one pass only
        order = np.arange(self.size)
        if self.shuffle:
            order = np.random.default_rng([self.seed, self.epoch]).permutation(self.size)
        order = np.resize(order, self.per_rank * self.world)  # pad by wrapping so ranks get equal counts
        for i in order[self.rank :: self.world][skip:]:
            yield int(self.epoch * self.size + i)


class EvalShardSampler(Sampler[int]):
    """Fixed evaluation indices ``0..size-1`` split across DDP ranks by whole batches, never padded.

    Batch ``b`` (indices ``b*batch_size ... (b+1)*batch_size - 1``) goes to rank ``b % world``, so
    every pair is evaluated exactly once and in the same batch as in a single-process run: the
    sum-reduced metrics (:class:`~src.metrics.RegistrationMetrics`) equal the single-process ones up
    to the order of the final float64 sum. Ranks may get different numbers of batches (the
    LightningModule logs eval losses per epoch only, so uneven counts cannot deadlock). A rank
    without any batch would skip the epoch-end synchronisation and hang the others, so fewer
    batches than ranks is an error. Without DDP this is ``range(size)`` (the old sequential order).
    """

    def __init__(self, size: int, batch_size: int, world: int | None = None, rank: int | None = None) -> None:
        if batch_size < 1:
            raise ConfigError(f"eval batch size must be >= 1, got {batch_size}")
        auto_world, auto_rank = _world_and_rank()
        self.size, self.batch_size = size, batch_size
        self.world = auto_world if world is None else world
        self.rank = auto_rank if rank is None else rank
        num_batches = math.ceil(size / batch_size)
        if num_batches < self.world:
            raise ConfigError(
                f"{size} evaluation pairs make {num_batches} batch(es) of data.eval_batch_size={batch_size}, fewer than "
                f"the {self.world} DDP processes: lower data.eval_batch_size or trainer.devices/num_nodes"
            )
        self.batches = list(range(self.rank, num_batches, self.world))

    def __len__(self) -> int:
        return sum(min(self.batch_size, self.size - b * self.batch_size) for b in self.batches)

    def __iter__(self) -> Iterator[int]:
        for b in self.batches:
            yield from range(b * self.batch_size, min((b + 1) * self.batch_size, self.size))
