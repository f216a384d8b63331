"""The repository's text files as git sees them (tracked, or new and not ignored), for checks over every file."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator

from tests.helpers.paths import ROOT


def tracked_texts() -> Iterator[tuple[str, str]]:
    """(path relative to the root, text) of every text file git tracks or would track (binary files left out)."""
    listed = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"], cwd=ROOT,
                            capture_output=True, check=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        path = ROOT / name
        if not path.is_file():  # deleted in the working tree
            continue
        data = path.read_bytes()
        if b"\0" not in data[:8192]:
            yield name, data.decode(errors="replace")
