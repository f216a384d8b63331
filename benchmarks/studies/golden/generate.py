"""Write a golden file: the authors' code, once, in float64 on the golden pairs.

    python -m benchmarks.studies.golden.generate METHOD --authors CHECKOUT

``CHECKOUT`` is a clone of the method's authors' repository (:data:`benchmarks.studies.golden.authors.REFERENCES`),
outside this repository; a classical method's reference is its library call, with no checkout. The pairs come from ``../shared`` (:mod:`benchmarks.studies.golden.pairs`), prepared into
a temporary cache. The file records the command (the checkout as a placeholder), the authors' commit, the weights
and their sha256, and the pairs' sha256.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from benchmarks.studies.golden.authors import REFERENCES, Reference
from benchmarks.studies.golden.golden_file import weights_sha256, write_golden
from benchmarks.studies.golden.pairs import golden_pairs, pairs_digest, prepare_cache
from src.utils.errors import ConfigError, exit_code_of


def commit_of(checkout: Path) -> str:
    """The checkout's commit (``git rev-parse HEAD``), or ``unknown`` where it is not a git clone."""
    result = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True, check=False)
    return result.stdout.strip() if result.returncode == 0 else "unknown"


def generate(method: str, checkout: Path | None) -> Path:
    """The golden file of ``method`` from the authors' code in ``checkout``."""
    reference: Reference = REFERENCES[method]
    if checkout is None and not reference.library:
        raise ConfigError(f"{method}: --authors CHECKOUT (a clone of {reference.repo}) is needed")
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as cache:
        pairs = golden_pairs(prepare_cache(Path(cache)))
    transforms = reference.run(checkout, pairs, torch.float64)
    if reference.library:
        from benchmarks.studies.golden.library import library_version

        authors, command_tail = library_version(method), ""
    else:
        authors, command_tail = f"{reference.repo}@{commit_of(checkout)}", f" --authors <checkout of {reference.repo}>"
    return write_golden(
        method, transforms, dtype="float64", authors=authors, weights=reference.weights,
        weights_sha256=weights_sha256(reference.weights) if reference.weights else "", pairs_sha256=pairs_digest(pairs),
        command=f"python -m benchmarks.studies.golden.generate {method}{command_tail}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.studies.golden.generate", description=__doc__.split("\n\n")[0])
    parser.add_argument("method", choices=sorted(REFERENCES))
    parser.add_argument("--authors", type=Path, default=None,
                        help="a checkout of the method's authors' repository (not for a library call)")
    args = parser.parse_args(argv)
    return exit_code_of(lambda: print(f"wrote {generate(args.method, args.authors)}"))


if __name__ == "__main__":
    sys.exit(main())
