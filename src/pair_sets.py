"""An experiment's fixed pairs: its test set as ``src.eval +exp=<experiment>`` evaluates it
(:func:`build_test_set`, with the definition that names it in the grid), or any stage's pairs (:class:`TestSet`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from src.compose import compose_experiment
from src.utils.errors import ConfigError, PointCloudError
from src.geometry.clouds import check_cloud

#: Data-loader settings: they change how the pairs are loaded, not which pairs (not part of a test set's definition).
LOADER_KEYS = ("batch_size", "eval_batch_size", "num_workers", "pin_memory", "persistent_workers", "cache_root", "_target_")


@dataclass
class TestSet:
    """One (experiment, sampling, partial): its composed config, datamodule and definition."""

    __test__ = False  # a product class whose name starts with "Test": not for pytest to collect
    experiment: str
    sampling: str
    partial: str
    cfg: DictConfig
    dataset: Any  # src.data.dataset.PairDataset
    definition: dict[str, Any]
    categories: tuple[str, ...] = ()
    """The cache's category names (a pair's shape label indexes them)."""
    _pairs: list | None = None
    _raw: list | None = None

    @property
    def key(self) -> str:
        return f"{self.experiment}/{self.sampling}/{self.partial}"

    @property
    def dataset_name(self) -> str:
        return str(self.definition["dataset"])

    @property
    def noise_sigma(self) -> float:
        return float(self.definition["pair"].get("noise_sigma") or 0.0)

    def pairs(self, n: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The first ``n`` pairs ``(src, ref, transform_gt)``; each cloud is checked (≥ 3 points, finite)."""
        if self._pairs is None:
            self._pairs, self._raw = [], []
        for index in range(len(self._pairs), n):
            sample = self.dataset[index]
            self._raw.append(sample["points_raw"].numpy() if "points_raw" in sample else None)
            src, ref = sample["points_src"].numpy(), sample["points_ref"].numpy()
            try:
                check_cloud(src, "points_src")
                check_cloud(ref, "points_ref")
            except PointCloudError as err:
                raise PointCloudError(f"test set {self.key}, pair {index}: {err}") from None
            self._pairs.append((src, ref, sample["transform_gt"].numpy().astype(np.float64)))
        return self._pairs[:n]

    def raw(self, n: int) -> list[np.ndarray] | None:
        """The reference's clean full cloud of each of the first ``n`` pairs (RPM-Net's modified Chamfer
        distance reads it), or None where the pairs do not carry it (real scan pairs)."""
        self.pairs(n)
        raw = self._raw[:n]
        return None if any(cloud is None for cloud in raw) else raw


def build_test_set(experiment: str, sampling: str, partial: str, data: str | None, extra: Sequence[str]) -> TestSet:
    overrides = [f"+exp={experiment}", f"sampling={sampling}", f"partial={partial}"]
    if data:
        overrides.append(f"data={data}")
    overrides += list(extra)
    cfg = compose_experiment(overrides)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.setup("test")  # DatasetError if the test set was never prepared
    if "test" not in datamodule.datasets:
        raise ConfigError(f"experiment {experiment} has no test split (data.splits.test)")
    data_cfg = OmegaConf.to_container(cfg.data, resolve=True)
    definition = {k: v for k, v in data_cfg.items() if k not in LOADER_KEYS}
    if "splits" in data_cfg:  # a cache datamodule: of its splits only the test split defines the test set
        definition["splits"] = {"test": data_cfg["splits"]["test"]}
    definition["content_hash"] = datamodule.cache.manifest.get("content_hash")
    definition["num_test_pairs"] = len(datamodule.datasets["test"])
    return TestSet(experiment, sampling, partial, cfg, datamodule.datasets["test"], definition,
                   tuple(getattr(datamodule.cache, "categories", ())))  # scan pairs: no categories
