"""One host, one file (src/data/download.py), against a real HTTP server on 127.0.0.1: every case ends
in the right file or a DownloadError naming what happened, and never leaves a corrupt file behind."""

import hashlib

import pytest

from src.data.download import DownloadError, download, part_file
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


def test_part_left_by_an_earlier_run_is_resumed(tmp_path):
    with serve({"/file.bin": File(PAYLOAD)}) as (url, requests):
        part_file(tmp_path / "file.bin", f"{url}/file.bin").write_bytes(PAYLOAD[:30000])
        dest = download(f"{url}/file.bin", tmp_path / "file.bin", SHA)
    assert requests == [("GET", "/file.bin", "bytes=30000-")] and dest.read_bytes() == PAYLOAD


@pytest.mark.parametrize(("route", "part", "ranges"), [
    (File(PAYLOAD, ranges=False), b"garbage", ["bytes=7-"]),  # range ignored: restarted
    (File(PAYLOAD), PAYLOAD + b"extra", [f"bytes={len(PAYLOAD) + 5}-", None]),  # 416: restarted
])
def test_part_that_cannot_be_resumed_is_restarted(tmp_path, route, part, ranges):
    with serve({"/file.bin": route}) as (url, requests):
        part_file(tmp_path / "file.bin", f"{url}/file.bin").write_bytes(part)
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


def test_huggingface_address_goes_through_huggingface_hub(tmp_path, monkeypatch):
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
