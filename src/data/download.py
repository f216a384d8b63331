"""Resumable downloads with urllib (HTTP Range on an interrupted ``.part`` file, sha256 check)."""

from __future__ import annotations

import re
import urllib.error
import urllib.request
from pathlib import Path

from tqdm import tqdm

from src.data.cache import file_sha256
from src.utils.errors import DatasetError

_CONTENT_RANGE = re.compile(r"bytes (\d+)-")


def _resumes(response, offset: int) -> bool:
    """Whether the server answered a Range request from ``offset`` with that partial content."""
    match = _CONTENT_RANGE.match(response.headers.get("Content-Range", ""))
    return getattr(response, "status", None) == 206 and match is not None and int(match[1]) == offset


def download(url: str, dest: Path, sha256: str | None = None, chunk_size: int = 1 << 20, timeout: float = 60) -> Path:
    """Download ``url`` to ``dest`` (skipped when ``dest`` exists and matches ``sha256``).

    Streams to ``dest.part``; an existing ``.part`` is resumed with an HTTP Range request (restarted
    when the server ignores it). A sha256 mismatch deletes the file and raises :class:`DatasetError`.
    ``file://`` URLs work too.
    """
    dest = Path(dest)
    if dest.is_file() and (sha256 is None or file_sha256(dest) == sha256):
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = dest.with_name(dest.name + ".part")
    offset = part.stat().st_size if part.is_file() else 0
    request = urllib.request.Request(url, headers={"Range": f"bytes={offset}-"} if offset else {})
    try:
        response = urllib.request.urlopen(request, timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code != 416 or not offset:  # 416: the .part is not a prefix of this file
            raise DatasetError(f"download of {url} failed: HTTP {e.code} {e.reason}") from e
        part.unlink()
        return download(url, dest, sha256, chunk_size, timeout)
    except (urllib.error.URLError, OSError) as e:
        raise DatasetError(f"download of {url} failed ({e}); download it manually and pass --source PATH") from e
    with response:
        if offset and not _resumes(response, offset):
            offset = 0
        length = response.headers.get("Content-Length")
        total = offset + int(length) if length else None
        with open(part, "ab" if offset else "wb") as f, tqdm(
            total=total, initial=offset, unit="B", unit_scale=True, desc=dest.name, disable=None
        ) as bar:
            try:
                while chunk := response.read(chunk_size):
                    f.write(chunk)
                    bar.update(len(chunk))
            except OSError as e:
                raise DatasetError(f"download of {url} interrupted ({e}); run again to resume") from e
    size = part.stat().st_size
    if total is not None and size != total:
        raise DatasetError(f"download of {url} incomplete ({size} of {total} bytes); run again to resume")
    if sha256 is not None and file_sha256(part) != sha256:
        part.unlink()
        raise DatasetError(f"download of {url} is corrupt (sha256 mismatch, expected {sha256}); file deleted")
    part.replace(dest)
    return dest
