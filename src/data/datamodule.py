"""LightningDataModule: cache → category/split selection → pair transforms → loaders."""

from __future__ import annotations

import difflib
import functools
import inspect
import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader

from src.data.cache import Cache, CacheSplit, default_cache_root
from src.data.categories import AXISYMMETRIC_CATEGORIES
from src.data.datasets import get_dataset
from src.data.dataset import EVAL_STREAM, TRAIN_STREAM, EpochSampler, EvalShardSampler, PairDataset
from src.data.prepare import ensure_cache
from src.data.pipelines import build_pair_transforms
from src.data.transforms import NORMALS
from src.utils.config_values import plain
from src.utils.errors import ConfigError, DatasetError
from src.utils.interrupts import loader_worker_init

STAGES = ("train", "val", "test")
log = logging.getLogger(__name__)


def resolve_categories(spec: str | Sequence[str], cache: Cache, remove_axisymmetric: bool) -> list[str]:
    """``"half1"``/``"half2"`` (the manifest's halves), ``"all"``, or an explicit list of names."""
    if isinstance(spec, str):
        if spec == "all":
            names = list(cache.categories)
        elif spec in ("half1", "half2"):
            names = list(cache.halves[spec[-1]])
        else:
            raise ConfigError(f"categories must be 'half1', 'half2', 'all' or a list of names, got {spec!r}")
    else:
        names = list(spec)
        unknown = sorted(set(names) - set(cache.categories))
        if unknown:
            raise ConfigError(f"unknown categories {unknown} for dataset {cache.dataset!r}; it has {cache.categories}")
    return [c for c in names if not (remove_axisymmetric and c in AXISYMMETRIC_CATEGORIES)]


SPEC_KEYS = ("split", "categories", "slice", "carve", "as_many_as", "exclude", "repeat", "instead", "when_missing")
"""What a ``data.splits.<stage>`` entry may hold (:func:`select_shapes`)."""


def select_shapes(
    cache: Cache, spec: Mapping[str, Any], remove_axisymmetric: bool, stages: Mapping[str, Mapping] | None = None,
) -> tuple[str, np.ndarray]:
    """Indices into ``cache.split(spec['split'])`` of the requested categories, then ``spec['carve']``
    (``[seed, start, stop]``: per category, the fractions ``[start, stop)`` of a permutation seeded by ``seed``
    and the category, e.g. a stratified validation carve-out), then ``spec['as_many_as']`` (``[seed, split]``: per
    category, a seeded draw of as many shapes as ``split`` has of it, built or withheld, e.g. a stand-in for a
    withheld test split with its composition), then ``spec['slice']`` (``[start, stop]`` as a
    Python slice over them in split-list order, e.g. ``[-100, null]``), less the shapes of the ``stages``
    that ``spec['exclude']`` names (e.g. ``[val]``: several categories but one category's validation
    carve-out; a stage drawn from another split excludes none), then each repeated ``spec['repeat']`` times
    (several fixed pairs per shape, e.g. for a few real scans). Where the cache has not built the split
    ``spec['when_missing']`` (default: ``spec['split']``; e.g. a withheld test split), ``spec['instead']``
    is selected in its place (:func:`effective_spec`)."""
    spec = effective_spec(cache, spec)
    unknown = set(spec) - set(SPEC_KEYS)
    if unknown:
        raise ConfigError(f"data.splits entries take {', '.join(SPEC_KEYS)}; unknown: {sorted(unknown)}")
    split = cache.split(spec["split"])
    categories = resolve_categories(spec.get("categories", "all"), cache, remove_axisymmetric)
    wanted = [cache.categories.index(c) for c in categories]
    labels = np.asarray(split.labels)
    indices = np.flatnonzero(np.isin(labels, wanted))
    if spec.get("carve") is not None:
        indices = _carve(indices, labels[indices], spec["carve"])
    if spec.get("as_many_as") is not None:
        indices = _as_many_as(indices, labels[indices], spec["as_many_as"], cache)
    bounds = spec.get("slice")
    if bounds is not None:
        indices = indices[slice(*(None if b is None else int(b) for b in bounds))]
    for stage in spec.get("exclude", ()):
        other = (stages or {}).get(stage)
        if other is None or "exclude" in effective_spec(cache, other):
            raise ConfigError(f"data.splits exclude: {stage!r} must be a stage without exclude")
        other_split, other_indices = select_shapes(cache, other, remove_axisymmetric)
        if other_split == spec["split"]:
            indices = indices[~np.isin(indices, other_indices)]
    repeat = int(spec.get("repeat", 1))
    if repeat < 1:
        raise ConfigError(f"data.splits repeat must be >= 1, got {repeat}")
    return spec["split"], np.tile(indices, repeat)


