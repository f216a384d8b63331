"""One host, one file (src/data/download.py), against a real HTTP server on 127.0.0.1: every case ends
in the right file or a DownloadError naming what happened, and never leaves a corrupt file behind."""

import hashlib
import json
import logging
import re
import time

import pytest

import src.data.download as download_module
from src.data.download import DownloadError, Limits, RangeDownloader, download, part_file, part_record
from src.utils.errors import DatasetError
from tests.helpers.http_server import File, HubFile, Redirect, dead_url, serve

PAYLOAD = bytes(range(256)) * 400  # 102,400 bytes
SHA = f"sha256:{hashlib.sha256(PAYLOAD).hexdigest()}"
MD5 = f"md5:{hashlib.md5(PAYLOAD).hexdigest()}"


def _files(folder):
    return sorted(p.name for p in folder.iterdir() if p.is_file())


def test_fresh_download_with_checksum_then_no_request(tmp_path):
    with serve({"/file.bin": File(PAYLOAD)}) as (url, requests):
        dest = download(f"{url}/file.bin", tmp_path / "d" / "file.bin", SHA)
        assert dest.read_bytes() == PAYLOAD and _files(tmp_path / "d") == ["file.bin"]
        assert download(f"{url}/file.bin", dest, MD5) == dest  # present and intact: no request
    assert requests == [("GET", "/file.bin", None)]


def test_interrupted_transfer_is_resumed_with_range(tmp_path):
    with serve({"/file.bin": File(PAYLOAD, drop_after=30000)}) as (url, requests):
        dest = download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert requests == [("GET", "/file.bin", None), ("GET", "/file.bin", "bytes=30000-")]
    assert dest.read_bytes() == PAYLOAD and _files(tmp_path) == ["file.bin"]


def _earlier_part(dest, url, data: bytes, version: bytes = PAYLOAD):
    """The ``.part`` an earlier run left, holding ``data``, recorded as the start of the file ``version``."""
    part = part_file(dest, url)
    part.write_bytes(data)
    etag = f'"{hashlib.sha256(version).hexdigest()}"'  # what the test server sends for it
    part_record(part).write_text(json.dumps({"if_range": etag, "size": len(version)}))
    return part


def test_part_left_by_an_earlier_run_is_resumed(tmp_path):
    with serve({"/file.bin": File(PAYLOAD, drop_after=30000)}) as (url, requests):
        part = part_file(tmp_path / "file.bin", f"{url}/file.bin")
        with pytest.raises(DownloadError, match=r"^interrupted after 30,000 of 102,400 bytes .*the next try resumes"):
            RangeDownloader(part, "file.bin", attempts=1)(f"{url}/file.bin", str(tmp_path / "out"))  # the earlier run
        dest = download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert requests == [("GET", "/file.bin", None), ("GET", "/file.bin", "bytes=30000-")] and dest.read_bytes() == PAYLOAD
    assert _files(tmp_path) == ["file.bin"]


@pytest.mark.parametrize(("route", "part", "ranges"), [
    (File(PAYLOAD, ranges=False), b"garbage", ["bytes=7-"]),  # range ignored: restarted
    (File(PAYLOAD), PAYLOAD + b"extra", [f"bytes={len(PAYLOAD) + 5}-", None]),  # 416: restarted
])
def test_part_that_cannot_be_resumed_is_restarted(tmp_path, route, part, ranges):
    with serve({"/file.bin": route}) as (url, requests):
        _earlier_part(tmp_path / "file.bin", f"{url}/file.bin", part)
        dest = download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert [r[2] for r in requests] == ranges and dest.read_bytes() == PAYLOAD


def test_redirect_is_followed(tmp_path):
    with serve({"/old.bin": Redirect("/file.bin"), "/file.bin": File(PAYLOAD)}) as (url, requests):
        dest = download(f"{url}/old.bin", tmp_path / "file.bin", SHA)
    assert dest.read_bytes() == PAYLOAD and [r[1] for r in requests] == ["/old.bin", "/file.bin"]


@pytest.mark.parametrize("route", [File(PAYLOAD, truncate_to=50000), File(PAYLOAD[::-1])])
def test_checksum_mismatch_deletes_the_transfer(tmp_path, route):
    with serve({"/file.bin": route}) as (url, _), pytest.raises(DownloadError, match=r"^checksum mismatch: expected sha256:"):
        download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert list(tmp_path.iterdir()) == []


