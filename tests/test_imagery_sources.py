"""Imagery from a real HTTP tile server on loopback, with latency, 404, 500, truncated bodies
and bodies that are no image; the on-disk cache and HTTP caching; MBTiles and folders; and a
flight whose tile server misbehaves."""

from __future__ import annotations

import io
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem
from _tileserver import TileServer, tile_colour
from lodscape import Camera, SceneOptions
from lodscape.imagery.layers import ImageryLayer
from lodscape.imagery.sources import (
    DirectorySource,
    HttpSource,
    ImageryError,
    MBTilesSource,
    TileCache,
    TileMissing,
)
from lodscape.store.provider import LayeredProvider, RasterProvider
from lodscape.stream import SimClock, StreamOptions
from lodscape.terrain.source import RasterSource


@pytest.fixture
def server() -> Iterator[TileServer]:
    s = TileServer()
    yield s
    s.close()


def _colour(data: bytes) -> tuple[int, int, int]:
    from PIL import Image

    px = Image.open(io.BytesIO(data)).convert("RGB").getpixel((5, 5))
    return tuple(px)  # type: ignore[arg-type, return-value]


def test_fetches_and_caches_on_disk_honouring_max_age(server: TileServer, tmp_path: Path) -> None:
    cache = TileCache(tmp_path / "cache.sqlite")
    src = HttpSource(server.template, cache=cache)
    assert _colour(src.fetch(3, 2, 1)) == tile_colour(3, 2, 1)
    assert _colour(src.fetch(3, 2, 1)) == tile_colour(3, 2, 1)
    assert server.count(3, 2, 1) == 1  # fresh: the second came from the cache
    src.close()
    # a new process's source finds it on disk
    again = HttpSource(server.template, cache=TileCache(tmp_path / "cache.sqlite"))
    again.fetch(3, 2, 1)
    assert server.count(3, 2, 1) == 1
    assert server.requests[0][1]["User-Agent"].startswith("lodscape/")
    again.close()


def test_a_stale_tile_is_revalidated_with_its_etag(server: TileServer, tmp_path: Path) -> None:
    server.max_age = 0
    src = HttpSource(server.template, cache=TileCache(tmp_path / "c.sqlite"))
    first = src.fetch(4, 5, 6)
    second = src.fetch(4, 5, 6)
    assert first == second
    assert server.count(4, 5, 6) == 2
    assert "If-None-Match" in server.requests[-1][1]
    src.close()


def test_caching_by_expires_and_last_modified(server: TileServer, tmp_path: Path) -> None:
    """A server with dates instead of tags: fresh until Expires (no request), then revalidated
    with If-Modified-Since, a 304 keeping the cached tile and refreshing its expiry."""
    server.dated = True
    server.max_age = 3600
    cache = TileCache(tmp_path / "c.sqlite")
    src = HttpSource(server.template, cache=cache)
    first = src.fetch(4, 5, 6)
    assert src.fetch(4, 5, 6) == first
    assert server.count(4, 5, 6) == 1  # fresh by its Expires
    _, etag, modified, expires = cache.get(src.url(4, 5, 6))  # type: ignore[misc]
    assert etag is None
    assert modified == "Mon, 02 Nov 2026 10:00:00 GMT"
    assert 3500 < expires - time.time() < 3700
    # made stale: revalidated by date, answered 304, the same bytes kept
    cache.put(src.url(4, 5, 6), first, None, modified, time.time() - 1.0)
    assert src.fetch(4, 5, 6) == first
    assert server.count(4, 5, 6) == 2
    assert server.requests[-1][1]["If-Modified-Since"] == modified
    assert "If-None-Match" not in server.requests[-1][1]
    assert cache.get(src.url(4, 5, 6))[3] > time.time() + 3500  # type: ignore[index]
    src.close()


@pytest.mark.parametrize("fault", ["500", "truncated", "garbage", "slow"])
def test_transient_faults_are_retried_then_succeed(server: TileServer, fault: str) -> None:
    server.delay = 0.6
    server.faults[(5, 1, 2)] = [fault, fault]
    src = HttpSource(server.template, retries=3, backoff=0.01, timeout=0.3)
    assert _colour(src.fetch(5, 1, 2)) == tile_colour(5, 1, 2)
    assert server.count(5, 1, 2) == 3
    assert src.retried == 2
    src.close()


