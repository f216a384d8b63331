"""The machine's matrix-product rate, the yardstick of every speed and budget figure on a shared machine:
GFLOP/s of one ``torch.mm`` of :data:`MM_REFERENCE` (absolute times drift with the load; ratios to this do not)."""

from __future__ import annotations

import math
import time
from typing import Any

MM_REFERENCE = (4096, 1024, 1024)  # the reference product: (M, K) by (K, N)
CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


class MatmulReference:
    """GFLOP/s of ``torch.mm`` of MM_REFERENCE on ``device`` (several per timing on a GPU), timed by ``clock``."""

    def __init__(self, device: str, dtype: Any = None, clock: str = "wall") -> None:
        import torch  # (here: importing the module stays light)

        m, k, n = MM_REFERENCE
        generator = torch.Generator().manual_seed(0)
        self.a = torch.randn(m, k, generator=generator).to(device, dtype or torch.float32)
        self.b = torch.randn(k, n, generator=generator).to(device, dtype or torch.float32)
        self.repeats = 1 if device == "cpu" else 20
        self.sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
        self.clock = CLOCKS[clock]
        self.rate()  # warm-up

    def rate(self) -> float:
        import torch

        self.sync()
        start = self.clock()
        for _ in range(self.repeats):
            torch.mm(self.a, self.b)
        self.sync()
        return 2.0 * math.prod(MM_REFERENCE) * self.repeats / (self.clock() - start) / 1e9