def test_http_error_and_refused_connection(tmp_path):
    with serve({}) as (url, _), pytest.raises(DownloadError, match="^HTTP 404 Not Found$"):
        download(f"{url}/absent.bin", tmp_path / "a.bin")
    with pytest.raises(DownloadError, match=r"^cannot connect \(.*[Cc]onnection refused"):
        download(dead_url(), tmp_path / "x.zip", timeout=5)
    assert list(tmp_path.iterdir()) == []


def test_file_url(tmp_path):
    (tmp_path / "src.bin").write_bytes(PAYLOAD)
    url = (tmp_path / "src.bin").as_uri()
    part_file(tmp_path / "out.bin", url).write_bytes(b"stale")  # file:// ignores Range: restarted
    assert download(url, tmp_path / "out.bin", SHA).read_bytes() == PAYLOAD
    assert _files(tmp_path) == ["out.bin", "src.bin"]


HUB = "https://huggingface.co/datasets/someone/data/resolve/main/file.bin"
HUB_PATH = "/datasets/someone/data/resolve/main/file.bin"


def test_huggingface_address_is_fetched_from_its_endpoint(tmp_path, monkeypatch):
    with serve({HUB_PATH: HubFile(PAYLOAD)}) as (url, requests):
        monkeypatch.setenv("HF_ENDPOINT", url)  # huggingface_hub's documented endpoint setting
        dest = download(HUB, tmp_path / "file.bin", SHA)
    assert dest.read_bytes() == PAYLOAD and ("GET", HUB_PATH, None) in requests
    assert _files(tmp_path) == ["file.bin"]


