"""Real scan-to-scan registration pairs (``data=scan_pairs``, ``+exp=scan_pairs``): a fixed test set.

Each pair (:func:`src.data.scans.scan_pairs`: two scans of one set that overlap under the ground-truth
poses) becomes a sample as the paper's protocols make theirs, with its randomness from
``default_rng([seed, EVAL_STREAM, index])``:

1. both scans, each in its own frame, normalised by one shared similarity (same centre and scale, so
   the ground truth, the relative pose of the two scans, stays rigid; the union fits the unit sphere);
2. a random subset of ``num_points`` points of each (the paper's partial clouds have 768);
3. a random rigid perturbation (Euler angles U[0°, rot_mag] per axis, translation U[±trans_mag]) moves
   the reference, as in the PRNet manner (:class:`~src.data.transforms.RandomRigidTransform`), so that
   ``transform_gt`` = perturbation · relative pose maps source to reference and the identity never wins.

Each sample also carries its pair's ``overlap`` (for results binned by overlap).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset

from src.data.dataset import EVAL_STREAM, float_tensor
from src.data.scans import ScanPair, ScanSet, ScanSource, normalise_pair, read_scans, scan_pairs
from src.data.transforms import Compose, RandomRigidTransform, Resample
from src.utils.errors import ConfigError, DatasetError
from src.geometry.clouds import check_cloud
from src.utils.paths import shared_path

log = logging.getLogger(__name__)

DEFAULT_SOURCE = ("data", "stanford", "stanford_bunny_scans.zip")
"""The Stanford Bunny's 10 range scans and bun.conf, inside the shared folder."""


@dataclass(frozen=True)
class ScanPairSettings:
    """``data.pair`` of ``conf/data/scan_pairs.yaml``."""

    num_points: int = 768
    min_overlap: float = 0.3
    overlap_spacing: float = 2.0
    rot_mag: float = 45.0
    trans_mag: float = 0.5

    def __post_init__(self) -> None:
        if self.num_points < 3:
            raise ConfigError(f"data.pair.num_points must be >= 3, got {self.num_points}")
        if not 0.0 <= self.min_overlap < 1.0:
            raise ConfigError(f"data.pair.min_overlap must be in [0, 1), got {self.min_overlap}")
        if self.overlap_spacing <= 0:
            raise ConfigError(f"data.pair.overlap_spacing must be > 0, got {self.overlap_spacing}")

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> ScanPairSettings:
        unknown = set(values) - {f.name for f in fields(cls)}
        if unknown:
            raise ConfigError(f"data.pair has unknown keys {sorted(unknown)}; scan pairs take {[f.name for f in fields(cls)]}")
        return cls(**values)


def dropped_pairs(scan_sets: list[ScanSet], pairs: list[ScanPair], min_overlap: float) -> dict[str, Any]:
    """What :func:`~src.data.scans.scan_pairs` left out: how many ordered pairs of scans of one set, why, and
    the scans that are in no pair (``<set>:<scan>``)."""
    candidates = sum(len(s.scans) * (len(s.scans) - 1) for s in scan_sets)
    paired = {(p.scan_set, i) for p in pairs for i in (p.source, p.reference)}
    unpaired = [f"{s.name}:{scan.name}" for k, s in enumerate(scan_sets) for i, scan in enumerate(s.scans)
                if (k, i) not in paired]
    return {"pairs": candidates - len(pairs), "reason": f"overlap <= data.pair.min_overlap={min_overlap}",
            "scans_in_no_pair": unpaired}


class ScanPairDataset(Dataset):
    """One sample per :class:`~src.data.scans.ScanPair` (see the module docstring)."""

    def __init__(self, source: ScanSource, pairs: list[ScanPair], settings: ScanPairSettings, seed: int) -> None:
        if not pairs:
            raise DatasetError(f"no two scans of {source.path} overlap by more than "
                               f"data.pair.min_overlap={settings.min_overlap}")
        self.source, self.pairs, self.seed = source, pairs, seed
        self.transforms = Compose([Resample(settings.num_points),
                                   RandomRigidTransform(settings.rot_mag, settings.trans_mag, apply_to="ref")])

    def __len__(self) -> int:
        return len(self.pairs)

    def names(self, index: int) -> tuple[str, str]:
        """The source and reference scans of pair ``index``."""
        pair = self.pairs[index]
        scans = self.source.scan_sets[pair.scan_set].scans
        return scans[pair.source].name, scans[pair.reference].name

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        pair = self.pairs[index]
        scans = self.source.scan_sets[pair.scan_set].scans
        src, ref, transform = normalise_pair(scans[pair.source].points, scans[pair.reference].points, pair.transform)
        rng = np.random.default_rng([self.seed, EVAL_STREAM, int(index)])
        sample = self.transforms({"points_src": src, "points_ref": ref, "transform_gt": transform}, rng)
        for key in ("points_src", "points_ref"):
            check_cloud(sample[key], key, allow_degenerate=True)
        return {
            **{key: float_tensor(sample[key]) for key in ("points_src", "points_ref", "transform_gt")},
            "overlap": torch.tensor(pair.overlap),
            "idx": torch.tensor(int(index)),
        }


class ScanPairsDataModule(L.LightningDataModule):
    """The scan pairs of a folder or .zip of range scans (default: the shared Stanford Bunny scans) as a
    test set. ``cache`` is the :class:`~src.data.scans.ScanSource` once set up: like a dataset cache it has
    a ``manifest`` with the ``content_hash`` of the files read, which the grid records. ``batch_size`` (for
    training) is unused: it is accepted because model recipes (``conf/recipe/``) set ``data.batch_size``."""

    def __init__(
        self,
        dataset: str = "scan_pairs",
        source: str | None = None,
        pair: Mapping[str, Any] | None = None,
        eval_batch_size: int = 16,
        batch_size: int | None = None,
        num_workers: int = 0,
        seed: int = 1234,
    ) -> None:
        super().__init__()
        self.dataset = dataset
        self.source = source
        self.settings = ScanPairSettings.from_mapping(dict(pair or {}))
        self.eval_batch_size, self.num_workers, self.seed = eval_batch_size, num_workers, seed
        self.cache: ScanSource | None = None
        self.datasets: dict[str, ScanPairDataset] = {}
        self.dropped: dict[str, Any] = {}

    def setup(self, stage: str | None = None) -> None:
        if stage not in ("test", None):
            raise ConfigError(f"scan pairs are a test set only (evaluate with src.eval), not for stage {stage!r}")
        if "test" in self.datasets:
            return
        self.cache = read_scans(self.source or shared_path(*DEFAULT_SOURCE))
        pairs = scan_pairs(self.cache.scan_sets, self.settings.min_overlap, self.settings.overlap_spacing)
        self.dropped = dropped_pairs(self.cache.scan_sets, pairs, self.settings.min_overlap)
        if self.dropped["scans_in_no_pair"]:
            log.warning("%d scans form no pair (%s) and are left out of the test set: %s",
                        len(self.dropped["scans_in_no_pair"]), self.dropped["reason"],
                        ", ".join(self.dropped["scans_in_no_pair"]))
        self.datasets["test"] = ScanPairDataset(self.cache, pairs, self.settings, self.seed)

    def test_dataloader(self) -> DataLoader:
        return DataLoader(self.datasets["test"], batch_size=self.eval_batch_size, num_workers=self.num_workers)