def effective_spec(cache: Cache, spec: Mapping[str, Any]) -> Mapping[str, Any]:
    """``spec['instead']`` where the cache has not built the split ``spec['when_missing']`` (default:
    ``spec['split']``), else ``spec`` without those two keys."""
    if not isinstance(spec.get("split"), str):
        raise ConfigError(f"data.splits entry {dict(spec)} names no split: give split: train or split: test")
    if not _uses_instead(cache, spec):
        return {key: value for key, value in spec.items() if key not in ("instead", "when_missing")}
    if not isinstance(spec["instead"], Mapping) or "instead" in spec["instead"]:
        raise ConfigError(f"data.splits instead: {spec['instead']!r} must be one split entry without instead")
    return spec["instead"]


def _uses_instead(cache: Cache, spec: Mapping[str, Any]) -> bool:
    return "instead" in spec and spec.get("when_missing", spec["split"]) not in cache.available_splits


def resolve_splits(cache: Cache, splits: Mapping[str, Mapping[str, Any]]) -> tuple[dict, list[str]]:
    """Every stage's :func:`effective_spec`, and one line for each stage that uses its ``instead``."""
    resolved, notes = {}, []
    for stage, spec in splits.items():
        resolved[stage] = plain(effective_spec(cache, spec))
        if _uses_instead(cache, spec):
            needed = spec.get("when_missing", spec["split"])
            notes.append(f"data.splits.{stage}: the {cache.dataset} cache has no {needed} split "
                         f"({_missing_count(cache, needed)}): using its stated alternative {resolved[stage]}")
    return resolved, notes


def _missing_count(cache: Cache, split: str) -> str:
    missing = cache.manifest.get("missing_splits", {}).get(split)
    return f"{missing['count']} shapes withheld" if missing and missing.get("count") else "not built"


def _carve(indices: np.ndarray, labels: np.ndarray, carve: Sequence[Any]) -> np.ndarray:
    """The ``[start, stop)`` fractions of each category's seeded permutation (``carve = [seed, start, stop]``),
    in split-list order; the same seed's fractions ``[a, b)`` and ``[b, c)`` never share a shape."""
    try:
        seed, start, stop = int(carve[0]), float(carve[1]), float(carve[2])
        ok = len(carve) == 3 and 0.0 <= start <= stop <= 1.0
    except (TypeError, ValueError, IndexError):
        ok = False
    if not ok:
        raise ConfigError(f"data.splits carve={list(carve) if isinstance(carve, Sequence) else carve!r} is invalid: "
                          "give [seed, start, stop] with 0 <= start <= stop <= 1")
    return _per_category(indices, labels, seed, lambda label, n: slice(int(round(start * n)), int(round(stop * n))))


def _per_category(indices: np.ndarray, labels: np.ndarray, seed: int,
                  part: Callable[[int, int], slice]) -> np.ndarray:
    """The union over categories of ``part(label, size)`` of each category's permutation seeded by
    ``[seed, label]``, in split-list order."""
    kept = []
    for label in np.unique(labels):
        members = indices[labels == label]
        order = np.random.default_rng([seed, int(label)]).permutation(len(members))
        kept.append(members[order[part(int(label), len(members))]])
    return np.sort(np.concatenate(kept)) if kept else indices[:0]


