"""Fetch one file from one host into a folder, verified, or raise :class:`DownloadError` with what happened.

* A plain address goes through ``pooch.retrieve``: the transfer lands in a temporary file that is moved
  to its name only when its checksum matches (deleted otherwise). ``pooch`` restarts an interrupted
  transfer from zero, so its downloader here is :class:`RangeDownloader` (urllib): it streams into a
  ``.part`` file kept beside the target, with a record of the version of the file it holds (the host's
  ``ETag`` or ``Last-Modified``, and the size), and resumes only that version: a Range request with
  ``If-Range``, whose answer must be the rest of a file of that size; any other answer starts over. A host
  that names no version or size cannot be resumed safely: its interrupted transfers start over.
* A HuggingFace dataset address (``https://huggingface.co/datasets/<repo>/resolve/<revision>/<file>``) is
  fetched the same way from the endpoint that ``HF_ENDPOINT`` names (``huggingface_hub``'s setting, read at
  each call), if set: its ``resolve`` address redirects to the file itself.
* Every host is held to :class:`Limits`: a time limit for its whole transfer (retries included) and a
  minimum rate, so that a host that keeps the connection open but sends almost nothing is given up. The
  progress is a bar on a terminal, else a plain line every :data:`PROGRESS_EVERY` seconds.
"""

from __future__ import annotations

import hashlib
import http.client
import json
import logging
import math
import os
import re
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pooch
from tqdm import tqdm

from src.utils.errors import DatasetError
from src.utils.files import write_text_atomic

log = logging.getLogger(__name__)

_CONTENT_RANGE = re.compile(r"bytes (\d+)-\d+/(\d+)")
HF_ADDRESS = re.compile(
    r"^https://huggingface\.co/datasets/(?P<repo>[^/]+/[^/]+)/resolve/(?P<revision>[^/]+)/(?P<file>[^?#]+)"
)
TIME_LIMIT_ENV = "OMNET_DOWNLOAD_TIME_LIMIT"
"""Seconds one host may take for its whole transfer (default :attr:`Limits.time_limit`)."""
MIN_RATE_ENV = "OMNET_DOWNLOAD_MIN_RATE"
"""Bytes per second under which a host is given up (default :attr:`Limits.min_rate`; 0: no minimum)."""
PROGRESS_EVERY = 30.0
"""Seconds between two progress lines where no terminal shows a bar (a log, a batch job)."""


class DownloadError(DatasetError):
    """One host did not serve the file intact; the message says what happened (no address)."""


class ChecksumMismatch(DownloadError):
    """What arrived is not the file the checksum names (it is deleted)."""


@dataclass(frozen=True)
class Limits:
    """How long one host may take: ``time_limit`` seconds for its whole transfer (its retries included), and
    at least ``min_rate`` bytes/s over every ``window`` seconds (0: no minimum)."""

    time_limit: float = 6 * 3600.0
    min_rate: float = 4096.0
    window: float = 120.0

    @classmethod
    def from_environment(cls) -> Limits:
        """The defaults, or the values of :data:`TIME_LIMIT_ENV` and :data:`MIN_RATE_ENV`."""
        values = {}
        for env, key, lowest in ((TIME_LIMIT_ENV, "time_limit", "> 0"), (MIN_RATE_ENV, "min_rate", ">= 0")):
            text = os.environ.get(env)
            if text is None:
                continue
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not math.isfinite(value) or value < 0 or (value == 0 and lowest == "> 0"):
                unit = "seconds" if key == "time_limit" else "bytes per second"
                raise DatasetError(f"{env}={text}: expected a number of {unit} {lowest}")
            values[key] = value
        return cls(**values)


class _GaveUp(Exception):
    """A host that exceeded its :class:`Limits`."""


class _Watch:
    """One host's transfer held to its :class:`Limits`, and its progress as plain lines where no terminal shows
    a bar."""

    def __init__(self, name: str, limits: Limits):
        self.name, self.limits = name, limits
        self.start = self.window_start = self.last_line = time.monotonic()
        self.window_bytes = self.received = self.done = 0
        self.total: int | None = None
        self.lines = not sys.stderr.isatty()

    def left(self) -> float:
        """Seconds left of the time limit (:class:`_GaveUp` when none are)."""
        left = self.start + self.limits.time_limit - time.monotonic()
        if left <= 0:
            raise _GaveUp(f"not finished within the time limit of {self.limits.time_limit:,.0f} s "
                          f"(set {TIME_LIMIT_ENV}=SECONDS to allow more)")
        return left

    def begin(self, done: int, total: int | None) -> None:
        """A try starts with ``done`` bytes of ``total`` (None: unknown) already there."""
        self.done, self.total = done, total

    def arrived(self, n: int) -> None:
        """``n`` more bytes; :class:`_GaveUp` past the limits."""
        now = time.monotonic()
        self.done += n
        self.received += n
        self.window_bytes += n
        self.left()
        elapsed = now - self.window_start
        if elapsed >= self.limits.window:
            rate = self.window_bytes / elapsed
            if rate < self.limits.min_rate:
                raise _GaveUp(f"{rate:,.0f} bytes/s over the last {elapsed:.0f} s, under the minimum of "
                              f"{self.limits.min_rate:,.0f} (set {MIN_RATE_ENV}=BYTES_PER_SECOND to accept slower "
                              "hosts)")
            self.window_start, self.window_bytes = now, 0
        if self.lines and now - self.last_line >= PROGRESS_EVERY:
            self.last_line = now
            of = f" of {self.total / 1e6:,.1f} MB ({100 * self.done / self.total:.0f} %)" if self.total else " MB"
            log.info(f"{self.name}: {self.done / 1e6:,.1f}{of}, {self.received / 1e6 / (now - self.start):.2f} MB/s")


