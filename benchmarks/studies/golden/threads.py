"""Whether RANSAC's library call depends on Open3D's threads: its seeded calls on the golden pairs with 1 thread,
with 2, and with 2 again, compared pair by pair.

    python -m benchmarks.studies.golden.threads
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from benchmarks.studies.golden import library
from benchmarks.studies.golden.golden_file import rotation_difference_deg
from benchmarks.studies.golden.pairs import golden_pairs, prepare_cache


def main() -> None:
    utility = library._o3d().utility
    with tempfile.TemporaryDirectory() as cache:
        pairs = golden_pairs(prepare_cache(Path(cache)))
    for call in (library.ransac, library.ransac_icp):
        runs = []
        for threads in (1, 2, 2):
            utility.set_max_threads(threads)
            runs.append(np.stack([call(src, ref) for src, ref in zip(pairs["src"], pairs["ref"])]))
        for label, (a, b) in (("1 and 2 threads", (0, 1)), ("two runs on 2 threads", (1, 2))):
            moved = rotation_difference_deg(runs[a], runs[b])
            print(f"{call.__name__}, {label}: {int((moved > 1e-6).sum())} of {len(moved)} pairs moved, "
                  f"up to {moved.max():.3g} deg")


if __name__ == "__main__":
    main()
