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

__all__ = [
    "TERRAIN_BOX",
    "TerrainServer",
    "TileServer",
    "geographic_terrain_tile",
    "serve_tileset",
    "terrain_height",
    "tile_colour",
]


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
def serve_tileset(
    site: Path, header_timeout: float = 10.0, tiling: str = "geographic"
) -> Iterator[str]:
    """``lodscape serve`` over ``site`` (its app, connections and file watch) on a free loopback
    port, on its own thread: its base URL while the block runs."""
    import asyncio
    import socket

    from lodscape.serve import TileService, serve

    service = TileService(site, tiling)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    loop = asyncio.new_event_loop()
    stop = asyncio.Event()
    ready = threading.Event()

    def run() -> None:
        asyncio.set_event_loop(loop)
        loop.run_until_complete(
            serve(
                service,
                "127.0.0.1",
                port,
                ready=lambda url: ready.set(),
                stop=stop,
                header_timeout=header_timeout,
            )
        )

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert ready.wait(30)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        loop.call_soon_threadsafe(stop.set)
        thread.join(30)
        loop.close()
        service.close()


# --- a quantized-mesh terrain server (EPSG:4326, as Cesium's), with faults ----------------------

#: Where the terrain server's tiles have data: west, south, east, north.
TERRAIN_BOX = (7.9, 45.95, 8.1, 46.05)


def terrain_height(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """The analytic terrain the servers encode: a tilted sine, metres."""
    return (
        300.0
        + 150.0 * np.sin((lon - 8.0) * 40.0) * np.cos((lat - 46.0) * 30.0)
        + 2000.0 * (lat - 46.0)
    )


def geographic_terrain_tile(z: int, x: int, tms: int) -> bytes | None:
    """Tile z/x/tms of the geographic tiling (two root tiles): a 17² grid of the analytic
    heights over the tile, where it meets ``TERRAIN_BOX``."""
    from lodscape.store.quantized_mesh import encode
    from lodscape.terrain.mesh import grid_indices

    span = 180.0 / (1 << z)
    w, s = -180.0 + x * span, -90.0 + tms * span
    e, n = w + span, s + span
    bw, bs, be, bn = TERRAIN_BOX
    if e < bw or w > be or n < bs or s > bn:
        return None
    g = 16
    lon, lat = np.meshgrid(np.linspace(w, e, g + 1), np.linspace(n, s, g + 1))
    tris = grid_indices(g)[: 2 * g * g].astype(np.int64)
    return encode(lon.ravel(), lat.ravel(), terrain_height(lon, lat).ravel(), tris, (w, s, e, n))


class TerrainServer:
    """A Cesium-style ``layer.json`` and its quantized-mesh tiles on loopback. ``fault`` is done
    to every tile of level ``from_z`` and deeper: "hang" (no answer), "trickle" (the body 16
    bytes a second), "500", "garbage", "bomb" (a PNG bomb), "truncated" (half the promised
    body); "root-down" answers 500 to the root tiles for ``down_s`` seconds after the first
    request for one. ``url`` is the layer's."""

    def __init__(
        self,
        fault: str | None = None,
        from_z: int = 4,
        maxzoom: int = 11,
        down_s: float = 2.0,
        shallow: tuple[float, int] | None = None,
        available: list[list[dict[str, int]]] | None = None,
    ) -> None:
        """``shallow`` (latitude, level z): the pyramid stops at level z under the level-z+1
        tiles whose north edge is at or south of that latitude (their descendants are 404s, as
        real servers' over the sea); ``available``: the layer's list of the tiles it has."""
        import json

        self.fault, self.from_z, self.down_s = fault, from_z, down_s
        self.first_root: float | None = None
        self.requests = 0
        layer = {
            "tilejson": "2.1.0",
            "format": "quantized-mesh-1.0",
            "version": "1.0.0",
            "scheme": "tms",
            "projection": "EPSG:4326",
            "tiles": ["tiles/{z}/{x}/{y}.terrain"],
            "maxzoom": maxzoom,
            "bounds": list(TERRAIN_BOX),
        }
        if available is not None:
            layer["available"] = available
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def do_GET(self) -> None:
                server.requests += 1
                path = self.path.split("?")[0]
                if path.endswith(("/layer.json", "/metadata")):  # a layer by another name
                    self._send(json.dumps(layer).encode())
                    return
                parts = path.split("/")
                z, x, y = int(parts[-3]), int(parts[-2]), int(parts[-1].split(".")[0])
                body = geographic_terrain_tile(z, x, y) if z <= maxzoom else None
                if shallow is not None and z > shallow[1]:
                    top = shallow[1] + 1
                    north = -90.0 + ((y >> (z - top)) + 1) * 180.0 / (1 << top)
                    if north <= shallow[0]:
                        body = None
                fault = server.fault if z >= server.from_z else None
                if server.fault == "root-down" and z == 0:
                    now = time.monotonic()
                    if server.first_root is None:
                        server.first_root = now
                    fault = "500" if now - server.first_root < server.down_s else None
                if body is None:
                    self.send_error(404)
                    return
                if fault == "hang":
                    time.sleep(60)
                    return
                if fault == "500":
                    self.send_error(500)
                    return
                if fault == "garbage":
                    body = b"<html>this is not a terrain tile</html>"
                if fault == "bomb":
                    body = _bomb()
                if fault in ("trickle", "truncated"):
                    self.send_response(200)
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    if fault == "truncated":
                        self.wfile.write(body[: len(body) // 2])
                        self.close_connection = True
                        return
                    for i in range(0, len(body), 16):
                        try:
                            self.wfile.write(body[i : i + 16])
                            self.wfile.flush()
                        except OSError:
                            return
                        time.sleep(1.0)
                    return
                self._send(body)

            def _send(self, body: bytes) -> None:
                self.send_response(200)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.httpd = _QuietServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/terrain/layer.json"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


class RangeServer:
    """One file on loopback answering HTTP byte ranges, as a cloud bucket does for a COG (what
    GDAL's /vsicurl/ reads), counting the requests and the bytes it sends. ``url`` is the
    file's; any other path is a 404."""

    def __init__(self, path: Path) -> None:
        self.data = path.read_bytes()
        self.sent = 0
        self.requests = 0
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def _missing(self) -> bool:
                if self.path.lstrip("/") == path.name:
                    return False
                self.send_response(404)
                self.send_header("Content-Length", "0")
                self.end_headers()
                return True

            def do_HEAD(self) -> None:
                if self._missing():
                    return
                self.send_response(200)
                self.send_header("Content-Length", str(len(owner.data)))
                self.send_header("Accept-Ranges", "bytes")
                self.end_headers()

            def do_GET(self) -> None:
                if self._missing():
                    return
                owner.requests += 1
                m = re.match(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
                a = 0
                if m is None:
                    body, code = owner.data, 200
                else:
                    a = int(m.group(1))
                    b = int(m.group(2)) if m.group(2) else len(owner.data) - 1
                    body, code = owner.data[a : b + 1], 206
                self.send_response(code)
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Accept-Ranges", "bytes")
                if code == 206:
                    self.send_header(
                        "Content-Range", f"bytes {a}-{a + len(body) - 1}/{len(owner.data)}"
                    )
                self.end_headers()
                self.wfile.write(body)
                owner.sent += len(body)

        self.httpd = _QuietServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/{path.name}"

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
