"""Fetch one file from one host into a folder, verified, or raise :class:`DownloadError` with what happened.

* A plain address goes through ``pooch.retrieve``: the transfer lands in a temporary file that is moved
  to its name only when its published checksum matches (deleted otherwise). ``pooch`` restarts an
  interrupted transfer from zero, so its downloader here is :class:`RangeDownloader` (urllib): it streams
  into a ``.part`` file kept beside the target and resumes it with an HTTP Range request.
* A HuggingFace dataset address (``https://huggingface.co/datasets/<repo>/resolve/<revision>/<file>``)
  goes through ``huggingface_hub.hf_hub_download`` (its own resume, revision and endpoint:
  ``HF_ENDPOINT``, read at each call); the checksum is then verified here.
"""

from __future__ import annotations

import hashlib
import http.client
import logging
import os
import re
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pooch
from tqdm import tqdm

from src.utils.errors import DatasetError

_CONTENT_RANGE = re.compile(r"bytes (\d+)-")
HF_ADDRESS = re.compile(
    r"^https://huggingface\.co/datasets/(?P<repo>[^/]+/[^/]+)/resolve/(?P<revision>[^/]+)/(?P<file>[^?#]+)"
)


class DownloadError(DatasetError):
    """One host did not serve the file intact; the message says what happened (no address)."""


def hash_matches(path: Path, known_hash: str) -> bool:
    """Whether ``path`` has the checksum ``known_hash`` (pooch's ``"alg:hex"``)."""
    alg, expected = known_hash.split(":", 1)
    return pooch.file_hash(str(path), alg) == expected.lower()


def part_file(dest: Path, url: str) -> Path:
    """Where an interrupted transfer of ``url`` to ``dest`` is kept: one per address, so that a
    transfer is only ever resumed from the host it started on."""
    return dest.with_name(f"{dest.name}.{hashlib.sha256(url.encode()).hexdigest()[:12]}.part")


def _resumes(response, offset: int) -> bool:
    """Whether the server answered a Range request from ``offset`` with that partial content."""
    match = _CONTENT_RANGE.match(response.headers.get("Content-Range", ""))
    return getattr(response, "status", None) == 206 and match is not None and int(match[1]) == offset


class RangeDownloader:
    """A ``pooch`` downloader (``downloader(url, output_file, pooch)``) that streams into ``part`` and
    resumes it with an HTTP Range request (restarting when the server ignores the range or refuses
    it); an interrupted transfer is tried again from where it stopped while each try makes progress,
    at most ``attempts`` times, and is kept for a later run otherwise."""

    def __init__(self, part: Path, name: str, timeout: float = 60, chunk_size: int = 1 << 20, attempts: int = 3):
        self.part, self.name, self.timeout = Path(part), name, timeout
        self.chunk_size, self.attempts = chunk_size, attempts

    def __call__(self, url: str, output_file: str, pooch_obj: object = None) -> None:
        for attempt in range(self.attempts):
            before = self._size()
            try:
                self._transfer(url)
                break
            except _Interrupted as e:
                if attempt == self.attempts - 1 or self._size() <= before:
                    raise DownloadError(str(e)) from e
        os.replace(self.part, output_file)

    def _size(self) -> int:
        return self.part.stat().st_size if self.part.is_file() else 0

    def _transfer(self, url: str) -> None:
        offset = self._size()
        request = urllib.request.Request(url, headers={"Range": f"bytes={offset}-"} if offset else {})
        try:
            response = urllib.request.urlopen(request, timeout=self.timeout)
        except urllib.error.HTTPError as e:
            if e.code == 416 and offset:  # the .part is not a prefix of this file: start again
                self.part.unlink()
                return self._transfer(url)
            raise DownloadError(f"HTTP {e.code} {e.reason}") from e
        except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
            raise DownloadError(f"cannot connect ({getattr(e, 'reason', e)})") from e
        with response:
            if offset and not _resumes(response, offset):
                offset = 0
            length = response.headers.get("Content-Length")
            total = offset + int(length) if length else None
            with open(self.part, "ab" if offset else "wb") as f, tqdm(
                total=total, initial=offset, unit="B", unit_scale=True, desc=self.name, disable=None
            ) as bar:
                try:
                    while chunk := response.read(self.chunk_size):
                        f.write(chunk)
                        bar.update(len(chunk))
                except (OSError, http.client.HTTPException) as e:
                    raise _Interrupted(f"{_stopped(f.tell(), total)} ({e})") from e
        if total is not None and self._size() != total:
            raise _Interrupted(_stopped(self._size(), total))


def _stopped(size: int, total: int | None) -> str:
    of = f" of {total:,}" if total is not None else ""
    return f"interrupted after {size:,}{of} bytes (kept: the next try resumes it)"


class _Interrupted(Exception):
    """A transfer that stopped before its end (its ``.part`` is kept)."""


@contextmanager
def _quiet(logger: logging.Logger, level: int) -> Iterator[None]:
    """Only ``level`` and above from ``logger``: the fetchers log each download, hash and retry, and
    :mod:`src.data.mirrors` says in one line what each host did."""
    before = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(before)


def download(url: str, dest: Path, known_hash: str | None = None, timeout: float = 60) -> Path:
    """``url`` at ``dest`` (kept when already there and matching ``known_hash``, pooch's ``"alg:hex"``).

    A transfer that fails its checksum is deleted; an interrupted one is kept to be resumed (from the
    same address). Raises :class:`DownloadError`.
    """
    dest = Path(dest)
    if HF_ADDRESS.match(url):
        return _hf_download(url, dest, known_hash, timeout)
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = part_file(dest, url)
    try:
        with _quiet(pooch.get_logger(), logging.WARNING):
            pooch.retrieve(url, known_hash, fname=dest.name, path=dest.parent,
                           downloader=RangeDownloader(part, dest.name, timeout=timeout))
    except ValueError as e:  # pooch: the checksum of the transfer does not match (the file is deleted)
        raise DownloadError(f"checksum mismatch: expected {known_hash}; the transfer is deleted") from e
    for stale in dest.parent.glob(f"{dest.name}.*.part"):  # other hosts' interrupted transfers of it
        stale.unlink()
    return dest


def _hf_download(url: str, dest: Path, known_hash: str | None, timeout: float) -> Path:
    """A HuggingFace dataset file through ``huggingface_hub`` (resumed and cached in
    ``<dest folder>/.huggingface/``), moved to ``dest`` once it matches ``known_hash``."""
    from huggingface_hub import hf_hub_download
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError

    if dest.is_file() and (known_hash is None or hash_matches(dest, known_hash)):
        return dest
    address = HF_ADDRESS.match(url)
    try:
        with _quiet(logging.getLogger("huggingface_hub"), logging.ERROR):  # its retries (5, back-off) are silent
            fetched = Path(hf_hub_download(
                address["repo"], address["file"], repo_type="dataset", revision=address["revision"],
                local_dir=dest.parent / ".huggingface", endpoint=os.environ.get("HF_ENDPOINT") or None,
                etag_timeout=timeout,
            ))
    except (HfHubHTTPError, LocalEntryNotFoundError, OSError) as e:
        cause = e.__cause__ if isinstance(e, LocalEntryNotFoundError) and e.__cause__ else e
        first = str(cause).strip().splitlines()[0]
        raise DownloadError(first if isinstance(cause, HfHubHTTPError) else f"cannot connect ({first})") from e
    if known_hash is not None and not hash_matches(fetched, known_hash):
        fetched.unlink()
        raise DownloadError(f"checksum mismatch: expected {known_hash}; the transfer is deleted")
    os.replace(fetched, dest)
    return dest
