"""``prepare --download``: a dataset's archive from the first of its hosts that serves it intact.

The hosts are the record's (:class:`~src.data.datasets.Mirror`, in order), or those that the JSON file
named by ``$OMNET_DATA_MIRRORS`` lists for the layout (a site's own mirrors), or the user's ``--url``.
Each host is tried once (an interrupted transfer is resumed while it progresses): a failure is one
logged line (address, what happened) and the next host is tried; when none serves it, one error says
how to download it by hand. What arrives is verified before it is used: its published checksum (else its
published size), then its structure (a readable archive in the expected layout); a file that fails is
deleted, so ``<cache_root>/downloads/`` only ever holds verified archives (and ``.part`` files that the
next try resumes). Where no checksum is published, one line says so and the sha256 of the first good
download is recorded beside it (``<name>.sha256``, as ``sha256sum`` writes it): later downloads, and the
archive kept, are verified against it. An archive kept from an earlier run is used only once verified so, with
one line naming it and the shapes it gives; one that nothing can verify is refused. A ``.tar.gz`` is unpacked
(``tarfile``'s ``data`` filter) into a folder beside it.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import tarfile
from collections.abc import Sequence
from pathlib import Path

from src.data.cache import file_sha256
from src.data.datasets import Dataset, Mirror, Source
from src.data.download import ChecksumMismatch, DownloadError, download, hash_matches
from src.data.readers import READERS, Archive, layout_of
from src.utils.errors import DatasetError
from src.utils.files import write_text_atomic

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
        recorded = None if mirror.known_hash else _recorded_hash(dest)
        try:
            _discard(dest)  # (what an earlier archive of that name unpacked to)
            archive, shapes = _verified(download(mirror.url, dest, mirror.known_hash or recorded), mirror.size, layouts)
        except ChecksumMismatch as e:
            log.warning(f"{mirror.url}: {e}{_recorded_note(dest) if recorded else ''}")
            continue
        except DownloadError as e:
            log.warning(f"{mirror.url}: {e}")
            continue
        if mirror.known_hash is None and recorded is None:
            _record(dest, mirror.url)
        log.info(f"downloaded {dest} from {mirror.url}: {shapes}")
        return archive
    archive = name or (mirrors[0].file_name if mirrors else "its archive")
    raise DatasetError(
        f"no host served {archive} intact ({len(mirrors)} tried, one line each above); download it by hand and run "
        f"`python -m src.data.prepare {dataset.name} --source PATH` (PATH: that archive or its unpacked folder)"
    )


def sha256_record(path: Path) -> Path:
    """Where the sha256 of the first good download of ``path`` is recorded, when no checksum of it is published."""
    return path.with_name(f"{path.name}.sha256")


def _recorded_hash(path: Path) -> str | None:
    """The sha256 recorded for ``path`` (pooch's ``"sha256:hex"``), None without a readable record."""
    try:
        digest = sha256_record(path).read_text().split()[0].lower()
    except (OSError, IndexError):
        return None
    return f"sha256:{digest}" if re.fullmatch(r"[0-9a-f]{64}", digest) else None


def _recorded_note(path: Path) -> str:
    return (f" (the sha256 recorded at its first download, in {sha256_record(path)}: delete that file to accept "
            "another version of the archive)")


def _record(path: Path, url: str) -> None:
    """Record the sha256 of ``path`` (a verified first download from ``url``, of which no checksum is published)."""
    digest = file_sha256(path)
    write_text_atomic(sha256_record(path), f"{digest}  {path.name}\n")
    log.warning(f"{url}: no checksum of {path.name} is published; the sha256 of this download, {digest}, is recorded "
                f"in {sha256_record(path)}, and later downloads of it are verified against it")


def _kept(path: Path, mirrors: Sequence[Mirror], layouts: Sequence[str]) -> Path | None:
    """``path``, kept from an earlier run, verified as if one of ``mirrors`` (the hosts of that file name) had just
    served it: against a published checksum, else the sha256 recorded at its first download (deleted when it
    matches none of them, then downloaded again); None when absent. DatasetError when nothing can verify it."""
    if not path.is_file():
        return None
    checks = {m.known_hash: (m.size, f"{m.known_hash.split(':')[0]} as published") for m in mirrors if m.known_hash}
    recorded = _recorded_hash(path) if any(m.known_hash is None for m in mirrors) else None
    if recorded:
        size = next(m.size for m in mirrors if m.known_hash is None)
        checks.setdefault(recorded, (size, f"sha256 as recorded at its first download, in {sha256_record(path)}"))
    if not checks:
        raise DatasetError(
            f"{path} is in the downloads folder, but no checksum of it is published and none was recorded when it "
            "was downloaded, so it cannot be verified (it may be partial or another file): delete it to download it "
            f"again, or pass it as --source {path} to use it as it is"
        )
    matching = next((h for h in checks if hash_matches(path, h)), None)
    try:
        if matching is None:
            raise DownloadError(f"checksum mismatch: expected {' or '.join(checks)}")
        size, how = checks[matching]
        archive, shapes = _verified(path, size, layouts)
    except DownloadError as e:
        _discard(path)
        log.warning(f"{path}: {e}; deleted: downloading it again")
        return None
    log.info(f"using {path}, kept from an earlier download ({how}): {shapes}")
    return archive


def _verified(path: Path, size: int | None, layouts: Sequence[str]) -> tuple[Path, str]:
    """``path`` (a .tar archive: its unpacked folder) and the shapes it gives (per split), when its size (``size``:
    the published one, None: none published) and structure are as expected; deleted (with what it unpacked to)
    otherwise."""
    try:
        if size is not None and path.stat().st_size != size:
            raise DownloadError(f"{path.stat().st_size:,} bytes where {size:,} are published")
        archive = _unpacked(path) if path.name.endswith(_TAR_SUFFIXES) else path
        layout, shapes = _contents(archive)
        if layout not in layouts:
            raise DownloadError(f"it holds the {layout} layout, not {' or '.join(layouts)}")
        return archive, shapes
    except DownloadError:
        _discard(path)
        raise


def _discard(path: Path) -> None:
    """Delete the archive ``path`` and what it unpacked to."""
    if path.name.endswith(_TAR_SUFFIXES):
        shutil.rmtree(_unpack_folder(path), ignore_errors=True)
    path.unlink(missing_ok=True)


def _contents(archive: Path) -> tuple[str, str]:
    """The layout of ``archive`` and the shapes it gives: ``"9,843 shapes (train 7,378, test 2,465)"``."""
    try:
        opened = Archive(archive)
        layout = layout_of(opened)
        entries = READERS[layout](opened).entries
    except DatasetError as e:
        raise DownloadError(f"not a readable archive of the dataset: {e}") from e
    splits = ", ".join(f"{split} {len(shapes):,}" for split, shapes in entries.items())
    return layout, f"{sum(map(len, entries.values())):,} shapes ({splits or 'no split'})"


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
