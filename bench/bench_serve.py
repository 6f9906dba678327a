"""``lodscape serve`` under load on loopback: requests per second and errors.

    python bench/bench_serve.py [--requests 20000] [--concurrency 64] [--connections 64 500]

A tileset built from a 1025² fBm DEM (10 m, UTM 17N), served by ``lodscape serve`` in its own
process; a Python client (httpx, asyncio) in this process asks for a mix of routes: terrain
tiles of every level (gzipped, as Cesium asks), imagery tiles, layer.json and absent tiles
(404). Reported:
requests/s, errors (anything but the expected status), and latency percentiles. Where wrk is
installed (Debian: wrk), the same server under wrk over the routes that exist, once per
``--connections`` count (the goal: p99 under 1 s at 500 connections).
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import fbm_heights, write_dem
from lodscape.cli import main as cli


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--requests", type=int, default=20000)
    ap.add_argument("--concurrency", type=int, default=64)
    ap.add_argument("--connections", type=int, nargs="+", default=[64, 500])
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        dem = write_dem(
            str(Path(tmp) / "dem.tif"),
            fbm_heights(1025),
            crs="EPSG:32617",
            west=700000.0,
            north=4060000.0,
            res=10.0,
        )
        site = Path(tmp) / "site.lods"
        cli(["build", dem, "-o", str(site), "-q"])
        with sqlite3.connect(site) as db:
            terrain = [
                f"/{z}/{x}/{(1 << z) - 1 - y}.terrain"
                for z, x, y in db.execute("SELECT z, x, y FROM terrain")
            ]
            imagery = [
                f"/imagery/{z}/{x}/{(1 << z) - 1 - r}.png"
                for z, x, r in db.execute("SELECT zoom_level, tile_column, tile_row FROM tiles")
            ]
        routes = [(p, 200) for p in terrain] + [(p, 200) for p in imagery[:50]]
        routes += [("/layer.json", 200), ("/5/0/0.terrain", 404), ("/imagery/3/0/0.png", 404)]
        port = _port()
        server = subprocess.Popen(
            # the stored tiles as they are (the default geographic tiling makes each tile on
            # its first request, then keeps it)
            [
                sys.executable,
                "-m",
                "lodscape.cli",
                "serve",
                str(site),
                "--port",
                str(port),
                "--tiling",
                "mercator",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            base = f"http://127.0.0.1:{port}"
            deadline = time.monotonic() + 30
            while True:
                try:
                    httpx.get(base + "/layer.json", timeout=1)
                    break
                except httpx.TransportError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.2)
            ok, errors, latency, seconds = asyncio.run(
                _load(base, routes, args.requests, args.concurrency)
            )
            if shutil.which("wrk"):
                for n in args.connections:
                    print(_wrk(base, [p for p, want in routes if want == 200], Path(tmp), n))
        finally:
            server.terminate()
            server.wait(10)
    lat = sorted(latency)
    print(
        f"{args.requests:,} requests, {args.concurrency} at a time, over {len(routes)} routes "
        f"({len(terrain)} terrain tiles): {args.requests / seconds:,.0f} requests/s, "
        f"{errors} errors; latency median {statistics.median(lat) * 1e3:.1f} ms, "
        f"p99 {lat[int(0.99 * (len(lat) - 1))] * 1e3:.1f} ms"
    )
    assert ok + errors == args.requests


def _wrk(base: str, paths: list[str], tmp: Path, connections: int) -> str:
    """The same server under wrk (2 threads, ``connections`` connections, 10 s) over the routes
    that exist, gzip accepted: what the server does when the client is not Python."""
    script = tmp / "routes.lua"
    listed = ",".join(f'"{p}"' for p in paths)
    script.write_text(
        f"paths = {{{listed}}}\ni = 0\nrequest = function()\n  i = i + 1\n"
        '  return wrk.format("GET", paths[(i % #paths) + 1], {["Accept-Encoding"] = "gzip"})\n'
        "end\n"
    )
    argv = ["wrk", "-t2", f"-c{connections}", "-d10s", "--latency", "--timeout", "10s"]
    out = subprocess.run(
        [*argv, "-s", str(script), base],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    keep = [
        line.strip()
        for line in out.splitlines()
        if line.strip().startswith(("Requests/sec", "Non-2xx", "Socket errors", "50%", "99%"))
        or "requests in" in line
    ]
    return (
        f"wrk, {connections} connections: "
        + "; ".join(keep)
        + ("" if "Non-2xx" in out else "; 0 non-2xx")
    )


async def _load(
    base: str, routes: list[tuple[str, int]], n: int, concurrency: int
) -> tuple[int, int, list[float], float]:
    ok = errors = 0
    latency: list[float] = []
    limits = httpx.Limits(max_connections=concurrency, max_keepalive_connections=concurrency)
    async with httpx.AsyncClient(base_url=base, limits=limits, timeout=30) as c:
        queue: asyncio.Queue[int] = asyncio.Queue()
        for i in range(n):
            queue.put_nowait(i)

        async def worker() -> None:
            nonlocal ok, errors
            while not queue.empty():
                i = queue.get_nowait()
                path, want = routes[(i * 7919) % len(routes)]
                t = time.perf_counter()
                try:
                    r = await c.get(path)
                    good = r.status_code == want
                except httpx.HTTPError:
                    good = False
                latency.append(time.perf_counter() - t)
                ok, errors = (ok + 1, errors) if good else (ok, errors + 1)

        t0 = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(concurrency)))
        seconds = time.perf_counter() - t0
    return ok, errors, latency, seconds


if __name__ == "__main__":
    main()
