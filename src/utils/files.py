"""Atomic file writes: a temporary beside the target, then a rename; and disk faults as one line.

Readers (and other ranks) never see half a file, and a process killed mid-write (``kill -9``,
out of memory, a time limit) leaves only a temporary ``.<name>.<pid>.tmp`` in the target's own
folder, never a partial target; :func:`remove_stale_temporaries` deletes those of dead processes.
A full disk or a folder without write permission (:func:`disk_errors`) is one
:class:`~src.utils.errors.DiskError` line naming what was written and where; the temporary is removed.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from src.utils.errors import DiskError

_TEMPORARY = re.compile(r"^\..+\.(\d+)\.tmp$")


def temporary_path(path: Path) -> Path:
    """Where :func:`write_atomic` stages ``path``: ``.<name>.<pid>.tmp`` in the same folder
    (so the final rename never crosses file systems)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


FULL = (errno.ENOSPC, errno.EDQUOT)
DENIED = (errno.EACCES, errno.EPERM, errno.EROFS)
NOT_A_FOLDER = (errno.EEXIST, errno.ENOTDIR)  # (creating a folder where a file is)
NEARLY_FULL = 1 << 20
"""Free bytes under which a writer's failure without an errno (torch's ``torch.save``: a RuntimeError) is
taken for a full disk."""


def _free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def disk_error(err: BaseException, what: str, folder: Path) -> DiskError | None:
    """The one line for ``err`` when a full disk or a folder without write permission caused it, else None."""
    code = getattr(err, "errno", None)
    free = _free_bytes(folder)
    if code in FULL or (isinstance(err, RuntimeError) and free is not None and free < NEARLY_FULL):
        shown = "" if free is None else f", {free / 2**20:.1f} MB free"
        return DiskError(f"{what}: the disk of {folder} is full{shown}: free space there, or write elsewhere "
                         "(OMNET_CACHE_DIR / --cache-root for caches, hydra.run.dir or output_dir for runs)")
    if code in DENIED:
        return DiskError(f"{what}: cannot write in {folder} ({os.strerror(code)}): make it writable, or write "
                         "elsewhere (OMNET_CACHE_DIR / --cache-root for caches, hydra.run.dir or output_dir for runs)")
    if code in NOT_A_FOLDER:
        return DiskError(f"{what}: {folder} or a folder above it is a file, not a folder: move the file, or write "
                         "elsewhere (OMNET_CACHE_DIR / --cache-root for caches, hydra.run.dir or output_dir for runs)")
    return None


@contextmanager
def disk_errors(what: str, folder: Path) -> Iterator[None]:
    """Within the block, an error of a full disk or a denied write becomes one :class:`DiskError` line."""
    try:
        yield
    except Exception as err:
        problem = disk_error(err, what, folder)
        if problem is None:
            raise
        raise problem from err


def preallocate(path: Path) -> None:
    """Reserve the blocks of ``path`` (a memory-mapped file about to be filled): a full disk is then an
    ``OSError`` here, not a ``SIGBUS`` at the first page written beyond the free space."""
    size = path.stat().st_size
    with open(path, "rb+") as handle:
        try:
            os.posix_fallocate(handle.fileno(), 0, size)
        except OSError as err:
            if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                raise
            free = _free_bytes(path.parent)
            if free is not None and free < size:  # a file system without fallocate: compare free space
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path)) from err


def write_atomic(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(temporary)``, flush it to disk and rename it to ``path``; the temporary is
    removed if ``write`` raises (a full disk or a denied write: :class:`DiskError`)."""
    tmp = temporary_path(path)
    try:
        with disk_errors(f"writing {path.name}", path.parent):
            write(tmp)
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
            os.replace(tmp, path)
    finally:
        if tmp.exists():  # (unlink raises on a read-only file system even when the file is not there)
            tmp.unlink()


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