@pytest.mark.parametrize(
    ("fault", "message"),
    [
        ("500", "HTTP 500"),
        ("garbage", "not an image"),
        ("truncated", "cut short"),
        ("slow", "no answer in 0.3 s"),
    ],
)
def test_lasting_faults_fail_in_one_line(server: TileServer, fault: str, message: str) -> None:
    server.default_fault = fault
    server.delay = 0.6
    src = HttpSource(server.template, retries=2, backoff=0.01, timeout=0.3)
    with pytest.raises(ImageryError, match=message) as info:
        src.fetch(2, 1, 1)
    assert "\n" not in str(info.value)
    assert server.count(2, 1, 1) == 3
    src.close()


def test_a_missing_tile_is_not_retried(server: TileServer) -> None:
    server.faults[(6, 6, 6)] = ["404"]
    src = HttpSource(server.template, retries=3, backoff=0.01)
    with pytest.raises(TileMissing):
        src.fetch(6, 6, 6)
    assert server.count(6, 6, 6) == 1
    src.close()


def test_subdomains_and_bad_templates(server: TileServer) -> None:
    src = HttpSource(f"http://127.0.0.1:{server.port}/{{s}}/{{z}}/{{x}}/{{y}}.png")
    assert src.url(1, 0, 1).split("/")[3] in "abc"
    src.fetch(1, 0, 1)
    src.close()
    with pytest.raises(ImageryError, match="lacks"):
        HttpSource("http://example.org/{z}/{x}.png")


def test_mbtiles_and_folders(tmp_path: Path) -> None:
    import sqlite3
    from contextlib import closing

    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((256, 256, 3), (10, 200, 30), np.uint8)).save(buf, format="PNG")
    path = tmp_path / "i.mbtiles"
    with closing(sqlite3.connect(path)) as db:
        db.execute("CREATE TABLE tiles (zoom_level, tile_column, tile_row, tile_data)")
        db.execute("INSERT INTO tiles VALUES (2, 1, 2, ?)", (buf.getvalue(),))  # TMS row 2
        db.commit()
    assert _colour(MBTilesSource(path).fetch(2, 1, 1)) == (10, 200, 30)
    with pytest.raises(TileMissing):
        MBTilesSource(path).fetch(2, 0, 0)
    (tmp_path / "d" / "2" / "1").mkdir(parents=True)
    (tmp_path / "d" / "2" / "1" / "1.png").write_bytes(buf.getvalue())
    (tmp_path / "d" / "2" / "1" / "3.png").write_bytes(b"nonsense")
    folder = DirectorySource(tmp_path / "d")
    assert _colour(folder.fetch(2, 1, 1)) == (10, 200, 30)
    with pytest.raises(ImageryError, match="not an image"):
        folder.fetch(2, 1, 3)


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("img") / "dem.tif"
    return write_dem(
        str(path), fbm_heights(257, seed=4), crs="EPSG:4326", west=7.0, north=46.5, res=0.0003
    )


