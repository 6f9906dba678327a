"""Every shell block of the README and docs/usage.md runs as written, in a folder that holds the
files they name (made from the bundled sample), with small pictures and short flights
substituted for speed, and the documentation hosts (``*.example.org``) served on loopback."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from _synthetic import fbm_heights, helsinki_tileset, write_dem
from lodscape.data import sample_city_path, sample_dem_path

pytestmark = pytest.mark.gl

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "docs" / "usage.md"]
SIZE = "128x96"
DURATION = "0.4"
#: Commands that draw a picture, a flight or a window: their size is made small.
DRAWING = ("render", "fly", "globe", "demo", "view")


def _blocks(path: Path) -> list[tuple[int, str]]:
    """(line, text) of each ```sh block of ``path``."""
    text = path.read_text()
    out = []
    for m in re.finditer(r"^```sh\n(.*?)^```", text, re.S | re.M):
        out.append((text[: m.start()].count("\n") + 1, m.group(1)))
    return out


BLOCKS = [(p, line, body) for p in DOCS for line, body in _blocks(p)]


def _terrarium_png(height: float, encoding: str) -> bytes:
    from PIL import Image

    if encoding == "terrarium":
        v = height + 32768.0
        rgb = (int(v // 256), int(v % 256), int((v % 1) * 256))
    else:  # Mapbox Terrain-RGB
        v = round((height + 10000.0) * 10.0)
        rgb = (v >> 16 & 255, v >> 8 & 255, v & 255)
    buf = io.BytesIO()
    Image.new("RGB", (256, 256), rgb).save(buf, "PNG")
    return buf.getvalue()


@pytest.fixture(scope="module")
def hosts() -> Iterator[str]:
    """The documentation's tile hosts on loopback: imagery tiles anywhere, and height tiles
    (a plain at 500 m) under ``terrarium/`` and ``rgb/``."""
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGB", (256, 256), (90, 130, 80)).save(buf, "PNG")
    colour = buf.getvalue()
    heights = {k: _terrarium_png(500.0, k) for k in ("terrarium", "rgb")}

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

        def do_GET(self) -> None:
            if not re.search(r"/\d+/\d+/\d+\.png$", self.path):
                self.send_error(404)
                return
            kind = (
                "terrarium" if "/terrarium/" in self.path else "rgb" if "/rgb/" in self.path else ""
            )
            body = heights[kind] if kind else colour
            self.send_response(200)
            self.send_header("Content-Type", "image/png")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def _run(argv: list[str], cwd: Path) -> None:
    subprocess.run([sys.executable, "-m", "lodscape.cli", *argv], cwd=cwd, check=True,
                   capture_output=True, timeout=600)  # fmt: skip


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The files the documentation names, made from the bundled sample."""
    d = tmp_path_factory.mktemp("docs")
    shutil.copy(sample_dem_path(), d / "DEM.tif")
    shutil.copy(sample_city_path(), d / "city.osm.pbf")
    _run(["build", "DEM.tif", "-o", "site.lods", "-q"], d)
    (d / "helsinki").mkdir()
    shutil.copy(helsinki_tileset(d / "helsinki"), d / "helsinki.lods")
    for name in ("imagery.mbtiles", "osm.mbtiles"):  # a tileset is an MBTiles file of imagery
        shutil.copy(d / "site.lods", d / name)
    cam = {"lon": -84.25, "lat": 36.5, "alt": 2500.0, "heading": 10.0, "pitch": -25.0}
    (d / "cam.json").write_text(json.dumps({**cam, "roll": 0.0, "fov_y": 60.0}))
    (d / "route.csv").write_text("lon,lat,alt\n-84.3,36.5,2500\n-84.25,36.55,2400\n")
    (d / "route.geojson").write_text(json.dumps({
        "type": "LineString", "coordinates": [[-84.3, 36.5, 2500], [-84.25, 36.55, 2400]],
    }))  # fmt: skip
    (d / "descent.csv").write_text(
        "lon,lat,alt,time,pitch\n-84.25,34.5,600000,0,-90\n-84.25,35.9,20000,6,-45\n"
        "-84.25,36.36,1400,10,-10\n"
    )
    (d / "poses.csv").write_text("lon,lat,alt,heading,pitch\n-84.25,36.5,2500,10,-25\n")
    # a two-band stack, a DEM in US survey feet, points, an orthophoto over the sample
    h = fbm_heights(65, seed=2).astype(np.float32)
    profile = {
        "driver": "GTiff",
        "width": 65,
        "height": 65,
        "count": 2,
        "dtype": "float32",
        "crs": "EPSG:32616",
        "transform": Affine(30.0, 0, 750000.0, 0, -30.0, 4050000.0),
    }
    with rasterio.open(d / "stack.tif", "w", **profile) as dst:
        dst.write(np.stack([h * 0.0 + 1.0, h]))
    write_dem(str(d / "texas.tif"), h * 3.28, crs="EPSG:2277", west=2_300_000.0,
              north=10_100_000.0, res=100.0)  # fmt: skip
    rng = np.random.default_rng(1)
    x, y = rng.uniform(700000, 703000, 400), rng.uniform(4040000, 4043000, 400)
    (d / "survey.csv").write_text(
        "x,y,z\n"
        + "".join(
            f"{a:.1f},{b:.1f},{300 + (a - 700000) / 30:.1f}\n" for a, b in zip(x, y, strict=True)
        )
    )
    rgb = rng.integers(0, 255, (3, 200, 200), dtype=np.uint8)
    with rasterio.open(
        d / "ortho.tif", "w", driver="GTiff", width=200, height=200, count=3, dtype="uint8",
        crs="EPSG:4326", transform=Affine(0.001, 0, -84.35, 0, -0.001, 36.6),
    ) as dst:  # fmt: skip
        dst.write(rgb)
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _script(body: str, hosts: str, port: int) -> str:
    """The block as a bash script: hosts on loopback, small pictures, short flights."""
    body = body.replace("\\\n", " ")
    body = re.sub(r"https://(\{s\}\.)?[a-z.]*example\.org", hosts, body)
    body = body.replace("8000", str(port))
    out = ["set -euo pipefail"]
    for raw in body.splitlines():
        line = raw.split("  #")[0].rstrip() if not raw.lstrip().startswith("#") else ""
        if not line.strip():
            continue
        if line.startswith(("sudo ", "python3 -m venv")):
            continue  # the machine's own setup: what this test runs on has it
        if line.startswith("pip install"):
            # the package is installed; a command after it still runs
            line = line.partition("&&")[2].strip()
            if not line or line.startswith("python -m pytest"):
                continue
        words = line.split()
        cmd = words[1] if words[:1] == ["lodscape"] and len(words) > 1 else ""
        if cmd in DRAWING:
            if "--size" in line:
                line = re.sub(r"--size \d+x\d+", f"--size {SIZE}", line)
            elif "--poses" not in line:
                line = line.replace(f"lodscape {cmd}", f"lodscape {cmd} --size {SIZE}", 1)
        if cmd == "fly":
            if "--duration" in line:
                line = re.sub(r"--duration [\d.]+", f"--duration {DURATION}", line)
            else:
                line = line.replace("lodscape fly", f"lodscape fly --duration {DURATION}", 1)
        if cmd == "view":
            line = line.replace("lodscape view", "lodscape view --exit-after 1", 1)
            if not os.environ.get("DISPLAY"):
                line = "xvfb-run -a " + line
        if cmd == "serve" and "&" not in line:
            # in the foreground it serves until stopped: it must still be serving after 5 s
            line = f"{{ timeout 5 {line} || [ $? -eq 124 ]; }}"
        out.append(line)
    return "\n".join(out) + "\n"


@pytest.mark.parametrize(
    ("doc", "line", "body"), BLOCKS, ids=[f"{p.name}:{line}" for p, line, _ in BLOCKS]
)
def test_the_documentation_runs_as_written(
    doc: Path, line: int, body: str, folder: Path, hosts: str, tmp_path: Path
) -> None:
    script = _script(body, hosts, _free_port())
    if "xvfb-run" in script and shutil.which("xvfb-run") is None:
        pytest.skip("a window needs a display or xvfb-run")
    # the block's own folder: the files it reads, and none of those it writes (-o)
    here = tmp_path / "here"
    shutil.copytree(folder, here)
    for out in re.findall(r"(?:-o|--output) (\S+)", script):
        target = here / out
        if target.is_dir():
            shutil.rmtree(target)
        else:
            target.unlink(missing_ok=True)
    folder = here
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    env["LODSCAPE_CACHE"] = str(folder / "cache")
    run = subprocess.run(
        ["bash", "-c", script], cwd=folder, env=env, capture_output=True, text=True, timeout=900
    )
    assert run.returncode == 0, (
        f"{doc.name}:{line}\n{script}\n{run.stdout[-2000:]}\n{run.stderr[-4000:]}"
    )


def test_every_block_is_seen() -> None:
    """The shell blocks are what this runs: a block fenced another way would be skipped."""
    for doc in DOCS:
        fenced = re.findall(r"^```(\w*)\n(?:lodscape|pip|mkdir|cp) ", doc.read_text(), re.M)
        assert all(kind == "sh" for kind in fenced), (doc, fenced)
