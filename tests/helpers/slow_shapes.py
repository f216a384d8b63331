"""A reader whose shapes take as many seconds to load as their entries say, for the tests that stop a pool of
``prepare``'s workers while they work; each worker leaves a file named by its pid in ``folder`` when it starts one."""

from __future__ import annotations

import os
import time
from pathlib import Path


class SlowReader:
    def __init__(self, folder: Path):
        self.folder = Path(folder)

    def load(self, seconds: float) -> float:
        (self.folder / str(os.getpid())).touch()
        time.sleep(seconds)
        return seconds


def as_loaded(shape: float, index: int, params: dict) -> float:
    """The compute step of :func:`src.data.prepare._shape_mapper`: the shape as the reader loaded it."""
    return shape
