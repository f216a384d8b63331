"""Atomic file writes: a temporary beside the target, then a rename.

Readers (and other ranks) never see half a file, and a process killed mid-write (``kill -9``,
out of memory, a time limit) leaves only a temporary ``.<name>.<pid>.tmp`` in the target's own
folder, never a partial target; :func:`remove_stale_temporaries` deletes those of dead processes.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

_TEMPORARY = re.compile(r"^\..+\.(\d+)\.tmp$")


def temporary_path(path: Path) -> Path:
    """Where :func:`write_atomic` stages ``path``: ``.<name>.<pid>.tmp`` in the same folder
    (so the final rename never crosses file systems)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_atomic(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(temporary)``, flush it to disk and rename it to ``path``; the temporary is
    removed if ``write`` raises."""
    tmp = temporary_path(path)
    try:
        write(tmp)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: Path, text: str) -> None:
    write_atomic(path, lambda tmp: tmp.write_text(text))


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(folder: Path) -> list[Path]:
    """Delete the temporaries in ``folder`` left by processes that no longer run here; return them."""
    if not folder.is_dir():
        return []
    removed = []
    for path in folder.iterdir():
        match = _TEMPORARY.match(path.name)
        if match and path.is_file() and not _process_alive(int(match.group(1))):
            path.unlink(missing_ok=True)
            removed.append(path)
    return removed