@pytest.mark.gl
def test_render_drapes_server_imagery(
    server: TileServer, dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "v.png"
    code, _, err = run_cli(
        [
            "render",
            dem,
            "--size",
            "160x100",
            "-o",
            str(out),
            "-q",
            "--imagery",
            server.template,
            "--imagery-cache",
            str(tmp_path),
            "--no-ellipsoid",
        ],
        capsys,
    )
    assert code == 0, err
    from PIL import Image

    with Image.open(out) as im:
        rgb = np.asarray(im.convert("RGB")).reshape(-1, 3).astype(int)
    served = np.array(
        [tile_colour(*map(int, p.rstrip(".png").split("/")[-3:])) for p, _ in server.requests]
    )
    # the ground is made of the server's flat tile colours: lit, so each pixel is one of them
    # scaled (the same hue); filtering blends the edges between tiles
    from lodscape.scene import SKY

    ground = rgb[np.abs(rgb - np.array(SKY) * 255).max(axis=1) > 2]
    unit = ground / np.maximum(np.linalg.norm(ground, axis=1, keepdims=True), 1.0)
    ref = served / np.linalg.norm(served, axis=1, keepdims=True)
    same_hue = (unit @ ref.T).max(axis=1) > 0.995
    # the overview shows the data under its horizon and sky: a fifth of the picture here
    assert len(ground) > 0.15 * len(rgb)
    assert same_hue.mean() > 0.9, same_hue.mean()
    assert (tmp_path / "imagery-cache.sqlite").exists()


@pytest.mark.gl
def test_a_misbehaving_server_never_stalls_or_crashes_a_flight(
    server: TileServer, dem: str
) -> None:
    from lodscape.flight import fly

    server.default_fault = "500"
    server.faults = {}
    src = HttpSource(server.template, retries=1, backoff=0.01, timeout=0.2)
    clock = SimClock()
    # no cooldown: a loaded machine's 500s may come slower than the 0.2 s timeout, and a
    # timeout rests the layer for seconds of real time, longer than these simulated flights
    layer = ImageryLayer(src, index=1, warn=lambda message: None, cooldown=0.0)
    provider = LayeredProvider(RasterProvider(RasterSource(dem)), [layer])
    opts = SceneOptions(stream=StreamOptions(backoff=0.2, in_flight=8))
    with lodscape.Scene(provider, opts, owns=True, clock=clock) as scene:
        b = scene.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        hi = scene.tree.height_range[1]
        cams = [
            Camera(lon + 0.0001 * i, lat, hi + 800, pitch=-40, width=96, height=64)
            for i in range(60)
        ]
        rows = fly(scene, iter(cams), 30.0)
        # every frame drawn (no exception), failures counted and retried, nothing waited on
        assert len(rows) == 60
        assert sum(r["failed"] for r in rows) > 0
        assert sum(r["retried"] for r in rows) > 0
        # the HTTP client's own retries (one per request here) are in the statistics too
        assert rows[-1]["http_retries"] > 0
        # (each failed tile: a request, a retry, its request; the last may still be in its pause)
        assert rows[-1]["http_requests"] > rows[-1]["http_retries"] > 0
        assert all(r["stall_ms"] == 0 for r in rows[1:])
        # the server heals: its tiles arrive on retry
        server.default_fault = None
        healed = fly(scene, iter(cams), 30.0)
        assert sum(r["fetched"] for r in healed) > 0
        # while it failed, the layer's tiles were drawn from what there was (ancestors or none)
        assert max(r["layer_fallbacks"] for r in rows) > 0
        assert max(r["imagery_failed"] for r in rows) > 0, [
            (r["failed"], r["imagery_failed"], r["requested"], r["http_requests"])
            for r in healed[::10]
        ]


@pytest.mark.parametrize("fault", ["trickle", "trickle-headers"])
def test_a_trickling_server_costs_a_tile_its_deadline_not_minutes(
    server: TileServer, fault: str
) -> None:
    """64 bytes every 0.3 s (under any per-read timeout): the tile fails as a timeout once its
    total deadline is spent, and is not retried past it."""
    server.default_fault = fault
    server.delay = 0.3
    src = HttpSource(server.template, timeout=5.0, deadline=1.5, retries=3, backoff=0.01)
    t = time.perf_counter()
    with pytest.raises(ImageryError) as info:
        src.fetch(4, 3, 2)
    took = time.perf_counter() - t
    assert info.value.kind == "timeout", str(info.value)
    assert took < 1.5 + 2 * server.delay + 0.5, took
    assert server.count(4, 3, 2) == 1


def test_a_decompression_bomb_is_refused_from_its_header(
    server: TileServer, tmp_path: Path
) -> None:
    """A 12000² PNG of ~20 KB: refused before decoding (576 MB as RGBA), counted as its own
    kind of failure, not retried, never cached."""
    import tracemalloc

    server.default_fault = "bomb"
    cache = TileCache(tmp_path / "cache.sqlite")
    src = HttpSource(server.template, cache=cache, retries=3, backoff=0.01)
    tracemalloc.start()
    try:
        with pytest.raises(ImageryError) as info:
            src.fetch(5, 1, 1)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert info.value.kind == "too-large"
    assert "12000×12000" in str(info.value)
    assert peak < 50 << 20, peak
    assert server.count(5, 1, 1) == 1
    assert cache.get(src.url(5, 1, 1)) is None
    # the same bytes in an MBTiles file or a folder are refused as well
    from lodscape.imagery.sources import decode_image

    body = src._client.get(src.url(5, 1, 1)).content
    with pytest.raises(ImageryError, match="12000"):
        decode_image(body, 256)
