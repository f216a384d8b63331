"""Tiny archives shaped like the shared per-category ModelNet40 zips (``modelnet40_normal_resampled``)."""

from pathlib import Path

import numpy as np

from src.data.categories import MODELNET40_CATEGORIES

TRAIN = {"airplane": 6, "bathtub": 4}
"""Train shapes per category; each also lists 2 test ids whose files are withheld."""


def write_category(root: Path, category: str, num_train: int, num_test: int = 2, num_points: int = 16) -> Path:
    """``<root>/<category>/modelnet40_normal_resampled/`` holding one category: its train files, split
    lists restricted to it whose test ids have no file, and all 40 shape names (as the shared zips)."""
    folder = root / category / "modelnet40_normal_resampled"
    ids = [f"{category}_{i:04d}" for i in range(1, num_train + num_test + 1)]
    (folder / category).mkdir(parents=True)
    for i, shape_id in enumerate(ids[:num_train]):
        values = np.random.default_rng([MODELNET40_CATEGORIES.index(category), i]).uniform(-0.5, 0.5, (num_points, 6))
        lines = "".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in values)
        (folder / category / f"{shape_id}.txt").write_text(lines)
    (folder / "modelnet40_shape_names.txt").write_text("\n".join(MODELNET40_CATEGORIES) + "\n")
    (folder / "modelnet40_train.txt").write_text("\n".join(ids[:num_train]) + "\n")
    (folder / "modelnet40_test.txt").write_text("\n".join(ids[num_train:]) + "\n")
    return folder
