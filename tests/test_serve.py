"""``lodscape serve`` on loopback: every route, its headers (CORS, ETag, gzip, content types),
404 for absent tiles, hostile paths that never reach outside the tileset, and a bounded load."""

from __future__ import annotations

import asyncio
import gzip
import json
import socket
import sqlite3
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from _synthetic import helsinki_tileset
from lodscape.cli import main
from lodscape.data import sample_city_path
from lodscape.serve import TileService, make_app
from lodscape.store.quantized_mesh import decode


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = helsinki_tileset(tmp_path_factory.mktemp("serve"))
    main(["city", "add", str(out), str(sample_city_path())])
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def server(site: Path) -> Iterator[str]:
    from aiohttp import web

    service = TileService(site)
    port = _free_port()
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
    yield f"http://127.0.0.1:{port}"
    asyncio.run_coroutine_threadsafe(runner.cleanup(), loop).result(30)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(30)
    loop.close()
    service.close()


def _some_tile(site: Path, table: str) -> tuple[int, int, int]:
    import sqlite3

    with sqlite3.connect(site) as db:
        if table == "terrain":
            z, x, y = db.execute("SELECT z, x, y FROM terrain ORDER BY z DESC LIMIT 1").fetchone()
            return int(z), int(x), (1 << int(z)) - 1 - int(y)  # TMS row
        z, x, row = db.execute(
            "SELECT zoom_level, tile_column, tile_row FROM tiles ORDER BY zoom_level DESC LIMIT 1"
        ).fetchone()
        return int(z), int(x), (1 << int(z)) - 1 - int(row)  # OSM row


def test_layer_json_headers_etag_and_gzip(server: str) -> None:
    with httpx.Client(base_url=server) as c:
        r = c.get("/layer.json")
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("application/json")
        assert r.headers["access-control-allow-origin"] == "*"
        layer = r.json()
        assert layer["format"] == "quantized-mesh-1.0"
        assert layer["scheme"] == "tms"
        assert r.headers["content-encoding"] == "gzip"  # httpx asks for it and unpacks it
        etag = r.headers["etag"]
        again = c.get("/layer.json", headers={"If-None-Match": etag})
        assert again.status_code == 304
        assert again.headers["access-control-allow-origin"] == "*"
        plain = c.get("/layer.json", headers={"Accept-Encoding": "identity"})
        assert "content-encoding" not in plain.headers
        assert plain.json() == layer
        pre = c.options("/layer.json", headers={"Origin": "http://example.org"})
        assert pre.status_code == 204
        assert "GET" in pre.headers["access-control-allow-methods"]
        index = c.get("/").json()
        assert index["buildings"] == "3dtiles/tileset.json"


def test_terrain_tiles_plain_and_gzipped(server: str, site: Path) -> None:
    z, x, y = _some_tile(site, "terrain")
    with httpx.Client(base_url=server) as c:
        r = c.get(f"/{z}/{x}/{y}.terrain")
        assert r.status_code == 200
        assert r.headers["content-type"] == "application/vnd.quantized-mesh"
        assert r.headers["content-encoding"] == "gzip"
        qm = decode(gzip.compress(r.content))  # decode takes the stored (gzipped) form
        assert len(qm.triangles) > 0
        raw = c.get(f"/{z}/{x}/{y}.terrain", headers={"Accept-Encoding": "identity"})
        assert "content-encoding" not in raw.headers
        assert raw.content == r.content
        # the layer's level 0 exists (a flat tile above the roots), a tile far away does not
        assert c.get("/0/0/0.terrain").status_code == 200
        missing = c.get(f"/{z}/{(x + 7) % (1 << z)}/{y}.terrain")
        assert missing.status_code == 404
        assert missing.headers["access-control-allow-origin"] == "*"


def test_imagery_tiles(server: str, site: Path) -> None:
    from io import BytesIO

    from PIL import Image

    z, x, y = _some_tile(site, "tiles")
    with httpx.Client(base_url=server) as c:
        r = c.get(f"/imagery/{z}/{x}/{y}.png")
        assert r.status_code == 200
        assert r.headers["content-type"] == "image/png"
        assert Image.open(BytesIO(r.content)).size == (256, 256)
        assert c.get(f"/imagery/{z}/{x}/{(y + 9) % (1 << z)}.png").status_code == 404


def test_imagery_tilejson(server: str, site: Path) -> None:
    with httpx.Client(base_url=server) as c:
        tj = c.get("/imagery.json").json()
        assert tj["tilejson"] == "3.0.0"
        with closing(sqlite3.connect(site)) as db:
            lo, hi = db.execute("SELECT MIN(zoom_level), MAX(zoom_level) FROM tiles").fetchone()
        assert (tj["minzoom"], tj["maxzoom"]) == (lo, hi)
        assert tj["attribution"]
        z, x, y = _some_tile(site, "tiles")
        url = tj["tiles"][0].format(z=z, x=x, y=y)
        assert url.startswith(server)
        assert c.get(url).status_code == 200
        assert c.get("/").json()["imagery_tilejson"] == "imagery.json"


def test_export_writes_the_stored_city_as_3d_tiles(site: Path, tmp_path: Path) -> None:
    from lodscape.store.export import export_cesium

    export_cesium(site, tmp_path / "out")
    tileset = json.loads((tmp_path / "out" / "3dtiles" / "tileset.json").read_text())
    uris = []

    def walk(tile: dict[str, Any]) -> None:
        if "content" in tile:
            uris.append(tile["content"]["uri"])
        for child in tile.get("children", []):
            walk(child)

    walk(tileset["root"])
    assert uris
    for uri in uris:
        assert (tmp_path / "out" / "3dtiles" / uri).read_bytes()[:4] == b"glTF"


