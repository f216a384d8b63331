import hashlib
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from src.data.download import download
from src.utils.errors import DatasetError

PAYLOAD = bytes(range(256)) * 400  # 102,400 bytes
SHA = hashlib.sha256(PAYLOAD).hexdigest()


class Handler(BaseHTTPRequestHandler):
    """Serves PAYLOAD at /file.bin (honours Range) and /norange.bin (ignores it); records Range headers."""

    ranges: list[str | None] = []

    def do_GET(self):
        if self.path not in ("/file.bin", "/norange.bin"):
            self.send_error(404)
            return
        self.ranges.append(self.headers.get("Range"))
        match = re.fullmatch(r"bytes=(\d+)-", self.headers.get("Range") or "")
        start = int(match[1]) if match and self.path == "/file.bin" else 0
        if start >= len(PAYLOAD) and match:
            self.send_error(416)
            return
        self.send_response(206 if start else 200)
        if start:
            self.send_header("Content-Range", f"bytes {start}-{len(PAYLOAD) - 1}/{len(PAYLOAD)}")
        self.send_header("Content-Length", str(len(PAYLOAD) - start))
        self.end_headers()
        self.wfile.write(PAYLOAD[start:])

    def log_message(self, *args):
        pass


@pytest.fixture
def server():
    Handler.ranges = []
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def test_fresh_download_with_checksum(server, tmp_path):
    dest = download(f"{server}/file.bin", tmp_path / "d" / "file.bin", sha256=SHA, chunk_size=4096)
    assert dest.read_bytes() == PAYLOAD and not (tmp_path / "d" / "file.bin.part").exists()
    assert Handler.ranges == [None]
    download(f"{server}/file.bin", dest, sha256=SHA)  # present and intact: no request
    assert Handler.ranges == [None]


def test_interrupted_download_resumes_with_range(server, tmp_path):
    (tmp_path / "file.bin.part").write_bytes(PAYLOAD[:30000])
    dest = download(f"{server}/file.bin", tmp_path / "file.bin", sha256=SHA)
    assert Handler.ranges == ["bytes=30000-"] and dest.read_bytes() == PAYLOAD


def test_server_ignoring_range_restarts(server, tmp_path):
    (tmp_path / "file.bin.part").write_bytes(b"garbage")
    dest = download(f"{server}/norange.bin", tmp_path / "file.bin", sha256=SHA)
    assert Handler.ranges == ["bytes=7-"] and dest.read_bytes() == PAYLOAD


def test_unsatisfiable_range_restarts(server, tmp_path):
    (tmp_path / "file.bin.part").write_bytes(PAYLOAD + b"extra")
    assert download(f"{server}/file.bin", tmp_path / "file.bin").read_bytes() == PAYLOAD
    assert Handler.ranges == [f"bytes={len(PAYLOAD) + 5}-", None]


def test_checksum_mismatch_deletes_and_raises(server, tmp_path):
    with pytest.raises(DatasetError, match="is corrupt \\(sha256 mismatch"):
        download(f"{server}/file.bin", tmp_path / "file.bin", sha256="0" * 64)
    assert list(tmp_path.iterdir()) == []


def test_http_and_network_errors(server, tmp_path):
    with pytest.raises(DatasetError, match="failed: HTTP 404"):
        download(f"{server}/absent.bin", tmp_path / "a.bin")
    with pytest.raises(DatasetError, match="download it manually and pass --source PATH"):
        download("http://127.0.0.1:9/x.zip", tmp_path / "x.zip", timeout=2)


def test_file_url(tmp_path):
    (tmp_path / "src.bin").write_bytes(PAYLOAD)
    (tmp_path / "out.bin.part").write_bytes(b"stale")  # file:// ignores Range: restarted
    dest = download((tmp_path / "src.bin").as_uri(), tmp_path / "out.bin", sha256=SHA)
    assert dest.read_bytes() == PAYLOAD
