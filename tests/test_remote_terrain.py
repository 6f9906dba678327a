"""Terrain streamed from servers on loopback: quantized-mesh from ``lodscape serve`` itself, and
Terrarium PNG tiles from a small server the test runs; the same surface as the local data, the
flight with no local file, and one-line errors for servers that fail."""

from __future__ import annotations

import io
import math
import threading
from collections.abc import Callable, Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_tileset, run_cli
from _tileserver import TERRAIN_BOX as BOX
from _tileserver import TerrainServer, serve_tileset
from _tileserver import terrain_height as _height
from lodscape.dataset import Origin, conventions
from lodscape.geo.frames import ecef_to_geodetic, geodetic_to_ecef
from lodscape.geo.tiles import ORIGIN, lonlat_to_merc, merc_to_lonlat
from lodscape.store.remote import interpolate_mesh, level_error, open_server

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fbm_tileset(tmp_path_factory.mktemp("remote"), seed=11, n=257)


@pytest.fixture(scope="module")
def served(site: Path) -> Iterator[str]:
    """``lodscape serve --tiling mercator``'s app on loopback: the stored tiles as they are."""
    with serve_tileset(site, tiling="mercator") as url:
        yield url


@pytest.fixture(scope="module")
def served_geographic(site: Path) -> Iterator[str]:
    """``lodscape serve``'s app on loopback, in its default tiling (EPSG:4326)."""
    with serve_tileset(site) as url:
        yield url


def _camera(site: Path) -> lodscape.Camera:
    """Over the site's south part, looking north across it."""
    with lodscape.open(site) as scene:
        b = scene.provider.bounds_merc
        lon, lat = merc_to_lonlat((b.left + b.right) / 2, b.bottom + 0.25 * (b.top - b.bottom))
        g = scene.ground_height(float(lon), float(lat))
    assert g is not None
    return lodscape.Camera(float(lon), float(lat), g + 600.0, heading=10, pitch=-30,
                           width=320, height=200)  # fmt: skip


def test_quantized_mesh_from_lodscape_serve_is_the_local_surface(
    site: Path, served: str, tmp_path: Path
) -> None:
    cam = _camera(site)
    with lodscape.open(site) as local:
        _, d_local = local.render(cam)
        tiles_local = local.last.selection["tiles"]
    with lodscape.open(f"{served}/layer.json", imagery_cache=tmp_path) as remote:
        _, d_remote = remote.render(cam)
        stats = remote.last.selection
        # heights anywhere: the served meshes, as the tileset's own
        lon = cam.lon + np.linspace(-0.01, 0.01, 50)
        lat = np.full(50, cam.lat + 0.004)
        got = remote.provider.heights_at(lon, lat)
    with lodscape.open(site) as local:
        want = local.provider.heights_at(lon, lat)
    ok = np.isfinite(want) & np.isfinite(got)
    assert ok.sum() > 40
    np.testing.assert_allclose(got[ok], want[ok], atol=0.05)
    both = np.isfinite(d_local) & np.isfinite(d_remote)
    assert both.mean() > 0.5
    rel = np.abs(d_remote[both] - d_local[both]) / d_local[both]
    assert np.median(rel) < 0.002, np.median(rel)
    assert stats["max_depth"] > 10
    assert stats["tiles"] > 4
    assert tiles_local > 4


def test_geographic_tiles_from_lodscape_serve_hold_the_local_surface(
    site: Path, served_geographic: str, tmp_path: Path
) -> None:
    """The default tiling's tiles, re-meshed from the stored ones, read back through lodscape's
    own Cesium client: the same ground within the stored tiles' recorded error, twice over."""
    cam = _camera(site)
    with lodscape.open(f"{served_geographic}/layer.json", imagery_cache=tmp_path) as remote:
        _, d_remote = remote.render(cam)
        lon = cam.lon + np.linspace(-0.01, 0.01, 50)
        lat = np.full(50, cam.lat + 0.004)
        got = remote.provider.heights_at(lon, lat)
    with lodscape.open(site) as local:
        want = local.provider.heights_at(lon, lat)
        _, d_local = local.render(cam)
        error = local.provider.max_error(int(local.provider.manifest["levels"]["zmax"]),
                                         0, 1 << 30, 0, 1 << 30)  # fmt: skip
    ok = np.isfinite(want) & np.isfinite(got)
    assert ok.sum() > 40
    assert np.abs(got[ok] - want[ok]).max() <= 2.0 * error + 0.05
    both = np.isfinite(d_local) & np.isfinite(d_remote)
    assert both.mean() > 0.5
    rel = np.abs(d_remote[both] - d_local[both]) / d_local[both]
    assert np.median(rel) < 0.01, np.median(rel)


