"""``prepare --download``: a dataset's archive from the first of its hosts that serves it intact.

The hosts are the record's (:class:`~src.data.datasets.Mirror`, in order), or those that the JSON file
named by ``$OMNET_DATA_MIRRORS`` lists for the layout (a site's own mirrors), or the user's ``--url``.
Each host is tried once (an interrupted transfer is resumed while it progresses): a failure is one
logged line (address, what happened) and the next host is tried; when none serves it, one error says
how to download it by hand. What arrives is verified before it is used: its published checksum (else its
published size), then its structure (a readable archive in the expected layout); a file that fails is
deleted, so ``<cache_root>/downloads/`` only ever holds verified archives (and ``.part`` files that the
next try resumes). A ``.tar.gz`` is unpacked (``tarfile``'s ``data`` filter) into a folder beside it.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tarfile
from collections.abc import Sequence
from pathlib import Path

from src.data.datasets import Dataset, Mirror, Source
from src.data.download import DownloadError, download, hash_matches
from src.data.readers import Archive, layout_of
from src.utils.errors import DatasetError

log = logging.getLogger(__name__)

MIRRORS_ENV = "OMNET_DATA_MIRRORS"
"""Names a JSON file ``{"<layout>": [{"url": ..., "sha256" or "md5": ..., "size": ...}, ...]}``
whose lists replace the records' hosts of those layouts."""

_TAR_SUFFIXES = (".tar.gz", ".tgz", ".tar")


def download_archive(dataset: Dataset, downloads: Path, layout: str | None = None, url: str | None = None) -> Path:
    """The archive (a .zip file or an unpacked folder) of ``dataset``'s ``layout`` (default: the first
    it downloads) in ``downloads``, from the first host that serves it intact, or ``url`` (any of the
    dataset's layouts; no checksum)."""
    if url:
        name = Mirror(url).file_name or f"{dataset.name}.zip"
        return _first_intact(dataset, [Mirror(url)], dataset.layouts, downloads, name)
    source = _source(dataset, layout)
    return _first_intact(dataset, _mirrors(source), (source.layout,), downloads)


def _source(dataset: Dataset, layout: str | None) -> Source:
    if not dataset.downloads:
        raise DatasetError(f"{dataset.name} has no archive to download: pass --source PATH (or --download --url URL)")
    if layout is None:
        return dataset.downloads[0]
    match = [s for s in dataset.downloads if s.layout == layout]
    if not match:
        known = ", ".join(s.layout for s in dataset.downloads)
        raise DatasetError(f"{dataset.name} downloads no {layout} archive; its layouts to download: {known}")
    return match[0]


def _mirrors(source: Source) -> tuple[Mirror, ...]:
    """The hosts of ``source``: those of ``$OMNET_DATA_MIRRORS`` for its layout, else the record's."""
    path = os.environ.get(MIRRORS_ENV)
    if not path:
        return source.mirrors
    try:
        listed = json.loads(Path(path).read_text())
        entries = listed.get(source.layout) if isinstance(listed, dict) else None
        if entries is None:
            return source.mirrors
        return tuple(Mirror(**entry, evidence=f"{MIRRORS_ENV}={path}") for entry in entries)
    except (OSError, ValueError, TypeError) as e:
        raise DatasetError(
            f"{MIRRORS_ENV}={path}: expected a JSON file mapping layouts to lists of "
            f'{{"url", "sha256" or "md5", "size"}} ({e})'
        ) from e


def _first_intact(
    dataset: Dataset, mirrors: Sequence[Mirror], layouts: Sequence[str], downloads: Path, name: str | None = None,
) -> Path:
    dests = {mirror: downloads / (name or mirror.file_name) for mirror in mirrors}
    for dest in dict.fromkeys(dests.values()):  # an archive kept from an earlier run, before the network
        kept = _kept(dest, [m for m, d in dests.items() if d == dest], layouts)
        if kept is not None:
            return kept
    for mirror, dest in dests.items():
        try:
            return _verified(download(mirror.url, dest, mirror.known_hash), mirror, layouts)
        except DownloadError as e:
            log.warning(f"{mirror.url}: {e}")
    archive = name or (mirrors[0].file_name if mirrors else "its archive")
    raise DatasetError(
        f"no host served {archive} intact ({len(mirrors)} tried, one line each above); download it by hand and run "
        f"`python -m src.data.prepare {dataset.name} --source PATH` (PATH: that archive or its unpacked folder)"
    )


def _kept(path: Path, mirrors: Sequence[Mirror], layouts: Sequence[str]) -> Path | None:
    """``path`` verified as if one of ``mirrors`` (the hosts of that file name) had just served it
    (deleted when none would have); None when absent."""
    if not path.is_file():
        return None
    matches = {h: hash_matches(path, h) for h in {m.known_hash for m in mirrors} if h}  # each read once
    matching = [m for m in mirrors if m.known_hash is None or matches[m.known_hash]]
    try:
        if not matching:
            raise DownloadError(f"checksum mismatch: expected {' or '.join(m.known_hash for m in mirrors)}")
        return _verified(path, matching[0], layouts)
    except DownloadError as e:
        path.unlink(missing_ok=True)
        log.warning(f"{path}: {e}; deleted")
        return None


def _verified(path: Path, mirror: Mirror, layouts: Sequence[str]) -> Path:
    """``path`` (a .tar archive: its unpacked folder) when its size and structure are as expected;
    deleted (with what it unpacked to) otherwise."""
    try:
        if mirror.size is not None and path.stat().st_size != mirror.size:
            raise DownloadError(f"{path.stat().st_size:,} bytes where {mirror.size:,} are published")
        archive = _unpacked(path) if path.name.endswith(_TAR_SUFFIXES) else path
        layout = _layout(archive)
        if layout not in layouts:
            raise DownloadError(f"it holds the {layout} layout, not {' or '.join(layouts)}")
        return archive
    except DownloadError:
        if path.name.endswith(_TAR_SUFFIXES):
            shutil.rmtree(_unpack_folder(path), ignore_errors=True)
        path.unlink(missing_ok=True)
        raise


def _layout(archive: Path) -> str:
    try:
        return layout_of(Archive(archive))
    except DatasetError as e:
        raise DownloadError(f"not a readable archive of the dataset: {e}") from e


def _unpack_folder(path: Path) -> Path:
    name = path.name
    for suffix in _TAR_SUFFIXES:
        name = name.removesuffix(suffix)
    return path.with_name(name)


def _unpacked(path: Path) -> Path:
    """The folder ``path`` (a tar archive) unpacks to, beside it (unpacked once: through a temporary
    folder renamed when complete)."""
    folder = _unpack_folder(path)
    if folder.is_dir():
        return folder
    if not hasattr(tarfile, "data_filter"):
        raise DatasetError(f"{path}: this Python cannot unpack archives safely (tarfile has no data filter): "
                           f"unpack it by hand and pass the folder as --source")
    staging = folder.with_name(f".{folder.name}.unpacking")
    shutil.rmtree(staging, ignore_errors=True)
    try:
        with tarfile.open(path) as tar:
            tar.extractall(staging, filter="data")
    except (tarfile.TarError, EOFError, OSError) as e:
        shutil.rmtree(staging, ignore_errors=True)
        raise DownloadError(f"not a readable tar archive ({e})") from e
    staging.rename(folder)
    return folder
