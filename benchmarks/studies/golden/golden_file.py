"""Golden files (``tests/fixtures/golden/<method>.npz``): the authors' estimates on the golden pairs and
where they came from; and the rotation difference the tests and the spread study measure."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from src.utils.paths import REPO_ROOT

GOLDEN_DIR = REPO_ROOT / "tests" / "fixtures" / "golden"
#: The text fields of a golden file, besides its (P, 4, 4) float64 ``transforms``.
FIELDS = ("method", "dtype", "authors", "weights", "weights_sha256", "pairs_sha256", "command")


def weights_file(weights: str) -> Path:
    """The file of published weights (``official:<name>``, in the shared folder) or of a shipped checkpoint (its name)."""
    from baselines.learned.published import PUBLISHED
    from src.utils.paths import SHIPPED_DIR, shared_path

    if weights.startswith("official:"):
        return shared_path("weights", PUBLISHED[weights.removeprefix("official:")].file)
    return SHIPPED_DIR / f"{weights}.ckpt"


def state_sha256(checkpoint: Path) -> str:
    """sha256 of a checkpoint's network weights (each tensor's name, dtype, shape and bytes, in name order): what
    the estimates depend on, unchanged by the metadata stored beside them."""
    import hashlib

    import torch

    digest = hashlib.sha256()
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["state_dict"]
    for name in sorted(state):
        tensor = state[name].contiguous()
        digest.update(f"{name}|{tensor.dtype}|{tuple(tensor.shape)}|".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def weights_sha256(weights: str) -> str:
    """sha256 of the published weights' file, or of a shipped checkpoint's network weights (:func:`state_sha256`)."""
    from src.data.cache import file_sha256

    path = weights_file(weights)
    return file_sha256(path) if weights.startswith("official:") else state_sha256(path)


def golden_path(method: str) -> Path:
    return GOLDEN_DIR / f"{method}.npz"


def write_golden(method: str, transforms: np.ndarray, **fields: str) -> Path:
    """``transforms`` and the :data:`FIELDS` into :func:`golden_path` (compressed)."""
    missing = set(FIELDS) - {"method", *fields}
    if missing:
        raise ValueError(f"golden file fields missing: {sorted(missing)}")
    path = golden_path(method)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, transforms=transforms.astype(np.float64),
                        **{k: np.array(v) for k, v in {"method": method, **fields}.items()})
    return path


def read_golden(method: str) -> dict:
    """``transforms`` (P, 4, 4) and the text :data:`FIELDS` of a golden file."""
    with np.load(golden_path(method), allow_pickle=False) as data:
        return {"transforms": data["transforms"], **{k: str(data[k]) for k in FIELDS}}


def rotation_difference_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (degrees) of ``a_R^T b_R`` per pair of (P, 4, 4) transforms, exact down to ~1e-14 degree
    (``2 asin(‖R − I‖_F / 2√2)``, not the arccos of the trace, which loses small angles)."""
    relative = np.einsum("pji,pjk->pik", a[:, :3, :3], b[:, :3, :3])
    norm = np.linalg.norm(relative - np.eye(3), axis=(1, 2))
    return np.degrees(2 * np.arcsin(np.clip(norm / (2 * np.sqrt(2)), 0.0, 1.0)))


def translation_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """‖t_a − t_b‖ per pair."""
    return np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