def test_meshes_interpolate_on_their_own_triangles() -> None:
    from lodscape.store.remote import _Mesh

    # two triangles over the unit square, a ridge along the diagonal u = v
    u = np.array([0.0, 1.0, 1.0, 0.0])
    v = np.array([0.0, 0.0, 1.0, 1.0])
    h = np.array([0.0, 10.0, 0.0, 10.0])
    mesh = _Mesh(u, v, h, np.array([[0, 1, 2], [0, 2, 3]]), 0)
    pu = np.array([0.75, 0.25, 0.5, 1.0, 0.0])
    pv = np.array([0.25, 0.75, 0.5, 0.0, 1.0])
    np.testing.assert_allclose(interpolate_mesh(mesh, pu, pv), [5.0, 5.0, 0.0, 10.0, 10.0])
    assert np.isnan(interpolate_mesh(mesh, np.array([1.5]), np.array([0.5]))).all()


# --- Terrarium ------------------------------------------------------------------------------


MAXZOOM = 13


def _terrarium_png(z: int, x: int, y: int) -> bytes | None:
    from PIL import Image

    n = 256
    size = 2.0 * ORIGIN / (1 << z)
    px = (np.arange(n) + 0.5) / n
    xm = -ORIGIN + (x + px) * size
    ym = ORIGIN - (y + px) * size
    lon, lat = merc_to_lonlat(xm[None, :], ym[:, None])
    lon, lat = np.broadcast_arrays(lon, lat)
    w, s, e, nn = BOX
    inside = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= nn)
    if not inside.any():
        return None
    v = _height(lon, lat) + 32768.0
    r = np.floor(v / 256.0)
    g = np.floor(v - r * 256.0)
    b = np.floor((v - r * 256.0 - g) * 256.0)
    rgba = np.dstack([r, g, b, np.where(inside, 255, 0)]).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buf, "PNG")
    return buf.getvalue()


class _PngServer:
    """PNG height tiles on loopback: ``answer(path parts)`` gives a tile's bytes (None: 404; a
    part that is not a number: 400); ``fail`` answers 500 to every tile."""

    def __init__(self, answer: Callable[[list[str]], bytes | None]) -> None:
        self.fail = False
        self.requests = 0
        owner = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: object) -> None:
                pass

            def do_GET(self) -> None:
                owner.requests += 1
                try:
                    body = answer(self.path.strip("/").split("/"))
                except (ValueError, IndexError):
                    self.send_error(400)
                    return
                if owner.fail:
                    self.send_error(500)
                    return
                if body is None:
                    self.send_error(404)
                    return
                self.send_response(200)
                self.send_header("Content-Type", "image/png")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def _zxy(parts: list[str]) -> bytes | None:
    """…/{z}/{x}/{y}.png: the analytic terrain as Terrarium tiles, to MAXZOOM."""
    z, x, y = int(parts[-3]), int(parts[-2]), int(parts[-1].split(".")[0])
    return _terrarium_png(z, x, y) if z <= MAXZOOM else None


@pytest.fixture
def terrarium() -> Iterator[_PngServer]:
    server = _PngServer(_zxy)
    yield server
    server.close()


