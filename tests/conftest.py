"""Shared test settings and fixtures, visible to every folder under tests/.

Single-threaded torch (tiny tensors run faster, and tests stay stable on 2 cores), and the markers of
pyproject.toml, skipped here in one place:

- ``slow``: runs only with ``--run-slow``;
- ``shared_data("data/<file>", ...)``: skipped when a named file of the shared folder
  (:func:`src.utils.paths.shared_path`: ``../shared`` or ``$OMNET_SHARED_DIR``) is absent;
- ``goicp``: skipped when the optional Go-ICP extension cannot be imported.

Property tests (hypothesis) run the ``suite`` profile: the same examples on every run and machine (a CI run is
reproducible), few of them, no shrinking. ``pytest --hypothesis-profile=explore`` draws new, more examples.

Plain helpers (archive writers, meshes, configs) are in :mod:`tests.helpers`.
"""

import json
import logging
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, Phase, settings

from src.data.categories import MODELNET40_CATEGORIES
from tests.helpers.markers import skip_reason
from tests.helpers.meshes import CUBE_QUADS, CUBE_TRIANGLES, CUBE_V, TETRA_F, TETRA_V, off_text
from tests.helpers.modelnet import TRAIN, write_category

torch.set_num_threads(1)

_PROPERTY_SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("suite", max_examples=30, derandomize=True, database=None,
                          phases=(Phase.explicit, Phase.generate), **_PROPERTY_SETTINGS)
settings.register_profile("explore", max_examples=300, **_PROPERTY_SETTINGS)
settings.load_profile("suite")


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--run-slow", action="store_true", default=False, help="also run the tests marked slow")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    from baselines.classical.goicp import goicp_available  # imported at collection, not when the conftest loads

    run_slow, has_goicp = config.getoption("--run-slow"), goicp_available()
    for item in items:
        reason = skip_reason(item, run_slow, has_goicp)
        if reason is not None:
            item.add_marker(pytest.mark.skip(reason=reason))


def _loggers() -> list[logging.Logger]:
    return [logging.root, *(x for x in logging.Logger.manager.loggerDict.values() if isinstance(x, logging.Logger))]


@pytest.fixture(autouse=True)
def _drop_logging_handlers_a_test_left():
    """A test that configures logging (a CLI's ``logging.basicConfig``, Hydra's job logging) leaves handlers
    on the streams pytest captured for it, closed once it ends: a later test's records then go there
    ("I/O operation on closed file", breaking e.g. test_disk's one-line error). Removed after each test
    (pytest's own capture handlers aside)."""
    before = {id(logger): list(logger.handlers) for logger in _loggers()}
    yield
    for logger in _loggers():
        kept = before.get(id(logger), [])
        for handler in [h for h in logger.handlers if h not in kept and not type(h).__module__.startswith("_pytest")]:
            logger.removeHandler(handler)
            handler.close()


# --- tiny ModelNet40 archives in the three layouts (folder; ``make_zip`` zips one) ----------


@pytest.fixture
def meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{"tetra", "cube" (triangles), "cube_quads"}: (vertices, faces)``; the cube spans [-1, 1]^3."""
    return {"tetra": (TETRA_V, TETRA_F), "cube": (CUBE_V, CUBE_TRIANGLES), "cube_quads": (CUBE_V, CUBE_QUADS)}


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


# --- one zip per category, as the shared ones (airplane + bathtub) -------------------------


@pytest.fixture
def zips(tmp_path) -> dict[str, Path]:
    """``{category: zip}`` for airplane (6 train) and bathtub (4 train)."""
    archives = {}
    for category, num_train in TRAIN.items():
        folder = write_category(tmp_path / "src", category, num_train)
        archives[category] = Path(shutil.make_archive(str(tmp_path / category), "zip", folder.parent, folder.name))
    return archives


@pytest.fixture
def merged_root(zips, tmp_path) -> Path:
    """A cache prepared from both ``zips`` (airplane + bathtub)."""
    from src.data.prepare import prepare

    prepare("modelnet40_resampled", source=list(zips.values()), cache_root=tmp_path / "cache")
    return tmp_path / "cache"
