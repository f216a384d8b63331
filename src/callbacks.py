"""Training callbacks beyond Lightning's own."""

from __future__ import annotations

import random
from typing import Any

import lightning as L
import numpy as np
import torch


class RngState(L.Callback):
    """Save the global RNG states (Python, NumPy, torch CPU and CUDA) in each checkpoint and restore
    them on resume, so stochastic training steps (e.g. PRNet's Gumbel noise) continue exactly as in
    the uninterrupted run. Pair generation does not need this: it is seeded per sample index.

    The states are applied at the first training batch after the restore, not when the checkpoint
    is read: Lightning may first finish a validation the checkpoint interrupted (PRNet's evaluation
    draws noise too), which the uninterrupted run had done before the states were saved.
    """

    def __init__(self) -> None:
        self._pending: dict[str, Any] | None = None

    def state_dict(self) -> dict[str, Any]:
        kind, keys, pos, has_gauss, gauss = np.random.get_state()
        # plain types and tensors only, so Lightning's weights-only checkpoint loading accepts them
        state = {"python": random.getstate(), "numpy": (kind, torch.from_numpy(keys.astype(np.int64)), pos,
                                                         has_gauss, gauss), "torch": torch.get_rng_state()}
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            state["cuda"] = torch.cuda.get_rng_state_all()
        return state

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._pending = state_dict

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int) -> None:
        if self._pending is not None:
            set_rng_states(self._pending)
            self._pending = None


def set_rng_states(state_dict: dict[str, Any]) -> None:
    """Apply states from :meth:`RngState.state_dict`."""
    random.setstate(state_dict["python"])
    kind, keys, pos, has_gauss, gauss = state_dict["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    torch.set_rng_state(state_dict["torch"])
    if "cuda" in state_dict and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state_dict["cuda"])