def test_huggingface_checksum_mismatch_and_missing_file(tmp_path, monkeypatch):
    with serve({HUB_PATH: HubFile(PAYLOAD[::-1])}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(DownloadError, match="^checksum mismatch"):
            download(HUB, tmp_path / "file.bin", SHA)
        with pytest.raises(DownloadError, match=r"404|not found|Not Found"):
            download(HUB.replace("file.bin", "absent.bin"), tmp_path / "absent.bin", SHA)
    assert _files(tmp_path) == []


OTHER = bytes(range(255, -1, -1)) * 400  # another version of the file, of the same size


def test_a_part_of_another_version_of_the_file_is_never_spliced(tmp_path, caplog):
    """The host's file changed since the .part was kept: If-Range gets the whole new file, not its tail after the
    old file's first 30,000 bytes (which no structure check would notice where no checksum is published)."""
    with serve({"/file.bin": File(OTHER)}) as (url, requests):
        _earlier_part(tmp_path / "file.bin", f"{url}/file.bin", PAYLOAD[:30000])
        dest = download(f"{url}/file.bin", tmp_path / "file.bin")  # no checksum
    assert requests == [("GET", "/file.bin", "bytes=30000-")] and dest.read_bytes() == OTHER
    assert "file.bin: the host now serves another version of the file than the 30,000 bytes kept from it: " \
           "starting over" in caplog.text
    assert _files(tmp_path) == ["file.bin"]


def test_a_range_of_a_file_of_another_size_is_not_appended(tmp_path):
    """A host that ignores If-Range answers with a range of its new file: its size is not the recorded one."""
    longer = OTHER + b"more"
    with serve({"/file.bin": File(longer, if_range=False)}) as (url, requests):
        _earlier_part(tmp_path / "file.bin", f"{url}/file.bin", PAYLOAD[:30000])
        dest = download(f"{url}/file.bin", tmp_path / "file.bin")
    assert [r[2] for r in requests] == ["bytes=30000-", None] and dest.read_bytes() == longer


def test_a_part_without_its_recorded_version_starts_over(tmp_path):
    with serve({"/file.bin": File(PAYLOAD)}) as (url, requests):
        part_file(tmp_path / "file.bin", f"{url}/file.bin").write_bytes(OTHER[:30000])  # whose file? unknown
        dest = download(f"{url}/file.bin", tmp_path / "file.bin")
    assert requests == [("GET", "/file.bin", None)] and dest.read_bytes() == PAYLOAD


def test_a_host_that_names_no_version_is_not_resumed(tmp_path):
    with serve({"/file.bin": File(PAYLOAD, drop_after=30000, etag=False)}) as (url, requests), pytest.raises(
            DownloadError, match=r"^interrupted after 30,000 of 102,400 bytes.*the host names no version of the file "
                                 r"\(ETag or Last-Modified, and size\), so the next try starts over$"):
        download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert requests == [("GET", "/file.bin", None)] and _files(tmp_path) == []


@pytest.mark.parametrize(("limits", "message"), [
    (Limits(time_limit=60, min_rate=2000, window=0.5),
     r"^given up after \d+ bytes: \d+ bytes/s over the last \d+ s, under the minimum of 2,000 \(set "
     r"OMNET_DOWNLOAD_MIN_RATE=BYTES_PER_SECOND to accept slower hosts\); kept: the next try resumes it$"),
    (Limits(time_limit=1, min_rate=0),
     r"^given up after \d+ bytes: not finished within the time limit of 1 s \(set OMNET_DOWNLOAD_TIME_LIMIT=SECONDS "
     r"to allow more\); kept: the next try resumes it$"),
], ids=["min_rate", "time_limit"])
def test_a_host_that_sends_almost_nothing_is_given_up(tmp_path, limits, message):
    """Each read arrives well within the per-read timeout (one byte every 20 ms), so only the rate or the time
    limit of the whole transfer ends it."""
    start = time.monotonic()
    with serve({"/file.bin": File(PAYLOAD, trickle=0.02)}) as (url, _), pytest.raises(DownloadError, match=message):
        download(f"{url}/file.bin", tmp_path / "file.bin", SHA, timeout=5, limits=limits)
    assert time.monotonic() - start < 5
    part = part_file(tmp_path / "file.bin", f"{url}/file.bin")
    assert part.stat().st_size > 0 and part_record(part).is_file()  # the next run resumes it


def test_a_huggingface_host_has_the_same_limits(tmp_path, monkeypatch):
    limits = Limits(time_limit=60, min_rate=2000, window=0.5)
    with serve({HUB_PATH: HubFile(PAYLOAD, trickle=0.02)}) as (url, _):
        monkeypatch.setenv("HF_ENDPOINT", url)
        with pytest.raises(DownloadError, match=r"^given up after \d+ bytes: \d+ bytes/s over the last \d+ s, under"):
            download(HUB, tmp_path / "file.bin", SHA, timeout=5, limits=limits)
    assert "file.bin" not in _files(tmp_path)


def test_progress_is_a_plain_line_without_a_terminal(tmp_path, monkeypatch, caplog):
    monkeypatch.setattr(download_module, "PROGRESS_EVERY", 0.0)
    with serve({"/file.bin": File(PAYLOAD)}) as (url, _), caplog.at_level(logging.INFO, logger="src.data.download"):
        download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    lines = [r.getMessage() for r in caplog.records if r.name == "src.data.download"]
    assert lines and re.fullmatch(r"file\.bin: 0\.1 of 0\.1 MB \(100 %\), [\d.]+ MB/s", lines[-1]), lines


@pytest.mark.parametrize(("env", "value", "expected"), [
    ({}, None, Limits()),
    ({"OMNET_DOWNLOAD_TIME_LIMIT": "600", "OMNET_DOWNLOAD_MIN_RATE": "0"}, None, Limits(time_limit=600, min_rate=0)),
    ({"OMNET_DOWNLOAD_TIME_LIMIT": "0"}, "OMNET_DOWNLOAD_TIME_LIMIT=0: expected a number of seconds > 0", None),
    ({"OMNET_DOWNLOAD_TIME_LIMIT": "inf"}, "OMNET_DOWNLOAD_TIME_LIMIT=inf: expected a number of seconds > 0", None),
    ({"OMNET_DOWNLOAD_MIN_RATE": "fast"}, "OMNET_DOWNLOAD_MIN_RATE=fast: expected a number of bytes per second >= 0",
     None),
])
def test_limits_from_the_environment(monkeypatch, env, value, expected):
    for key in ("OMNET_DOWNLOAD_TIME_LIMIT", "OMNET_DOWNLOAD_MIN_RATE"):
        monkeypatch.delenv(key, raising=False)
    for key, text in env.items():
        monkeypatch.setenv(key, text)
    if expected is not None:
        assert Limits.from_environment() == expected and 0 < Limits().time_limit < float("inf")
    else:
        with pytest.raises(DatasetError) as error:
            Limits.from_environment()
        assert str(error.value) == value