def hash_matches(path: Path, known_hash: str) -> bool:
    """Whether ``path`` has the checksum ``known_hash`` (pooch's ``"alg:hex"``)."""
    alg, expected = known_hash.split(":", 1)
    return pooch.file_hash(str(path), alg) == expected.lower()


def part_file(dest: Path, url: str) -> Path:
    """Where an interrupted transfer of ``url`` to ``dest`` is kept: one per address, so that a
    transfer is only ever resumed from the host it started on."""
    return dest.with_name(f"{dest.name}.{hashlib.sha256(url.encode()).hexdigest()[:12]}.part")


def part_record(part: Path) -> Path:
    """The record of the version of the file that ``part`` holds the start of (JSON: ``if_range``, ``size``)."""
    return part.with_name(f"{part.name}.json")


def _version(response: Any) -> dict[str, Any] | None:
    """The version of the whole file a response serves: its strong ``ETag`` (else its ``Last-Modified``) and its
    size; None when it names either not."""
    etag = response.headers.get("ETag")
    validator = etag if etag and not etag.startswith("W/") else response.headers.get("Last-Modified")
    size = response.headers.get("Content-Length")
    return {"if_range": validator, "size": int(size)} if validator and size and size.isdigit() else None


def _resumes(response: Any, offset: int, size: int) -> bool:
    """Whether the answer to a Range request from ``offset`` is the rest of a file of ``size`` bytes."""
    match = _CONTENT_RANGE.match(response.headers.get("Content-Range", ""))
    return (getattr(response, "status", None) == 206 and match is not None and int(match[1]) == offset
            and int(match[2]) == size)