def test_buildings_as_3d_tiles(server: str) -> None:
    with httpx.Client(base_url=server, timeout=120) as c:
        r = c.get("/3dtiles/tileset.json")
        assert r.status_code == 200
        ts = r.json()
        assert ts["asset"]["version"] == "1.1"
        root = ts["root"]
        assert len(root["transform"]) == 16
        # the transform puts the city near Helsinki on the ellipsoid
        origin = np.array(root["transform"][12:15])
        assert 6.3e6 < np.linalg.norm(origin) < 6.4e6
        # every tile, depth first: groups of box models refined to the full buildings
        tiles, stack = [], [(root, None)]
        while stack:
            tile, parent = stack.pop()
            tiles.append((tile, parent))
            stack += [(child, tile) for child in tile.get("children", [])]
        uris = sorted(int(t["content"]["uri"][:-4]) for t, _ in tiles if "content" in t)
        assert uris
        assert uris == list(range(len(uris)))
        triangles = {0.0: 0, 1.0: 0}  # full (leaves, geometric error 0), boxes
        for tile, parent in tiles:
            if parent is not None:
                assert tile["geometricError"] <= parent["geometricError"]
            if "content" not in tile:
                continue
            assert tile["geometricError"] == 0.0 or tile["refine"] == "REPLACE"
            g = c.get(f"/3dtiles/{tile['content']['uri']}")
            assert g.status_code == 200
            assert g.headers["content-type"] == "model/gltf-binary"
            data = g.content
            magic, version, total = struct.unpack("<4sII", data[:12])
            assert (magic, version, total) == (b"glTF", 2, len(data))
            jlen, jtype = struct.unpack("<I4s", data[12:20])
            assert jtype == b"JSON"
            doc = json.loads(data[20 : 20 + jlen])
            blen, btype = struct.unpack("<I4s", data[20 + jlen : 28 + jlen])
            assert btype == b"BIN\x00"
            assert blen == doc["buffers"][0]["byteLength"]
            for prim in doc["meshes"][0]["primitives"]:
                idx = doc["accessors"][prim["indices"]]
                pos = doc["accessors"][prim["attributes"]["POSITION"]]
                view = doc["bufferViews"][idx["bufferView"]]
                start = 28 + jlen + view["byteOffset"]
                ind = np.frombuffer(data[start : start + view["byteLength"]], np.uint32)
                assert ind.max() < pos["count"]
                triangles[float(tile["geometricError"] > 0)] += len(ind) // 3
        assert triangles[0.0] > 1000
        # the boxes stand in for the buildings with far fewer triangles
        assert 0 < triangles[1.0] < triangles[0.0] / 2
        children = uris
        assert c.get(f"/3dtiles/{len(children)}.glb").status_code == 404


HOSTILE = [
    "/../../etc/passwd",
    "/%2e%2e/%2e%2e/etc/passwd",
    "/imagery/..%2F..%2Fsite.lods",
    "/imagery/%2e%2e/%2e%2e/site.lods",
    "/3dtiles/../../site.lods",
    "/3dtiles/..%2fsite.lods",
    "/site.lods",
    "/3/0/0.terrain/../../../site.lods",
    "/99999999999/0/0.terrain",
    "/99/0/0.terrain",
    "/3/-1/0.terrain",
    "/3/0/99999999999999999999999.terrain",
    "/3/8/0.terrain",
    "/imagery/40/0/0.png",
    "/imagery/3/0/0.png%00.txt",
    "/3dtiles/-1.glb",
    "/3dtiles/99999999999.glb",
    "/layer.json%2F..",
    "/" + "a" * 5000,
    "/%ff%fe/0/0.terrain",
]


@pytest.mark.parametrize("path", HOSTILE)
def test_hostile_paths_never_leave_the_tileset(server: str, site: Path, path: str) -> None:
    secret = site.read_bytes()[:16]
    with httpx.Client(base_url=server) as c:
        r = c.get(httpx.URL(server + path) if "%" in path else path)
        assert r.status_code in (400, 404, 414), (path, r.status_code)
        assert secret not in r.content
        assert b"root:" not in r.content


def test_a_bounded_load_has_no_errors(server: str, site: Path) -> None:
    z, x, y = _some_tile(site, "terrain")
    paths = ["/layer.json", f"/{z}/{x}/{y}.terrain", "/0/0/0.terrain", "/3dtiles/tileset.json"]

    async def load() -> tuple[int, int, float]:
        ok = bad = 0
        t = time.perf_counter()
        async with httpx.AsyncClient(base_url=server) as c:
            sem = asyncio.Semaphore(16)

            async def one(i: int) -> None:
                nonlocal ok, bad
                async with sem:
                    r = await c.get(paths[i % len(paths)])
                    if r.status_code == 200:
                        ok += 1
                    else:
                        bad += 1

            await asyncio.gather(*(one(i) for i in range(400)))
        return ok, bad, time.perf_counter() - t

    ok, bad, _ = asyncio.run(load())
    assert (ok, bad) == (400, 0)


def test_cli_refuses_what_is_not_a_tileset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from _synthetic import run_cli

    junk = tmp_path / "junk.lods"
    junk.write_bytes(b"junk")
    code, _, err = run_cli(["serve", str(junk), "--port", "8765"], capsys)
    assert code == 2
    assert err.count("\n") == 1
    code, _, err = run_cli(["serve", str(tmp_path / "none.lods")], capsys)
    assert code == 2
    assert "no such file" in err
