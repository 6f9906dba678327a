"""A cloud-optimised GeoTIFF over HTTP (issue 36): opened through GDAL's /vsicurl/ with range
requests from a real loopback server, its first picture made from a small part of the file."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from _synthetic import periodic_fbm


class _Ranges:
    """A loopback HTTP server of one file that answers byte ranges, counting what it sends."""

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

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}/{path.name}"

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture(scope="module")
def cog(tmp_path_factory: pytest.TempPathFactory) -> Iterator[_Ranges]:
    import rasterio
    from rasterio.transform import Affine

    folder = tmp_path_factory.mktemp("cog")
    h = periodic_fbm(4096, seed=8, relief=600.0)
    path = folder / "dem.tif"
    profile = {
        "driver": "COG",
        "width": h.shape[1],
        "height": h.shape[0],
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:32617",
        "transform": Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 4000000.0),
        "compress": "deflate",
        "blocksize": 256,
        "overview_resampling": "average",
    }
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(h, 1)
    server = _Ranges(path)
    yield server
    server.close()


@pytest.mark.parametrize("prefix", ["", "/vsicurl/"])
def test_a_remote_cog_renders_from_a_small_part_of_it(
    cog: _Ranges, tmp_path: Path, prefix: str
) -> None:
    cog.sent = 0
    out = tmp_path / "remote.png"
    env = {**os.environ, "LODSCAPE_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape", "render", prefix + cog.url, "--size", "480x270",
         "-o", str(out), "-q"],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    share = cog.sent / len(cog.data)
    assert share < 0.25, f"fetched {100 * share:.1f} % of the file"
    from PIL import Image

    rgb = np.asarray(Image.open(out).convert("RGB"))
    assert (rgb.std(axis=(0, 1)) > 5).all()  # a picture, not a blank


def test_a_remote_file_that_is_not_there_is_one_line(cog: _Ranges, tmp_path: Path) -> None:
    url = cog.url.rsplit("/", 1)[0] + "/missing.tif"
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape", "render", url, "-o", str(tmp_path / "x.png"), "-q"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "missing.tif" in lines[0]