class RangeDownloader:
    """A ``pooch`` downloader (``downloader(url, output_file, pooch)``) that streams into ``part`` and resumes
    the version of the file recorded beside it (:func:`part_record`) with a Range request and ``If-Range``
    (starting over on any other answer); an interrupted transfer is tried again from where it stopped while each
    try makes progress, at most ``attempts`` times, and kept for a later run otherwise. The whole transfer is
    held to ``limits``; each read waits at most ``timeout`` seconds."""

    def __init__(self, part: Path, name: str, timeout: float = 60, chunk_size: int = 1 << 20, attempts: int = 3,
                 limits: Limits | None = None):
        self.part, self.name, self.timeout = Path(part), name, timeout
        self.record = part_record(self.part)
        self.chunk_size, self.attempts, self.limits = chunk_size, attempts, limits or Limits()

    def __call__(self, url: str, output_file: str, pooch_obj: object = None) -> None:
        watch = _Watch(self.name, self.limits)
        for attempt in range(self.attempts):
            before = self._size()
            try:
                self._transfer(url, watch)
                break
            except _Interrupted as e:
                if attempt == self.attempts - 1 or self._size() <= before:
                    raise DownloadError(str(e)) from e
            except _GaveUp as e:
                raise DownloadError(f"given up after {self._size():,} bytes: {e}{self._kept()}") from e
        os.replace(self.part, output_file)
        self.record.unlink(missing_ok=True)

    def _size(self) -> int:
        return self.part.stat().st_size if self.part.is_file() else 0

    def _kept(self) -> str:
        return "; kept: the next try resumes it" if self.record.is_file() and self._size() else ""

    def _recorded(self) -> dict[str, Any] | None:
        """The recorded version of the file the ``.part`` holds the start of; None when none is recorded (the
        ``.part`` is then deleted: whose file it holds is unknown)."""
        try:
            version = json.loads(self.record.read_text())
            if isinstance(version, dict) and isinstance(version.get("if_range"), str) and version.get("size"):
                return version
        except (OSError, ValueError):
            pass
        self._discard()
        return None

    def _discard(self) -> None:
        self.part.unlink(missing_ok=True)
        self.record.unlink(missing_ok=True)

    def _transfer(self, url: str, watch: _Watch) -> None:
        version = self._recorded() if self.part.is_file() else None
        offset = self._size() if version else 0
        headers = {"Range": f"bytes={offset}-", "If-Range": version["if_range"]} if offset else {}
        try:
            response = urllib.request.urlopen(urllib.request.Request(url, headers=headers),
                                              timeout=min(self.timeout, watch.left()))
        except urllib.error.HTTPError as e:
            if e.code == 416 and offset:  # the .part is no prefix of this file: start again
                self._discard()
                return self._transfer(url, watch)
            raise DownloadError(f"HTTP {e.code} {e.reason}") from e
        except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
            raise DownloadError(f"cannot connect ({getattr(e, 'reason', e)})") from e
        with response:
            if offset and not _resumes(response, offset, version["size"]):
                whole = getattr(response, "status", None) != 206
                why = ("does not resume transfers" if whole and _version(response) == version else
                       f"now serves another version of the file than the {offset:,} bytes kept from it")
                log.warning(f"{self.name}: the host {why}: starting over")
                if not whole:  # a part of the other version: ask for all of it
                    self._discard()
                    return self._transfer(url, watch)
                offset = 0  # the whole file follows
            if not offset:
                self.record.unlink(missing_ok=True)
                version = _version(response)
                if version is not None:
                    write_text_atomic(self.record, json.dumps(version))
            length = response.headers.get("Content-Length")
            total = version["size"] if version else (int(length) if length and length.isdigit() else None)
            watch.begin(offset, total)
            with open(self.part, "ab" if offset else "wb") as f, tqdm(
                total=total, initial=offset, unit="B", unit_scale=True, desc=self.name, disable=None
            ) as bar:
                try:
                    while chunk := response.read1(self.chunk_size):  # what arrived, however little: limits checked
                        f.write(chunk)
                        bar.update(len(chunk))
                        watch.arrived(len(chunk))
                except (OSError, http.client.HTTPException) as e:
                    raise self._interrupted(f.tell(), total, e) from e
        if total is not None and self._size() != total:
            raise self._interrupted(self._size(), total)

    def _interrupted(self, size: int, total: int | None, cause: BaseException | None = None) -> _Interrupted:
        """The error of a transfer that stopped at ``size`` bytes: its ``.part`` kept when its version is recorded
        (the next try resumes it), else deleted (the next try starts over)."""
        of = f" of {total:,}" if total is not None else ""
        because = f" ({cause})" if cause is not None else ""
        if self.record.is_file():
            return _Interrupted(f"interrupted after {size:,}{of} bytes{because} (kept: the next try resumes it)")
        self._discard()
        return _Interrupted(f"interrupted after {size:,}{of} bytes{because}; the host names no version of the file "
                            "(ETag or Last-Modified, and size), so the next try starts over")


class _Interrupted(Exception):
    """A transfer that stopped before its end."""


@contextmanager
def _quiet(logger: logging.Logger, level: int) -> Iterator[None]:
    """Only ``level`` and above from ``logger``: pooch logs each download and hash, and :mod:`src.data.mirrors`
    says in one line what each host did."""
    before = logger.level
    logger.setLevel(level)
    try:
        yield
    finally:
        logger.setLevel(before)


def download(url: str, dest: Path, known_hash: str | None = None, timeout: float = 60,
             limits: Limits | None = None) -> Path:
    """``url`` at ``dest`` (kept when already there and matching ``known_hash``, pooch's ``"alg:hex"``), the
    host held to ``limits`` (default: :meth:`Limits.from_environment`).

    A transfer that fails its checksum is deleted (:class:`ChecksumMismatch`); an interrupted one is kept to be
    resumed (from the same address, the same version of the file). Raises :class:`DownloadError`.
    """
    dest = Path(dest)
    limits = limits or Limits.from_environment()
    dest.parent.mkdir(parents=True, exist_ok=True)
    part = part_file(dest, url)
    try:
        with _quiet(pooch.get_logger(), logging.WARNING):
            pooch.retrieve(_on_endpoint(url), known_hash, fname=dest.name, path=dest.parent,
                           downloader=RangeDownloader(part, dest.name, timeout=timeout, limits=limits))
    except ValueError as e:  # pooch: the checksum of the transfer does not match (the file is deleted)
        raise ChecksumMismatch(f"checksum mismatch: expected {known_hash}; the transfer is deleted") from e
    for stale in dest.parent.glob(f"{dest.name}.*.part*"):  # other hosts' interrupted transfers of it
        stale.unlink()
    return dest


def _on_endpoint(url: str) -> str:
    """A HuggingFace dataset address on the endpoint ``$HF_ENDPOINT`` names, when set; any other address as given."""
    endpoint = os.environ.get("HF_ENDPOINT")
    if endpoint and HF_ADDRESS.match(url):
        return endpoint.rstrip("/") + url.removeprefix("https://huggingface.co")
    return url
