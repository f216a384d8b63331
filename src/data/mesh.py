"""Triangle meshes as plain arrays, shared by the readers, the synthetic generator and the cache."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshShape:
    """One CAD model: a triangle mesh with its category, split and shape id.

    ``vertices`` is ``(V, 3)`` float64, ``faces`` is ``(F, 3)`` int64 indexing ``vertices``.
    """

    name: str
    category: str
    split: str
    vertices: np.ndarray
    faces: np.ndarray
