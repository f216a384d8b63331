"""Atomic file writes: a temporary beside the target, then a rename; and disk faults as one line.

Readers (and other ranks) never see half a file, and a process killed mid-write (``kill -9``,
out of memory, a time limit) leaves only a temporary ``.<name>.<pid>.tmp`` in the target's own
folder, never a partial target; :func:`remove_stale_temporaries` deletes those of dead processes.
A full disk, a folder without write permission, a file where a folder goes or a folder where a file goes
(:func:`disk_errors`; before anything is written: :func:`refuse_unwritable_outputs`) is one
:class:`~src.utils.errors.DiskError` line naming what was written and where; the temporary is removed.
Tables are written as parquet with a CRC checksum in every page and read back verified against them
(:func:`write_parquet`, :func:`read_parquet`): a damaged file is one line, never numbers read wrong.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from src.utils.errors import DiskError, UserError

_TEMPORARY = re.compile(r"^\..+\.(\d+)\.tmp$")


def temporary_path(path: Path) -> Path:
    """Where :func:`write_atomic` stages ``path``: ``.<name>.<pid>.tmp`` in the same folder
    (so the final rename never crosses file systems)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


FULL = (errno.ENOSPC, errno.EDQUOT)
DENIED = (errno.EACCES, errno.EPERM, errno.EROFS)
NOT_A_FOLDER = (errno.EEXIST, errno.ENOTDIR)  # (creating a folder where a file is)
A_FOLDER = (errno.EISDIR,)  # (writing a file where a folder is)
NEARLY_FULL = 1 << 20
"""Free bytes under which a writer's failure without an errno (torch's ``torch.save``: a RuntimeError) is
taken for a full disk."""


def _free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def disk_error(err: BaseException, what: str, folder: Path) -> DiskError | None:
    """The one line for ``err`` when a full disk, a folder without write permission, a file where a folder goes or a
    folder where a file goes caused it, else None."""
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
    if code in A_FOLDER:  # (os.replace names the target second)
        return DiskError(f"{what}: {getattr(err, 'filename2', None) or getattr(err, 'filename', folder)} is a folder, "
                         "where a file goes: move the folder, or write elsewhere (hydra.run.dir or output_dir for runs)")
    return None


def refuse_unwritable_outputs(folder: Path, names: Sequence[str], option: str) -> None:
    """DiskError, before anything is written, when ``folder`` or a folder above it is a file, or when one of the files
    ``names`` to be written in it is a folder; ``option`` names the folder on the command line (``--out``)."""
    above = next((path for path in (folder, *folder.parents) if path.exists()), None)
    if above is not None and not above.is_dir():
        raise DiskError(f"{option} {folder}: {above} is a file, not a folder: move the file, or give another {option}")
    taken = next((folder / name for name in names if (folder / name).is_dir()), None)
    if taken is not None:
        raise DiskError(f"{option} {folder}: {taken} is a folder, where a file goes: move the folder, or give another "
                        f"{option}")


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


def write_parquet(frame: Any, path: Path) -> None:
    """``frame`` (a pandas DataFrame, its index left out) at ``path`` atomically, with a CRC checksum in every page."""
    write_atomic(path, lambda tmp: frame.to_parquet(tmp, index=False, write_page_checksum=True))


def read_parquet(path: Path) -> Any:
    """The pandas DataFrame at ``path``, every page verified against its checksum (pages written without one are
    read as they are); a damaged file is one :class:`~src.utils.errors.UserError` line naming it. A missing file
    raises ``FileNotFoundError``."""
    import pandas as pd
    import pyarrow as pa

    try:
        return pd.read_parquet(path, page_checksum_verification=True)
    except FileNotFoundError:
        raise
    except (OSError, ValueError, pa.ArrowException) as err:
        detail = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise UserError(f"{path} is damaged ({detail}): write it again with the command that made it") from err


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


def owned_prefix(prefix: str) -> str:
    """``<prefix><pid>-``: the start of a working folder's name (``tempfile.mkdtemp(prefix=...)``) that names this
    process as its owner, for :func:`remove_stale_folders`."""
    return f"{prefix}{os.getpid()}-"


def remove_stale_folders(folder: Path, prefix: str) -> list[Path]:
    """Delete the folders in ``folder`` whose names start with :func:`owned_prefix` of ``prefix`` and whose owner no
    longer runs here (killed before it could clean up); return them."""
    if not folder.is_dir():
        return []
    owned = re.compile(rf"^{re.escape(prefix)}(\d+)-")
    removed = []
    for path in folder.iterdir():
        match = owned.match(path.name)
        if match and path.is_dir() and not path.is_symlink() and not _process_alive(int(match.group(1))):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed
