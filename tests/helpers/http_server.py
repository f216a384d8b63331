"""A real HTTP server on 127.0.0.1 (a thread) whose routes misbehave on purpose, for the download tests.

``serve({path: route})`` is a context manager yielding ``(base_url, requests)``: ``requests`` records
``(method, path, Range header)`` of every request. Routes:

* :class:`File` serves bytes (honours ``Range``; ``ranges=False`` ignores it) with an ``ETag`` (the data's
  sha256; ``etag=False``: none) and honours ``If-Range`` (another ETag: the whole file; ``if_range=False``
  ignores it), ``drop_after=N`` sends the full ``Content-Length`` but closes the connection after N bytes on
  the first request only, ``truncate_to=N`` serves the first N bytes as if they were the whole file,
  ``trickle=S`` sends one byte every S seconds (a host that keeps the connection open but sends almost nothing);
* :class:`Redirect` answers 302 to another path; a path without a route answers 404;
* :class:`HubFile` answers like the HuggingFace Hub's ``resolve`` endpoint (``X-Repo-Commit``, ``ETag``
  on ``HEAD``; ``GET`` as :class:`File`).

:func:`dead_url` is an address nothing listens on (connection refused).
"""

from __future__ import annotations

import hashlib
import re
import socket
import threading
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


@dataclass
class File:
    data: bytes
    ranges: bool = True
    drop_after: int | None = None
    truncate_to: int | None = None
    etag: bool = True
    if_range: bool = True
    trickle: float | None = None


@dataclass
class Redirect:
    location: str


@dataclass
class HubFile(File):
    commit: str = "0123456789abcdef0123456789abcdef01234567"


def _handler(routes: Mapping[str, object], requests: list) -> type[BaseHTTPRequestHandler]:
    dropped: set[str] = set()

    class Handler(BaseHTTPRequestHandler):
        def do_HEAD(self):
            self._answer(head=True)

        def do_GET(self):
            self._answer(head=False)

        def _answer(self, head: bool) -> None:
            path = self.path.split("?")[0]
            requests.append((self.command, path, self.headers.get("Range")))
            route = routes.get(path)
            if isinstance(route, Redirect):
                self.send_response(302)
                self.send_header("Location", route.location)
                self.send_header("Content-Length", "0")
                self.end_headers()
            elif isinstance(route, File):
                self._file(path, route, head)
            else:
                self.send_error(404)

        def _file(self, path: str, route: File, head: bool) -> None:
            data = route.data[: route.truncate_to] if route.truncate_to is not None else route.data
            etag = f'"{hashlib.sha256(data).hexdigest()}"'
            match = re.fullmatch(r"bytes=(\d+)-", self.headers.get("Range") or "")
            if_range = self.headers.get("If-Range")
            if route.if_range and if_range is not None and (not route.etag or if_range != etag):  # another version
                match = None
            start = int(match[1]) if match and route.ranges else 0
            if match and route.ranges and start >= len(data):
                self.send_error(416)
                return
            self.send_response(206 if start else 200)
            if start:
                self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
            if isinstance(route, HubFile):
                self.send_header("X-Repo-Commit", route.commit)
            if route.etag:
                self.send_header("ETag", etag)
            self.send_header("Content-Length", str(len(data) - start))
            self.end_headers()
            if head:
                return
            body = data[start:]
            if route.trickle is not None:
                self._trickle(body, route.trickle)
                return
            if route.drop_after is not None and path not in dropped:
                dropped.add(path)
                self.wfile.write(body[: route.drop_after])
                self.wfile.flush()
                self.close_connection = True
                self.connection.shutdown(socket.SHUT_RDWR)
                return
            self.wfile.write(body)

        def _trickle(self, body: bytes, every: float) -> None:
            for k in range(len(body)):
                try:
                    self.wfile.write(body[k : k + 1])
                    self.wfile.flush()
                except OSError:  # the client gave up
                    return
                time.sleep(every)

        def log_message(self, *args):
            pass

    return Handler


@contextmanager
def serve(routes: Mapping[str, object]) -> Iterator[tuple[str, list]]:
    requests: list[tuple[str, str, str | None]] = []
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _handler(routes, requests))
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}", requests
    finally:
        httpd.shutdown()
        httpd.server_close()


def dead_url(path: str = "/x.zip") -> str:
    """An address on 127.0.0.1 where nothing listens (a port bound, then freed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}{path}"
