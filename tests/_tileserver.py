"""A real HTTP tile server on loopback for the tests: generated PNG tiles, and faults on demand.

Each tile is a flat colour made from z/x/y (so a picture shows which tile it came from). Faults
are set per tile with ``server.faults[(z, x, y)] = [...]`` (consumed one per request) or for every
tile with ``server.default_fault``: "404", "500", "slow" (sleeps ``server.delay`` seconds),
"truncated" (promises more bytes than it sends), "truncated-png" (a whole answer holding half
a PNG), "garbage" (200 with a body that is no image), "trickle" (the headers at once, then the
body 64 bytes every ``server.delay`` seconds), "trickle-headers" (the headers themselves a line
every ``server.delay`` seconds), "bomb" (a valid PNG of 12000² pixels, ~20 KB).
Responses carry an ETag and Cache-Control: max-age=``server.max_age``; If-None-Match gets 304.
With ``server.dated`` they carry Last-Modified and Expires (``server.max_age`` from now) instead,
and If-Modified-Since gets 304.
"""

from __future__ import annotations

import hashlib
import io
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

__all__ = ["TileServer", "serve_tileset", "tile_colour"]


def tile_colour(z: int, x: int, y: int) -> tuple[int, int, int]:
    h = hashlib.sha1(f"{z}/{x}/{y}".encode()).digest()
    return h[0], h[1], h[2]


_BOMB: list[bytes] = []


def _bomb() -> bytes:
    """A whole PNG of 12000×12000 one-bit pixels: small on the wire, 576 MB as RGBA."""
    if not _BOMB:
        from PIL import Image

        buf = io.BytesIO()
        Image.new("1", (12000, 12000)).save(buf, format="PNG")
        _BOMB.append(buf.getvalue())
    return _BOMB[0]


def _png(colour: tuple[int, int, int], size: int = 256) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((size, size, 3), colour, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


class _QuietServer(ThreadingHTTPServer):
    """A client that hangs up mid-answer (a render that closed, a request past its deadline) is
    not the server's error: no traceback on stderr, where a later test's output would catch it."""

    def handle_error(self, request: object, client_address: object) -> None:
        import sys

        if isinstance(sys.exc_info()[1], ConnectionError):
            return
        super().handle_error(request, client_address)  # type: ignore[arg-type]


class TileServer:
    def __init__(self) -> None:
        self.faults: dict[tuple[int, int, int], list[str]] = {}
        self.default_fault: str | None = None
        self.delay = 0.5
        self.max_age = 3600
        self.dated = False
        self.requests: list[tuple[str, dict[str, str]]] = []
        self.lock = threading.Lock()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:  # keep test output quiet
                pass

            def do_GET(self) -> None:
                with server.lock:
                    server.requests.append((self.path, dict(self.headers)))
                m = re.fullmatch(r"/(?:[a-c]/)?(\d+)/(\d+)/(\d+)\.png", self.path)
                if m is None:
                    self.send_error(404)
                    return
                key = (int(m[1]), int(m[2]), int(m[3]))
                with server.lock:
                    queue = server.faults.get(key)
                    fault = queue.pop(0) if queue else server.default_fault
                if fault == "slow":
                    time.sleep(server.delay)
                if fault == "404":
                    self.send_error(404)
                    return
                if fault == "500":
                    self.send_error(500)
                    return
                body = _png(tile_colour(*key))
                etag = '"' + hashlib.sha1(body).hexdigest()[:16] + '"'
                if server.dated:
                    self._dated(body)
                    return
                if self.headers.get("If-None-Match") == etag:
                    self.send_response(304)
                    self.send_header("ETag", etag)
                    self.send_header("Cache-Control", f"max-age={server.max_age}")
                    self.end_headers()
                    return
                if fault == "garbage":
                    body = b"<html>this is not an image</html>"
                if fault == "bomb":
                    body = _bomb()
                if fault == "trickle-headers":
                    self.wfile.write(b"HTTP/1.1 200 OK\r\n")
                    for i in range(1000):
                        time.sleep(server.delay)
                        try:
                            self.wfile.write(f"X-Slow-{i}: x\r\n".encode())
                            self.wfile.flush()
                        except OSError:
                            return
                    return
                if fault == "trickle":
                    self.send_response(200)
                    self.send_header("Content-Type", "image/png")
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    for i in range(0, len(body), 64):
                        try:
                            self.wfile.write(body[i : i + 64])
                            self.wfile.flush()
                        except OSError:
                            return
                        time.sleep(server.delay)
                    return
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("ETag", etag)
                self.send_header("Cache-Control", f"max-age={server.max_age}")
                if fault == "truncated-png":
                    # a whole HTTP answer whose PNG stops half way
                    body = body[: len(body) // 2]
                if fault == "truncated":
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    self.wfile.write(body[: len(body) // 2])
                    self.close_connection = True
                    return
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def _dated(self, body: bytes) -> None:
                """Validators by date: Last-Modified (a fixed day) and Expires."""
                from email.utils import formatdate

                modified = "Mon, 02 Nov 2026 10:00:00 GMT"
                expires = formatdate(time.time() + server.max_age, usegmt=True)
                if self.headers.get("If-Modified-Since") == modified:
                    self.send_response(304)
                    self.send_header("Expires", expires)
                    self.end_headers()
                    return
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Last-Modified", modified)
                self.send_header("Expires", expires)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.httpd = _QuietServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    @property
    def template(self) -> str:
        return f"http://127.0.0.1:{self.port}/{{z}}/{{x}}/{{y}}.png"

    def count(self, z: int, x: int, y: int) -> int:
        with self.lock:
            return sum(1 for p, _ in self.requests if p.endswith(f"/{z}/{x}/{y}.png"))

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@contextmanager
def serve_tileset(site: Path) -> Iterator[str]:
    """``lodscape serve``'s app over ``site`` on a free loopback port, on its own thread: its
    base URL while the block runs."""
    import asyncio
    import socket

    from aiohttp import web

    from lodscape.serve import TileService, make_app

    service = TileService(site)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    loop = asyncio.new_event_loop()
    runner = web.AppRunner(make_app(service))
    ready = threading.Event()

    def serve() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(runner.setup())
        loop.run_until_complete(web.TCPSite(runner, "127.0.0.1", port).start())
        ready.set()
        loop.run_forever()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    assert ready.wait(30)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        asyncio.run_coroutine_threadsafe(runner.cleanup(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(30)
        loop.close()
        service.close()