def _as_many_as(indices: np.ndarray, labels: np.ndarray, as_many_as: Sequence[Any], cache: Cache) -> np.ndarray:
    """Per category, the first ``n`` of a seeded permutation (``as_many_as = [seed, split]``), ``n`` the number of
    shapes of that category in ``split`` (:meth:`Cache.category_counts`; all of the category where it has fewer);
    in split-list order. The seeds are :func:`_carve`'s, so ``as_many_as: [s, test]`` draws from the front of
    ``carve: [s, ...]``'s permutation."""
    try:
        seed, split = int(as_many_as[0]), str(as_many_as[1])
        ok = len(as_many_as) == 2 and split in (*cache.available_splits, *cache.manifest.get("missing_splits", {}))
    except (TypeError, ValueError, IndexError, KeyError):
        ok = False
    if not ok:
        raise ConfigError(f"data.splits as_many_as={as_many_as!r} is invalid: give [seed, split] with a split of the "
                          f"{cache.dataset} cache ({', '.join(cache.available_splits)}) or one it withheld")
    counts = cache.category_counts(split)
    return _per_category(indices, labels, seed, lambda label, n: slice(0, counts.get(cache.categories[label], 0)))


#: Layouts whose clouds are whole samplings of a shape (``data.pair.num_points`` picks no points there).
_WHOLE_SAMPLINGS = ("independent_samplings", "single_sampling")


def check_pair_layout(pair: Mapping[str, Any], pair_sampling: str, cloud_points: int, dataset: str) -> None:
    """ConfigError for ``data.pair.num_points`` on a cache layout that cannot honour it: each cloud is a whole
    sampling of ``cloud_points`` points (meshes, synthetic, PointNet h5); only the PointNet++ resampled layout
    (``disjoint_subsets``) picks ``num_points`` of a shape's points. The sampling's own size passes."""
    wanted = pair.get("num_points")
    if pair_sampling not in _WHOLE_SAMPLINGS or wanted is None or wanted == cloud_points:
        return
    build = (f"data.build.num_points={wanted}" if get_dataset(dataset).generated
             else f"python -m src.data.prepare {dataset} --source PATH --num-points {wanted}")
    raise ConfigError(
        f"data.pair.num_points={wanted} cannot take effect on the {dataset} cache (layout {pair_sampling}): each "
        f"cloud is a whole sampling of {cloud_points} points; sample {wanted} points per sampling ({build}), "
        f"or use data.pair.num_points={cloud_points}"
    )


def check_pair_keys(pair: Mapping[str, Any]) -> None:
    """ConfigError for a ``data.pair`` key (nested ones included) that the pair pipeline
    (:func:`~src.data.pipelines.build_pair_transforms`) does not take, with the close matches."""
    takes = [name for name in inspect.signature(build_pair_transforms).parameters if name != "pair_sampling"]
    unknown = sorted(set(pair) - set(takes))
    if unknown:
        close = difflib.get_close_matches(unknown[0], takes, n=3)
        hint = f"did you mean {', '.join(f'data.pair.{k}' for k in close)}?" if close else f"it takes {', '.join(takes)}"
        raise ConfigError(f"data.pair.{unknown[0]} is not a pair setting (nothing reads it): {hint}")


