"""``lodscape serve`` on loopback: every route, its headers (CORS, ETag, gzip, content types),
404 for absent tiles, hostile paths that never reach outside the tileset, and a bounded load."""

from __future__ import annotations

import asyncio
import gzip
import json
import shutil
import socket
import sqlite3
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import closing
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from _synthetic import helsinki_tileset
from _tileserver import serve_tileset
from lodscape.cli import main
from lodscape.data import sample_city_path
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
    with serve_tileset(site) as url:
        yield url


def _some_tile(site: Path, table: str) -> tuple[int, int, int]:
    import sqlite3

    with sqlite3.connect(site) as db:
        if table == "terrain":
            # the finest geographic tile served (the default tiling): z, x, TMS row
            from lodscape.store.geographic import available_tiles

            available = available_tiles(db)
            z = max(available)
            x, tms = min(available[z])
            return z, x, tms
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
        index = c.get("/index.json").json()
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
        assert (tj["minzoom"], tj["maxzoom"]) == (0, hi)  # overviews above the stored levels
        assert lo > 0
        assert tj["attribution"]
        z, x, y = _some_tile(site, "tiles")
        url = tj["tiles"][0].format(z=z, x=x, y=y)
        assert url.startswith(server)
        assert c.get(url).status_code == 200
        assert c.get("/index.json").json()["imagery_tilejson"] == "imagery.json"


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


