"""The identity: no registration. The reference row of every table (what a method must beat)."""

from __future__ import annotations

import numpy as np

from baselines.base import Registrator


class Identity(Registrator):
    """Returns the identity transform for every pair."""

    name = "identity"
    needs_training = False
    needs_normals = False
    point_budget = None  # reads no point

    def frame(self, src: np.ndarray, ref: np.ndarray) -> None:
        """None: the identity in any frame is the identity."""
        return None

    def _register(self, src: np.ndarray, ref: np.ndarray) -> np.ndarray:
        return np.eye(4)