class RegistrationDataModule(L.LightningDataModule):
    """Train/val/test pair loaders for one experiment.

    ``splits`` maps each stage to ``{split, categories, slice}``; ``pair`` holds the pair-transform
    parameters (:func:`~src.data.pipelines.build_pair_transforms`); ``normals`` is one of
    :data:`NORMALS`.
    """

    def __init__(
        self,
        dataset: str = "synthetic",
        cache_root: str | None = None,
        splits: Mapping[str, Mapping[str, Any]] | None = None,
        remove_axisymmetric: bool = True,
        pair: Mapping[str, Any] | None = None,
        batch_size: int = 64,
        eval_batch_size: int = 64,
        num_workers: int = 4,
        pin_memory: bool = True,
        persistent_workers: bool = True,
        seed: int = 1234,
        build: Mapping[str, Any] | None = None,
        normals: str = "none",
    ) -> None:
        super().__init__()
        for key, value in (("splits", splits), ("pair", pair), ("build", build)):
            if value is not None and not isinstance(value, Mapping):
                raise ConfigError(f"data.{key}={value!r} is invalid: it must be a mapping of settings (data.{key}.<key>=...)")
        if normals not in NORMALS:
            raise ConfigError(f"data.normals must be one of {NORMALS}, got {normals!r}")
        self.dataset, self.normals = dataset, normals
        self.cache_root = Path(cache_root).expanduser() if cache_root else default_cache_root()
        self.splits = plain(splits or {})
        unknown = set(self.splits) - set(STAGES)
        if unknown:
            raise ConfigError(f"data.splits has unknown stages {sorted(unknown)}; expected {STAGES}")
        for stage, spec in self.splits.items():
            if not isinstance(spec, Mapping):
                raise ConfigError(f"data.splits.{stage}={spec!r} is invalid: it must be a mapping such as "
                                  "{split: test, categories: [airplane], slice: [-100, null]}")
        self.remove_axisymmetric = remove_axisymmetric
        self.pair = dict(pair or {})
        check_pair_keys(self.pair)
        self.batch_size, self.eval_batch_size = batch_size, eval_batch_size
        self.num_workers = num_workers
        self.pin_memory = pin_memory and torch.cuda.is_available()
        self.persistent_workers = persistent_workers and num_workers > 0
        self.seed, self.build = seed, dict(build or {})
        self.datasets: dict[str, PairDataset] = {}
        self.cache: Cache | None = None
        self._train_sampler: EpochSampler | None = None
        self._resume_position: dict[str, int] | None = None

    def setup(self, stage: str | None = None) -> None:
        if self.cache is None:
            self.cache = ensure_cache(self.dataset, self.cache_root, **self.build)
            self.splits, notes = resolve_splits(self.cache, self.splits)
            for note in notes:
                log.warning(note)
        wanted = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",), None: STAGES}.get(stage, STAGES)
        if "train" in wanted:
            self._refuse_leaks()
        transforms = build_pair_transforms(self.cache.pair_sampling, **self.pair)
        for name in wanted:
            if name in self.datasets or name not in self.splits:
                continue
            split, indices = select_shapes(self.cache, self.splits[name], self.remove_axisymmetric, self.splits)
            data = self.cache.split(split)
            check_pair_layout(self.pair, self.cache.pair_sampling, data.points.shape[2], self.dataset)
            stream = TRAIN_STREAM if name == "train" else EVAL_STREAM
            self.datasets[name] = PairDataset(data.points, data.labels, indices, transforms, self.seed, stream,
                                              normals=self._normals_of(data))

    def _refuse_leaks(self) -> None:
        """ConfigError if a training shape is also a validation or test shape (e.g. one category for
        both sides of ``+exp=real_unseen_category``, a carve-out that overlaps the training slice, or
        one shape id in two splits of a cache: shapes are compared by their ids across splits)."""
        if "train" not in self.splits:
            return
        split, train = select_shapes(self.cache, self.splits["train"], self.remove_axisymmetric, self.splits)
        train_names = set(np.asarray(self.cache.split(split).shape_names)[train])
        for name in ("val", "test"):
            spec = self.splits.get(name)
            if spec is None:
                continue
            other, indices = select_shapes(self.cache, spec, self.remove_axisymmetric, self.splits)
            names = np.asarray(self.cache.split(other).shape_names)[np.unique(indices)]
            shared = [n for n in names if n in train_names]
            if shared:
                where = "" if other == split else f" (cache splits {split!r} and {other!r} list the same shape ids)"
                raise ConfigError(
                    f"{len(shared)} shapes of the {name} set are also training shapes{where} (first: {shared[0]}): "
                    f"make data.splits.train and data.splits.{name} disjoint (slice, exclude or other categories)"
                )

    def _normals_of(self, data: CacheSplit) -> np.ndarray | None:
        """The split's normals when ``data.normals=cache`` (DatasetError if the cache has none)."""
        if self.normals == "none":
            return None
        if data.normals is None:
            raise DatasetError(
                f"data.normals=cache, but the {self.dataset} cache stores no normals for split {data.name!r}: build "
                "it with them (synthetic: data.build.normals=true; meshes: `python -m src.data.prepare ... --normals`; "
                "the PointNet++ resampled layout always has them) or use data.normals=none "
                "(RPMNet: model.network.normals=estimated)"
            )
        return data.normals

    def _loader_options(self) -> dict[str, Any]:
        rank = self.trainer.global_rank if self.trainer is not None else 0
        return {"num_workers": self.num_workers, "pin_memory": self.pin_memory,
                "persistent_workers": self.persistent_workers,
                "worker_init_fn": functools.partial(loader_worker_init, rank=rank)}

    def train_dataloader(self) -> DataLoader:
        self._require("train")
        self._train_sampler = EpochSampler(len(self.datasets["train"]), self.seed)
        if self._resume_position is not None:
            self._train_sampler.resume_at(self._resume_position["epoch"],
                                          self._resume_position["batches_done"] * self.batch_size)
            self._resume_position = None
        # its own generator: creating an iterator draws a worker seed, which must not consume the
        # global RNG (a resumed run creates one mid-epoch, where the uninterrupted run does not)
        return DataLoader(self.datasets["train"], batch_size=self.batch_size, sampler=self._train_sampler,
                          drop_last=True, generator=torch.Generator(), **self._loader_options())

    def state_dict(self) -> dict[str, int]:
        """Where training is in the data (epoch, batches done), saved in every Lightning checkpoint and
        restored by :meth:`load_state_dict` before the resumed fit builds its loader, so a run resumed
        from a mid-epoch checkpoint sees exactly the batches the uninterrupted run would have. Counts
        are the trainer's (Lightning prefetches a batch ahead, so the loader cannot know what was
        trained on); an epoch the trainer has closed (ended, or stopped by max_steps/max_time) resumes
        at the next one, as Lightning's loops do."""
        if self._train_sampler is None or self.trainer is None:
            return {}
        fit_loop = self.trainer.fit_loop
        epoch, done = self._train_sampler.epoch, fit_loop.epoch_loop.batch_progress.current.processed
        epoch_closed = fit_loop.epoch_progress.current.completed > epoch
        if epoch_closed or done >= self.trainer.num_training_batches:  # (limit_train_batches included)
            epoch, done = epoch + 1, 0
        return {"epoch": epoch, "batches_done": done, "batch_size": self.batch_size}

    def load_state_dict(self, state_dict: dict[str, int]) -> None:
        if not state_dict:
            return
        if state_dict["batch_size"] != self.batch_size:
            raise ConfigError(
                f"the checkpoint was trained with data.batch_size={state_dict['batch_size']}, this run uses "
                f"{self.batch_size}: resume with the same batch size"
            )
        self._resume_position = dict(state_dict)

    def _require(self, name: str) -> None:
        if name not in self.splits:
            raise ConfigError(f"data.splits has no {name!r} entry for this experiment")

    def _eval_loader(self, name: str) -> DataLoader:
        """Sequential fixed set; under DDP each rank gets whole batches, none padded or repeated
        (:class:`EvalShardSampler`; ``trainer=ddp`` sets ``use_distributed_sampler: false``)."""
        self._require(name)
        sampler = EvalShardSampler(len(self.datasets[name]), self.eval_batch_size)
        return DataLoader(self.datasets[name], batch_size=self.eval_batch_size, sampler=sampler,
                          **self._loader_options())

    def val_dataloader(self) -> DataLoader:
        return self._eval_loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._eval_loader("test")