def test_city_add_stores_its_3d_tiles_and_serve_reads_them(
    site: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``city add`` makes the 3D Tiles in its transaction and keeps them in the file: a server
    answers its first request from them, making nothing (it took 77 s on a request before)."""
    import sqlite3

    from lodscape.serve import TileService
    from lodscape.store import city_tiles

    with sqlite3.connect(site) as db:
        names = {n for (n,) in db.execute("SELECT name FROM city_3dtiles")}
    assert {"tileset.json", "signature", "0.glb"} <= names

    def boom(*args: object) -> None:
        raise AssertionError("3D Tiles made on a request")

    monkeypatch.setattr(city_tiles, "make_city_tiles", boom)
    service = TileService(site)
    try:
        made = service.tiles3d()
        assert made is not None
        assert json.loads(made[0])["asset"]["version"] == "1.1"
        assert len(made[1]) == len(names) - 2
    finally:
        service.close()


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
        contents = 0
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
                # every vertex inside the tile's box (east-north-up; glTF is y-up)
                pview = doc["bufferViews"][pos["bufferView"]]
                at = 28 + jlen + pview["byteOffset"] + pos.get("byteOffset", 0)
                xyz = np.frombuffer(data[at : at + 12 * pos["count"]], np.float32).reshape(-1, 3)
                enu = np.column_stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]]).astype(np.float64)
                box = np.array(tile["boundingVolume"]["box"])
                half = np.array([box[3], box[7], box[11]])
                assert (np.abs(enu - box[:3]) <= half + 1e-3).all(), tile["content"]["uri"]
            contents += 1
        assert triangles[0.0] > 1000
        assert contents == len(uris)
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
    code, out, err = run_cli(["serve", str(junk), "--port", "8765"], capsys)
    assert code == 2
    assert err.count("\n") == 1
    assert "serving" not in out  # said only once it listens
    code, out, err = run_cli(["serve", str(tmp_path / "none.lods")], capsys)
    assert code == 2
    assert "no such file" in err
    assert "serving" not in out


def _digits(n: int, zero: int) -> str:
    """``n`` written with the digits of another script (``zero`` is its 0's code point)."""
    return "".join(chr(zero + int(d)) for d in str(n))


def test_a_tile_has_one_name(server: str, site: Path) -> None:
    """Only ASCII digits without leading zeros name a tile (fullwidth, Arabic-Indic and
    Devanagari digits, and 01126 for 1126, aliased real tiles)."""
    z, x, y = _some_tile(site, "terrain")
    with httpx.Client(base_url=server) as c:
        assert c.get(f"/{z}/{x}/{y}.terrain").status_code == 200
        for zero in (0xFF10, 0x0660, 0x0966):
            alias = httpx.URL(server + f"/{_digits(z, zero)}/{x}/{y}.terrain")
            assert c.get(alias).status_code == 404, hex(zero)
        assert c.get(f"/{z}/0{x}/{y}.terrain").status_code == 404
        assert c.get(f"/0{z}/{x}/{y}.terrain").status_code == 404
        assert c.get("/0/0/0.terrain").status_code == 200  # a lone 0 is a number


@pytest.mark.parametrize(
    ("accept", "gzipped"),
    [
        ("gzip", True),
        ("gzip;q=0.5, identity", True),
        ("*", True),
        ("gzip;q=0", False),
        ("gzip; q=0.000", False),
        ("nogzip", False),
        ("deflate, br", False),
        ("identity", False),
        ("*;q=0", False),
        ("x-gzip", True),
    ],
)
def test_accept_encoding_is_read_with_its_q_values(
    server: str, site: Path, accept: str, gzipped: bool
) -> None:
    z, x, y = _some_tile(site, "terrain")
    with httpx.Client(base_url=server) as c:
        for path in ("/layer.json", f"/{z}/{x}/{y}.terrain"):
            r = c.get(path, headers={"Accept-Encoding": accept})
            assert r.status_code == 200
            assert (r.headers.get("content-encoding") == "gzip") == gzipped, (path, accept)


def test_etags_name_the_bytes_sent_and_conditionals_are_honoured(server: str, site: Path) -> None:
    z, x, y = _some_tile(site, "terrain")
    with httpx.Client(base_url=server) as c:
        for path in ("/layer.json", f"/{z}/{x}/{y}.terrain"):
            gz = c.get(path, headers={"Accept-Encoding": "gzip"})
            plain = c.get(path, headers={"Accept-Encoding": "identity"})
            assert gz.headers["etag"] != plain.headers["etag"], path  # two bodies, two tags
            tag = gz.headers["etag"]
            for inm in (tag, f"W/{tag}", f'"other", {tag}', "*", f'W/"x", W/{tag}'):
                r = c.get(path, headers={"Accept-Encoding": "gzip", "If-None-Match": inm})
                assert r.status_code == 304, (path, inm)
                assert r.headers["vary"] == "Accept-Encoding"
                assert r.headers["etag"] == tag
            # the plain body's client holding the gzip body's tag gets the plain body
            r = c.get(path, headers={"Accept-Encoding": "identity", "If-None-Match": tag})
            assert r.status_code == 200
            assert r.content == plain.content
            r = c.get(path, headers={"Accept-Encoding": "gzip", "If-None-Match": '"other"'})
            assert r.status_code == 200


def test_preflight_only_for_routes_that_exist(server: str) -> None:
    with httpx.Client(base_url=server) as c:
        ok = c.options("/3/1/2.terrain", headers={"Origin": "http://example.org"})
        assert ok.status_code == 204
        assert ok.headers["access-control-allow-origin"] == "*"
        for path in ("/nothing", "/3/1/2.png", "/imagery/3/1/x.png", "/site.lods"):
            assert c.options(path).status_code == 404, path


def _city_add_paused(tileset: Path) -> subprocess.Popen[bytes]:
    """``city add`` stopped (SIGSTOP) in the middle of its transaction, its page cache made tiny
    so that its pages spill to the file (a big city's do): in rollback-journal mode that is an
    exclusive lock that every reader waits on."""
    code = (
        "import os, signal, sqlite3, sys, shapely\n"
        "from lodscape.cli import main\n"
        "connect = sqlite3.connect\n"
        "def small_cache(*a, **k):\n"
        "    db = connect(*a, **k)\n"
        "    db.execute('PRAGMA cache_size=1')\n"
        "    return db\n"
        "sqlite3.connect = small_cache\n"
        "real, calls = shapely.to_wkb, [0]\n"
        "def to_wkb(*a, **k):\n"
        "    calls[0] += 1\n"
        "    if calls[0] == 20:\n"
        "        sys.stdout.write('paused\\n'); sys.stdout.flush()\n"
        "        os.kill(os.getpid(), signal.SIGSTOP)\n"
        "    return real(*a, **k)\n"
        "shapely.to_wkb = to_wkb\n"
        "main(['city', 'add', sys.argv[1], sys.argv[2], '--name', 'second'])\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(tileset), str(sample_city_path())],
        stdout=subprocess.PIPE,
    )
    assert proc.stdout is not None
    assert proc.stdout.readline() == b"paused\n"
    return proc


def _serve_process(
    tileset: Path, port: int, flags: list[str] | None = None
) -> subprocess.Popen[str]:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "lodscape.cli",
            "serve",
            str(tileset),
            "--port",
            str(port),
            *(flags or []),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None
    line = proc.stdout.readline()
    assert line.startswith("serving "), (line, proc.stderr.read() if proc.poll() else "")
    return proc


def test_serve_as_a_process_never_waits_for_a_writer(site: Path, tmp_path: Path) -> None:
    """``lodscape serve`` on a real port while ``city add`` holds its write transaction open:
    every request answers at once (it waited 5 s, then 500 "database is locked", and even the
    in-memory layer.json queued behind); a malformed request logs one line, no traceback."""
    copy = tmp_path / "site.lods"
    shutil.copy(site, copy)
    port = _free_port()
    server = _serve_process(copy, port)
    writer = None
    try:
        base = f"http://127.0.0.1:{port}"
        z, x, y = _some_tile(copy, "terrain")
        with httpx.Client(base_url=base, timeout=5.0) as c:
            assert c.get(f"/{z}/{x}/{y}.terrain").status_code == 200
            writer = _city_add_paused(copy)
            for path in ("/layer.json", f"/{z}/{x}/{y}.terrain", "/imagery.json", "/index.json"):
                t = time.perf_counter()
                r = c.get(path)
                assert r.status_code == 200, (path, r.status_code)
                assert time.perf_counter() - t < 1.0, path
        with socket.create_connection(("127.0.0.1", port)) as raw:
            raw.sendall(b"GET /layer.json HTTP/1.1\r\nHost: x\r\nContent-Length: nope\r\n\r\n")
            assert b" 400 " in raw.recv(100).split(b"\r\n")[0]
    finally:
        if writer is not None:
            writer.kill()
            writer.communicate()
        server.terminate()
        _, err = server.communicate(timeout=30)
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err  # the malformed request, in one line
    assert lines[0].startswith("lodscape serve: "), err
    assert "Content-Length" in lines[0], err


def test_serve_says_serving_only_once_it_listens(
    site: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from _synthetic import run_cli

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code, out, err = run_cli(["serve", str(site), "--port", str(port)], capsys)
    assert code == 2
    assert "serving" not in out
    assert err.count("\n") == 1, err
    assert f"127.0.0.1:{port}" in err, err


def _wait_for(probe: Any, seconds: float = 10.0) -> Any:
    """``probe()`` until it is truthy (the server looks at its file twice a second)."""
    deadline = time.monotonic() + seconds
    got = probe()
    while not got and time.monotonic() < deadline:
        time.sleep(0.1)
        got = probe()
    return got


def test_a_file_renamed_into_place_and_a_city_added_are_served(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``lodscape build`` to a new name then ``mv`` over the served file (an atomic rename), and
    ``city add`` / ``remove`` on it: served from the next requests, no restart."""
    from _synthetic import fbm_tileset

    first = helsinki_tileset(tmp_path)
    (tmp_path / "other").mkdir()
    other = fbm_tileset(tmp_path / "other", seed=3, n=129)
    served = tmp_path / "served.lods"
    shutil.copy(first, served)
    with serve_tileset(served) as url, httpx.Client(base_url=url) as c:
        assert c.get("/3dtiles/tileset.json").status_code == 404  # no city yet
        z, x, y = _some_tile(other, "terrain")
        assert c.get(f"/{z}/{x}/{y}.terrain").status_code == 404
        bounds = c.get("/layer.json").json()["bounds"]
        tmp = tmp_path / "next.lods"
        shutil.copy(other, tmp)
        tmp.replace(served)  # the old inode stays open in the server until it looks again
        assert _wait_for(lambda: c.get(f"/{z}/{x}/{y}.terrain").status_code == 200)
        assert c.get("/layer.json").json()["bounds"] != bounds
        # the city: added, then removed, seen each time
        shutil.copy(first, tmp)
        tmp.replace(served)
        assert _wait_for(lambda: c.get(f"/{z}/{x}/{y}.terrain").status_code == 404)
        main(["city", "add", str(served), str(sample_city_path())])
        assert _wait_for(lambda: c.get("/3dtiles/tileset.json").status_code == 200)
        assert c.get("/index.json").json()["buildings"] == "3dtiles/tileset.json"
        main(["city", "remove", str(served), sample_city_path().name])
        assert _wait_for(lambda: c.get("/3dtiles/tileset.json").status_code == 404)


def test_a_file_being_written_over_keeps_the_last_tileset_served(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    site = helsinki_tileset(tmp_path)
    served = tmp_path / "served.lods"
    shutil.copy(site, served)
    z, x, y = _some_tile(site, "terrain")
    with serve_tileset(served) as url, httpx.Client(base_url=url) as c:
        broken = tmp_path / "broken.lods"
        broken.write_bytes(b"not a tileset at all")
        broken.replace(served)
        time.sleep(0.7)
        for _ in range(3):
            assert c.get(f"/{z}/{x}/{y}.terrain").status_code == 200
            time.sleep(0.6)
    err = capsys.readouterr().err
    assert err.count("still serving the last tileset") == 1, err


def test_half_sent_headers_are_cut_off(site: Path) -> None:
    """A client that opens connections and sends part of a request's headers (or nothing) is
    closed after the header deadline, and the server answers the others meanwhile."""
    with serve_tileset(site, header_timeout=1.0) as url:
        port = int(url.rsplit(":", 1)[1])
        held = []
        for i in range(20):
            s = socket.create_connection(("127.0.0.1", port))
            if i % 2:
                s.sendall(b"GET /layer.json HTTP/1.1\r\nHost: x\r\nX-Slow: ")
            held.append(s)
        with httpx.Client(base_url=url) as c:
            assert c.get("/layer.json").status_code == 200
        time.sleep(2.5)
        for s in held:
            s.settimeout(2.0)
            try:
                assert s.recv(1024) == b""  # closed by the server
            except ConnectionResetError:
                pass  # closed by the server (aborted)
            finally:
                s.close()
        with httpx.Client(base_url=url) as c:
            assert c.get("/layer.json").status_code == 200


def test_the_tilejson_names_the_url_clients_reach_behind_a_proxy(server: str, site: Path) -> None:
    """Behind an HTTPS proxy the TileJSON's tiles are the proxy's URL (X-Forwarded-Proto and
    -Host, the first of a list); a header that is not a scheme or a host is ignored; and
    ``--public-url`` overrides both."""
    from lodscape.serve import public_base

    with httpx.Client(base_url=server) as c:
        headers = {"X-Forwarded-Proto": "https, http", "X-Forwarded-Host": "tiles.example.org"}
        tj = c.get("/imagery.json", headers=headers).json()
        assert tj["tiles"][0] == "https://tiles.example.org/imagery/{z}/{x}/{y}.png"
        bad = {"X-Forwarded-Proto": "javascript", "X-Forwarded-Host": "a b/<script>"}
        tj = c.get("/imagery.json", headers=bad).json()
        assert tj["tiles"][0].startswith(server.rstrip("/") + "/imagery/")
    got = public_base("http", "127.0.0.1:8000", {"X-Forwarded-Host": "x.org"}, "https://a.b/t/")
    assert got == "https://a.b/t"
    assert public_base("http", "h:1", {"X-Forwarded-Host": "[::1]:8080"}) == "http://[::1]:8080"


def test_serve_refuses_a_public_url_that_is_not_one(
    site: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main(["serve", str(site), "--public-url", "tiles.example.org"])
    assert info.value.code == 2
    assert "--public-url" in capsys.readouterr().err


def test_the_root_is_a_viewer_page_that_names_what_is_served(
    server: str, site: Path, tmp_path: Path
) -> None:
    """``/`` is an HTML page: CesiumJS from the default CDN build, over the terrain at ./ and
    what /index.json names (the imagery's TileJSON, the buildings); every URL it fetches is
    served. With --viewer-js a local build, its files are served under /viewer-js/."""
    from lodscape.serve import VIEWER_JS, viewer_source

    with httpx.Client(base_url=server) as c:
        r = c.get("/")
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/html")
        page = r.text
        assert f'src="{VIEWER_JS}Cesium.js"' in page
        assert 'fetch("index.json")' in page
        assert 'fromUrl("./"' in page
        assert site.stem in page
        index = c.get("/index.json").json()
        for key in ("terrain", "imagery_tilejson", "buildings"):
            assert c.get("/" + index[key]).status_code == 200, key
    build = tmp_path / "Build" / "Cesium"
    (build / "Widgets").mkdir(parents=True)
    (build / "Cesium.js").write_text("window.Cesium = {};")
    (build / "Widgets" / "widgets.css").write_text("body {}")
    assert viewer_source(str(build)) == ("viewer-js/", build.resolve())
    with pytest.raises(Exception, match="--viewer-js"):
        viewer_source(str(tmp_path))


def test_serve_offers_a_local_cesium_build(site: Path, tmp_path: Path) -> None:
    build = tmp_path / "Cesium"
    (build / "Widgets").mkdir(parents=True)
    (build / "Cesium.js").write_text("window.Cesium = {};")
    (build / "Widgets" / "widgets.css").write_text("body {}")
    port = _free_port()
    proc = _serve_process(site, port, ["--viewer-js", str(build)])
    try:
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=5.0) as c:
            page = c.get("/").text
            assert 'src="viewer-js/Cesium.js"' in page
            assert c.get("/viewer-js/Cesium.js").text == "window.Cesium = {};"
            assert c.get("/viewer-js/../site.lods").status_code in (403, 404)
    finally:
        proc.terminate()
        proc.communicate(timeout=10)
