"""The golden pairs: real airplanes of the shared ModelNet40 zip, PRNet manner, OS and TS, from the framework's
seeded data pipeline.

A cache of the zip's first :data:`SHAPES` train airplanes is prepared (``src.data.prepare``, ``limit``), and
``+exp=real_airplane`` carves its test set out of them (the last :data:`PAIRS_PER_SAMPLING`); each sampling
gives that many fixed pairs (768 of 1,024 points per cloud, clean). :func:`pairs_digest` fingerprints the
arrays, so a golden file records which pairs it was computed on and a change of the pipeline is told apart
from a change of a method.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from src.utils.paths import shared_path

ZIP = ("data", "modelnet40_normal_resampled_airplane.zip")
#: The first train airplanes prepared; the test carve-out is the last PAIRS_PER_SAMPLING of them.
SHAPES = 14
PAIRS_PER_SAMPLING = 12
SAMPLINGS = ("os", "ts")


def overrides(sampling: str, cache_root: Path) -> list[str]:
    """The experiment of the golden pairs for one sampling (``os`` / ``ts``)."""
    return ["+exp=real_airplane", f"sampling={sampling}", "partial=prnet", "data.pair.noise_sigma=0.0",
            f"test_size={PAIRS_PER_SAMPLING}", f"val_size={SHAPES - PAIRS_PER_SAMPLING}",
            f"data.cache_root={cache_root}", "data.num_workers=0"]


def prepare_cache(cache_root: Path) -> Path:
    """The zip's first :data:`SHAPES` train airplanes prepared into ``cache_root`` (about a second)."""
    from src.data.prepare import prepare

    prepare("modelnet40_resampled", source=[shared_path(*ZIP)], cache_root=cache_root, limit=SHAPES, workers=1)
    return cache_root


def golden_pairs(cache_root: Path) -> dict[str, np.ndarray]:
    """``src``, ``ref`` (P, 768, 3) float32, ``transform_gt`` (P, 4, 4), ``sampling`` (P,) of the golden pairs
    from a cache made by :func:`prepare_cache`: the OS pairs, then the TS pairs."""
    import hydra

    from src.compose import compose_conf

    parts: dict[str, list[np.ndarray]] = {"src": [], "ref": [], "transform_gt": [], "sampling": []}
    for sampling in SAMPLINGS:
        datamodule = hydra.utils.instantiate(compose_conf(overrides(sampling, cache_root)).data)
        datamodule.setup("test")
        dataset = datamodule.datasets["test"]
        for index in range(len(dataset)):
            item = dataset[index]
            parts["src"].append(item["points_src"].numpy())
            parts["ref"].append(item["points_ref"].numpy())
            parts["transform_gt"].append(item["transform_gt"].numpy())
            parts["sampling"].append(np.array(sampling))
    return {key: np.stack(values) for key, values in parts.items()}


def pairs_digest(pairs: dict[str, np.ndarray]) -> str:
    """sha256 of the pairs' points and ground truth (float32 bytes, in order)."""
    digest = hashlib.sha256()
    for key in ("src", "ref", "transform_gt"):
        digest.update(np.ascontiguousarray(pairs[key], dtype=np.float32).tobytes())
    return digest.hexdigest()
