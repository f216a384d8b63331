"""Shared test settings: single-threaded torch (tiny tensors run faster, and tests stay stable on 2 cores)."""

import torch

torch.set_num_threads(1)


# --- tiny ModelNet40 archives in the three layouts (folder; ``make_zip`` zips one) ----------

import json  # noqa: E402
import shutil  # noqa: E402
from pathlib import Path  # noqa: E402

import h5py  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from src.data.categories import MODELNET40_CATEGORIES  # noqa: E402

TETRA_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float)
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
CUBE_V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
CUBE_QUADS = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
CUBE_TRIANGLES = np.concatenate([CUBE_QUADS[:, [0, 1, 2]], CUBE_QUADS[:, [0, 2, 3]]])


@pytest.fixture
def meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{"tetra", "cube" (triangles), "cube_quads"}: (vertices, faces)``; the cube spans [-1, 1]^3."""
    return {"tetra": (TETRA_V, TETRA_F), "cube": (CUBE_V, CUBE_TRIANGLES), "cube_quads": (CUBE_V, CUBE_QUADS)}


def off_text(vertices: np.ndarray, faces: np.ndarray, glued: bool = False, comment: bool = False) -> str:
    """An OFF file; ``glued`` writes ``OFF4 4 0``, ``comment`` adds comment and blank lines."""
    counts = f"{len(vertices)} {len(faces)} 0"
    lines = [f"OFF{counts}"] if glued else ["OFF", *(["# a comment", ""] if comment else []), counts]
    lines += [" ".join(map(str, v)) for v in vertices]
    lines += [" ".join(map(str, [len(f), *f])) for f in faces]
    return "\n".join(lines) + "\n"


@pytest.fixture
def make_zip(tmp_path: Path):
    """``make_zip(folder) -> <folder>_zip.zip`` holding the folder itself (as the official archives do)."""

    def make(folder: Path) -> Path:
        return Path(shutil.make_archive(str(tmp_path / f"{folder.name}_zip"), "zip", folder.parent, folder.name))

    return make


@pytest.fixture
def princeton_dir(tmp_path: Path) -> Path:
    """``ModelNet40/``: airplane (2 train: glued-header tetra, quad cube with comments; 1 test), chair (1 + 1)."""
    root = tmp_path / "ModelNet40"
    files = {
        "airplane/train/airplane_0001.off": off_text(TETRA_V, TETRA_F, glued=True),
        "airplane/train/airplane_0002.off": off_text(CUBE_V, CUBE_QUADS, comment=True),
        "airplane/test/airplane_0003.off": off_text(TETRA_V * 3 + 5, TETRA_F),
        "chair/train/chair_0001.off": off_text(CUBE_V * 2, CUBE_QUADS),
        "chair/test/chair_0002.off": off_text(TETRA_V, TETRA_F),
    }
    for name, text in files.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


@pytest.fixture
def h5_dir(tmp_path: Path) -> Path:
    """``modelnet40_ply_hdf5_2048/``: 3 train (with id2file json) + 2 test shapes of 32 points."""
    root = tmp_path / "modelnet40_ply_hdf5_2048"
    root.mkdir()
    (root / "shape_names.txt").write_text("\n".join(MODELNET40_CATEGORIES) + "\n")
    rng = np.random.default_rng(0)
    for split, labels in (("train", [0, 8, 0]), ("test", [8, 0])):
        with h5py.File(root / f"ply_data_{split}0.h5", "w") as f:
            f["data"] = rng.normal(size=(len(labels), 32, 3)).astype(np.float32)
            f["normal"] = rng.normal(size=(len(labels), 32, 3)).astype(np.float32)
            f["label"] = np.array(labels, dtype=np.uint8)[:, None]
    ids = ["airplane/airplane_0001.ply", "chair/chair_0001.ply", "airplane/airplane_0002.ply"]
    (root / "ply_data_train_0_id2file.json").write_text(json.dumps(ids))
    return root


@pytest.fixture
def resampled_dir(tmp_path: Path) -> Path:
    """``modelnet40_normal_resampled/`` with folders for airplane and chair only (all 40 names
    listed); the split lists also name bathtub shapes, whose folder is absent. 20 points per file."""
    root = tmp_path / "modelnet40_normal_resampled"
    for i, shape_id in enumerate(["airplane_0001", "airplane_0002", "chair_0001", "airplane_0003", "chair_0002"]):
        path = root / shape_id.rsplit("_", 1)[0] / f"{shape_id}.txt"
        path.parent.mkdir(parents=True, exist_ok=True)
        values = np.random.default_rng(i).uniform(-1, 1, size=(20, 6))
        path.write_text("".join(",".join(f"{v:.6f}" for v in row) + "\n" for row in values))
    (root / "modelnet40_shape_names.txt").write_text("\n".join(MODELNET40_CATEGORIES) + "\n")
    (root / "modelnet40_train.txt").write_text("airplane_0001\nairplane_0002\nbathtub_0001\nchair_0001\n")
    (root / "modelnet40_test.txt").write_text("airplane_0003\nbathtub_0002\nchair_0002\n")
    return root