def test_terrarium_heights_are_the_servers(
    terrarium: _PngServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = f"terrarium:{MAXZOOM}:{terrarium.url}/{{z}}/{{x}}/{{y}}.png"
    heights, tree = open_server(spec, cache_dir=tmp_path)
    try:
        rng = np.random.default_rng(1)
        lon = rng.uniform(7.95, 8.05, 400)
        lat = rng.uniform(45.97, 46.03, 400)
        xm, ym = lonlat_to_merc(lon, lat)
        h, ok = heights.sample(xm, ym, heights.resolution_merc)
        assert ok.all()
        # bilinear between pixel centres 2.4 m apart (at z 13, 46°N) on a smooth surface,
        # heights encoded to 1/256 m
        np.testing.assert_allclose(h, _height(lon, lat), atol=0.5)
        # outside what the server has: no data, not a made-up height
        _h2, ok2 = heights.sample(*lonlat_to_merc(np.array([9.0]), np.array([46.0])), 10.0)
        assert not ok2.any()
        heights.sample(*lonlat_to_merc(np.array([9.5]), np.array([46.5])), 10.0)
        said = capsys.readouterr().err
        assert said.count("its deepest ancestor the server has is drawn") == 1, (
            said
        )  # the first missing tile, said once
        assert tree.zmax == MAXZOOM
        assert level_error(0, 64) == pytest.approx(6378137.0 * 2 * math.pi * 0.25 / 65)
    finally:
        heights.close()


def test_terrarium_renders_with_no_local_data(terrarium: _PngServer, tmp_path: Path) -> None:
    spec = f"terrarium:{MAXZOOM}:{terrarium.url}/{{z}}/{{x}}/{{y}}.png"
    g = float(_height(np.array(8.0), np.array(45.99)))
    cam = lodscape.Camera(8.0, 45.99, g + 1500.0, heading=0.0, pitch=-35.0, width=320, height=200)
    with lodscape.open(spec, imagery_cache=tmp_path) as scene:
        _rgb, depth = scene.render(cam)
        ground = scene.ground_height(8.0, 46.0)
        stats = scene.last.selection
    assert ground == pytest.approx(float(_height(np.array(8.0), np.array(46.0))), abs=0.5)
    assert np.isfinite(depth).mean() > 0.6
    assert stats["max_depth"] >= 12
    # the centre pixel's ray meets the analytic surface where the depth says
    o = Origin(8.0, 46.0)
    m = conventions(cam, o)
    ray = np.linalg.inv(m.K) @ np.array([159.5, 99.5, 1.0])
    local = m.R.T @ (ray * float(depth[99:101, 159:161].mean()) - m.t)
    ecef = o.basis.T @ local + geodetic_to_ecef(8.0, 46.0, 0.0)
    plon, plat, ph = ecef_to_geodetic(ecef)
    assert float(ph) == pytest.approx(float(_height(np.array(plon), np.array(plat))), abs=3.0)


def test_a_failing_terrain_server_is_one_line(
    terrarium: _PngServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    terrarium.fail = True
    spec = f"terrarium:{MAXZOOM}:{terrarium.url}/{{z}}/{{x}}/{{y}}.png"
    out = tmp_path / "v.png"
    code, _, err = run_cli(
        ["render", spec, "--lon", "8", "--lat", "45.99", "--alt", "3000", "-o", str(out),
         "--imagery-cache", str(tmp_path), "--imagery-timeout", "2"],
        capsys,
    )  # fmt: skip
    assert code == 2
    assert "HTTP 500" in err
    assert err.strip().count("\n") == 0
    assert not out.exists()
    for argv, message in [
        (["render", "http://127.0.0.1:1/layer.json"], "cannot fetch the layer"),
        (["render", f"{terrarium.url}/x/layer.json"], "HTTP 400 for the layer"),
        (["render", "terrarium:http//x"], "expected terrarium:"),
    ]:
        code, _, err = run_cli([*argv, "-o", str(out)], capsys)
        assert code == 2, argv
        assert message in err, (argv, err)
        assert err.strip().count("\n") == 0


def test_fly_a_served_site_with_no_local_data(
    site: Path, served: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cam = _camera(site)
    out = tmp_path / "f.mp4"
    stats = tmp_path / "f.csv"
    line = f"{cam.lon},{cam.lat},{cam.lon},{cam.lat + 0.01},{cam.alt}"
    code, _stdout, err = run_cli(
        ["fly", f"{served}/layer.json", "--imagery", f"{served}/imagery/{{z}}/{{x}}/{{y}}.png",
         "--line", line, "--speed", "200", "--fps", "10", "--size", "160x96",
         "-o", str(out), "--stats", str(stats), "--imagery-cache", str(tmp_path), "-q"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert out.stat().st_size > 1000
    import csv

    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) >= 5
    # the tree opens a level a round of loads while it flies: the first frame draws the root
    # tile over the whole view; the last ones draw the served terrain within the error bound,
    # nothing falling back
    assert float(rows[0]["max_sse_px"]) > 1e3
    assert float(rows[-1]["max_sse_px"]) <= 2.0
    assert int(rows[-1]["fallback_max"]) == 0
    assert int(rows[-1]["tiles"]) >= 1


# --- a geographic (EPSG:4326) quantized-mesh server, as Cesium's ----------------------------

GEO_MAXZOOM = 11


@pytest.fixture
def geographic() -> Iterator[str]:
    server = TerrainServer(maxzoom=GEO_MAXZOOM)
    yield server.url
    server.close()


def test_a_geographic_quantized_mesh_layer(geographic: str, tmp_path: Path) -> None:
    heights, tree = open_server(geographic, cache_dir=tmp_path)
    try:
        assert heights.tiles.geographic
        assert tree.zmax == GEO_MAXZOOM + 1  # a geographic level z spans Web Mercator's z + 1
        rng = np.random.default_rng(4)
        lon = rng.uniform(7.95, 8.05, 300)
        lat = rng.uniform(45.97, 46.03, 300)
        xm, ym = lonlat_to_merc(lon, lat)
        h, ok = heights.sample(xm, ym, heights.resolution_merc)
        assert ok.all()
        # linear on the served triangles (cells of 0.0055°, ~500 m): the sine's curvature over
        # a cell is up to 1.4 m; a vertex misplaced by one cell would be off by up to 33 m
        err = np.abs(h - _height(lon, lat))
        assert err.max() < 1.5
        assert np.median(err) < 0.8
    finally:
        heights.close()
    g = float(_height(np.array(8.0), np.array(45.99)))
    cam = lodscape.Camera(8.0, 45.99, g + 1500.0, heading=0.0, pitch=-35.0, width=160, height=100)
    with lodscape.open(geographic, imagery_cache=tmp_path) as scene:
        _, depth = scene.render(cam)
    assert np.isfinite(depth).mean() > 0.6


def test_availability_past_the_listed_levels_follows_the_last_listed() -> None:
    """Servers list the first levels in layer.json (Cesium's metadata availability lists the
    rest in tiles): below them, a tile is asked for where its listed ancestor is."""
    from lodscape.store.remote import ServerTiles

    tiles = ServerTiles(
        "t",
        "http://127.0.0.1:1/{z}/{x}/{y}.terrain",
        "quantized-mesh",
        geographic=True,
        tms=True,
        maxzoom=12,
        # level 0: both roots; level 1: only the north-east quarter (TMS row 1, column 3)
        available=[[(0, 0, 1, 0)], [(3, 1, 3, 1)]],
    )
    try:
        x = np.array([3, 2, 24, 24, 16])
        y = np.array([0, 0, 0, 7, 8])  # rows from the north
        assert tiles.has(1, x[:2], y[:2]).tolist() == [True, False]
        # level 4: 32 x 16 tiles; (24, 0) and (24, 7) lie under (3, 0) of level 1, (16, 8) not
        assert tiles.has(4, x[2:], y[2:]).tolist() == [True, True, False]
        assert not tiles.has(13, np.array([0]), np.array([0])).any()  # past maxzoom
    finally:
        tiles.close()


# --- height tiles of other sizes ------------------------------------------------------------


def _encoded(kind: str, side: int, border: int, z: int, x: int, y: int) -> bytes | None:
    """Tile z/x/y of the analytic terrain as a ``side``-pixel PNG (``border``: pixels of the
    neighbours' around it), Terrarium through lodscape's own writer (``store.pmtiles``) or
    Mapbox Terrain-RGB (0.1 m steps from -10000 m)."""
    from PIL import Image

    from lodscape.store.pmtiles import terrarium

    w, s, e, n = BOX
    inner = side - 2 * border
    size = 2.0 * ORIGIN / (1 << z)
    f = (np.arange(side) - border + 0.5) / inner
    lon, lat = merc_to_lonlat(-ORIGIN + (x + f)[None, :] * size, ORIGIN - (y + f)[:, None] * size)
    lon, lat = np.broadcast_arrays(lon, lat)
    inside = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)
    if not inside[border : -border or None, border : -border or None].any():
        return None
    if kind == "terrarium" and border == 0:
        return terrarium(
            lambda lo, la: np.where(
                (lo >= w) & (lo <= e) & (la >= s) & (la <= n), _height(lo, la), np.nan
            ),
            z,
            x,
            y,
            size=side,
        )
    h = _height(lon, lat)
    if kind == "terrarium":
        v = h + 32768.0
        r = np.floor(v / 256.0)
        g = np.floor(v - r * 256.0)
        b = np.floor((v - r * 256.0 - g) * 256.0)
    else:
        v = np.round((h + 10000.0) * 10.0)
        r, g, b = np.floor(v / 65536.0), np.floor(v / 256.0) % 256, v % 256
    rgba = np.dstack([r, g, b, np.where(inside, 255, 0)]).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buf, "PNG")
    return buf.getvalue()


def _sized(parts: list[str]) -> bytes | None:
    """/{kind}/{side}/{border}/{z}/{x}/{y}.png: ``_encoded``'s tiles, to MAXZOOM."""
    kind, side, border = parts[0], int(parts[1]), int(parts[2])
    z, x, y = int(parts[3]), int(parts[4]), int(parts[5].split(".")[0])
    return _encoded(kind, side, border, z, x, y) if z <= MAXZOOM else None


@pytest.fixture(scope="module")
def sized() -> Iterator[_PngServer]:
    server = _PngServer(_sized)
    yield server
    server.close()


@pytest.mark.parametrize(
    ("kind", "side", "border"),
    [
        ("terrarium", 256, 0),
        ("terrarium", 512, 0),
        ("terrain-rgb", 512, 0),
        ("terrarium", 514, 1),
        ("terrain-rgb", 258, 1),
    ],
)
def test_height_tiles_of_any_square_size_are_read_whole(
    sized: _PngServer, tmp_path: Path, kind: str, side: int, border: int
) -> None:
    """rio-rgbify, MapTiler and Mapbox's @2x tiles are 512 pixels; some carry a border of
    their neighbours' pixels. Every size is read from the image: heights right everywhere
    over the data (they were read as 256-pixel tiles: the top-left quadrant, hundreds of
    metres off, half of it no data)."""
    spec = f"{kind}:{MAXZOOM}:{sized.url}/{kind}/{side}/{border}/{{z}}/{{x}}/{{y}}.png"
    heights, _tree = open_server(spec, cache_dir=tmp_path)
    try:
        rng = np.random.default_rng(3)
        lon = rng.uniform(7.95, 8.05, 500)
        lat = rng.uniform(45.97, 46.03, 500)
        xm, ym = lonlat_to_merc(lon, lat)
        for spacing in (heights.resolution_merc, 40.0, 300.0):
            h, ok = heights.sample(xm, ym, spacing)
            assert ok.all(), (spacing, (~ok).sum())
            # bilinear between pixel centres on a smooth surface; coarser levels' pixels are
            # farther apart (300 m spacing: level 9, 150 m pixels over a 150 m sine)
            tol = {40.0: 2.0, 300.0: 40.0}.get(spacing, 0.5)
            np.testing.assert_allclose(h, _height(lon, lat), atol=tol)
        assert heights.tiles.pixels == side - 2 * border
        # a 512-pixel server resolves twice as fine a cell at its finest level
        assert heights.resolution_merc == pytest.approx(
            2.0 * ORIGIN / (1 << MAXZOOM) / (side - 2 * border)
        )
    finally:
        heights.close()


@pytest.mark.parametrize(("side", "border"), [(300, 0), (257, 0)])
def test_a_height_tile_of_another_shape_is_refused_in_one_line(
    sized: _PngServer, tmp_path: Path, side: int, border: int
) -> None:
    from lodscape.imagery.sources import ImageryError

    spec = f"terrarium:{MAXZOOM}:{sized.url}/terrarium/{side}/{border}/{{z}}/{{x}}/{{y}}.png"
    heights, _tree = open_server(spec, cache_dir=tmp_path)
    try:
        xm, ym = lonlat_to_merc(np.array([8.0]), np.array([46.0]))
        with pytest.raises(ImageryError, match=r"2\^k pixels a side") as info:
            heights.sample(xm, ym, 40.0)
        assert "\n" not in str(info.value)
        assert f"{side}×{side}" in str(info.value)
    finally:
        heights.close()


# --- a pyramid of uneven depth ----------------------------------------------------------------


@pytest.mark.parametrize("listed", [False, True])
def test_a_pyramid_of_uneven_depth_is_drawn_from_the_deepest_tile_there(
    tmp_path: Path, listed: bool
) -> None:
    """Real servers are deep on land and shallow over the sea: under the level-11 tiles south
    of 46.0° this one stops at level 10 (a 404 below, or not in its ``available`` list).
    Heights there come from the deepest tile it has, as CesiumJS draws them, not a hole;
    elsewhere from the deep ones (level 12)."""
    from _tileserver import TERRAIN_BOX

    split, shallow_z, maxzoom = 46.0, 10, 12
    available = None
    if listed:
        w, s, e, n = TERRAIN_BOX
        top = shallow_z + 1
        first_deep = math.floor((split + 90.0) / (180.0 / (1 << top)))  # level-11 row
        available = []
        for z in range(maxzoom + 1):
            span = 180.0 / (1 << z)
            x0, x1 = int((w + 180) // span), int((e + 180) // span)
            y0, y1 = int((s + 90) // span), int((n + 90) // span)
            if z > shallow_z:
                y0 = max(y0, first_deep << (z - top))
            available.append([{"startX": x0, "startY": y0, "endX": x1, "endY": y1}])
    server = TerrainServer(maxzoom=maxzoom, shallow=(split, shallow_z), available=available)
    try:
        heights, _tree = open_server(server.url, cache_dir=tmp_path)
        try:
            rng = np.random.default_rng(4)
            lon = rng.uniform(7.92, 8.08, 400)
            lat = rng.uniform(45.952, 46.045, 400)
            xm, ym = lonlat_to_merc(lon, lat)

            def spacing(z: int) -> float:  # what a geographic level z resolves
                return 2.0 * ORIGIN / 64 / (1 << (z + 1))

            h, ok = heights.sample(xm, ym, spacing(maxzoom))
            assert ok.all(), int((~ok).sum())  # no hole where the server is shallower
            h10, ok10 = heights.sample(xm, ym, spacing(shallow_z))
            assert ok10.all()
            edge = -90.0 + math.floor((split + 90.0) / (180.0 / 2048)) * 180.0 / 2048
            south = lat < edge - 0.001  # under the shallow level-11 tiles
            deep = lat > edge + 0.001
            assert south.sum() > 20
            assert deep.sum() > 200
            np.testing.assert_allclose(h[south], h10[south], atol=1e-6)
            # the deep tiles follow the terrain better than level 10 does
            err = np.abs(h - _height(lon, lat))
            err10 = np.abs(h10 - _height(lon, lat))
            assert err[deep].mean() < 0.5 * err10[deep].mean()
        finally:
            heights.close()
    finally:
        server.close()


def test_a_terrain_layer_is_known_by_what_it_answers_not_its_path(tmp_path: Path) -> None:
    """A URL that answers a quantized-mesh layer.json is a terrain server whatever its path
    (it was read as a raster file), and so is the layer's folder, as CesiumJS takes it; a
    URL answering something else is left to GDAL."""
    from lodscape.sources import parse_source

    server = TerrainServer(maxzoom=8)
    try:
        other = server.url.replace("layer.json", "metadata")
        folder = server.url.removesuffix("layer.json")
        assert parse_source(other) == type(parse_source(other))("server", other)
        assert parse_source(folder).kind == "server"
        assert parse_source(folder).text == server.url
        assert parse_source(folder.rstrip("/")).text == server.url
        assert parse_source(server.url.replace("layer.json", "nothing.bin")).kind == "raster"
        assert parse_source("http://127.0.0.1:1/dem").kind == "raster"  # nothing answers
        with lodscape.open(other, imagery_cache=tmp_path) as scene:
            g, ok = scene.provider.heights.sample(*lonlat_to_merc([8.0], [46.0]), 100.0)
        assert ok.all()
        assert abs(g[0] - float(_height(np.array(8.0), np.array(46.0)))) < 30.0
    finally:
        server.close()


@pytest.mark.parametrize("tiling", ["mercator", "geographic"])
def test_heights_over_a_server_are_not_biased(site: Path, tiling: str) -> None:
    """Heights read over ``lodscape serve`` at the data's levels scatter around the tileset's
    own finest surface with no bias (a +5..+9 m bias was reported against the DEM: it is not
    in what the server gives or how it is read); coarser levels scatter more. (Above the
    data's roots the server gives Cesium's filler tiles of the ellipsoid, height 0, as
    CesiumJS draws them: a view far enough to ask for those levels draws the ellipsoid.)"""
    from lodscape.store.tileset import TilesetProvider

    provider = TilesetProvider(site)
    b = provider.bounds_merc
    rng = np.random.default_rng(6)
    xm = rng.uniform(b.left + 0.1 * (b.right - b.left), b.right - 0.1 * (b.right - b.left), 2000)
    ym = rng.uniform(b.bottom + 0.1 * (b.top - b.bottom), b.top - 0.1 * (b.top - b.bottom), 2000)
    want = provider.heights(*merc_to_lonlat(xm, ym))
    provider.close()
    spread = []
    with serve_tileset(site, tiling=tiling) as url:
        heights, _tree = open_server(url + "/layer.json")
        try:
            for spacing in (heights.resolution_merc, 20.0, 40.0):
                h, ok = heights.sample(xm, ym, spacing)
                assert ok.all()
                d = h - want
                assert abs(float(np.mean(d))) < 0.5, (spacing, float(np.mean(d)))
                spread.append(float(np.percentile(np.abs(d), 95)))
        finally:
            heights.close()
    assert spread[0] <= spread[-1]
