"""Imagery layers on the whole globe (paper 000's pixel band on Web Mercator tiles): the tiles a
camera selects cover every visible ground point, a loopback tile server's tiles are what the
globe shows (no base image left between them, from orbit to the street), one-shot renders wait
for them, flights stream them on the one frame loop, and the terrain's own tiles sit inside."""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from _synthetic import fbm_heights, run_cli, write_dem
from _tileserver import TileServer, tile_colour
from lodscape import Camera
from lodscape.geo.frames import WGS84_A, WGS84_B, ecef_to_geodetic
from lodscape.geo.keys import texture_key_array
from lodscape.geo.tiles import MAX_LAT, lonlat_to_merc, tile_id_array, tiles_array
from lodscape.lod.mercator import resident_ancestors, select_tiles

MAGENTA = np.array([255, 0, 255])

VIEWS = {
    # over the equator: the poles are beyond its horizon (76° away)
    "orbit": Camera(10.0, 0.0, 2.0e7, pitch=-90.0, fov_y=35.0, width=320, height=180),
    "1000 km": Camera(-98.0, 33.0, 1.0e6, heading=20.0, pitch=-40.0, width=320, height=180),
    "100 km": Camera(140.0, -35.0, 1.0e5, heading=200.0, pitch=-25.0, width=320, height=180),
    "1.5 km": Camera(-0.1, 51.5, 1500.0, heading=75.0, pitch=-15.0, width=320, height=180),
    "100 m grazing": Camera(170.0, 10.0, 100.0, heading=90.0, pitch=-3.0, width=320, height=180),
    "across the antimeridian": Camera(179.9, -17.0, 4.0e5, heading=90.0, pitch=-50.0),
    "polar": Camera(150.0, 75.0, 3.0e6, pitch=-40.0, width=320, height=180),
}


def _ground(camera: Camera, n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(lon, lat) where rays through an n × n grid of the camera's pixels meet the ellipsoid."""
    rot = camera.rotation
    t = math.tan(math.radians(camera.fov_y) / 2.0)
    u = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    x, y = np.meshgrid(u * t * camera.aspect, u * t)
    d = -rot[2] + x.ravel()[:, None] * rot[0] + y.ravel()[:, None] * rot[1]
    scale = np.array([1 / WGS84_A, 1 / WGS84_A, 1 / WGS84_B])
    o, ds = camera.position * scale, d * scale
    a = (ds * ds).sum(1)
    b = 2.0 * ds @ o
    c = o @ o - 1.0
    disc = b * b - 4 * a * c
    hit = disc > 0
    s = (-b[hit] - np.sqrt(disc[hit])) / (2 * a[hit])
    p = camera.position + s[:, None] * d[hit]
    lon, lat, _ = ecef_to_geodetic(p[s > 0])
    return np.asarray(lon), np.asarray(lat)


@pytest.mark.parametrize("name", list(VIEWS))
def test_the_selected_tiles_cover_every_visible_ground_point(name: str) -> None:
    cam = VIEWS[name].with_clip(0.5, 1e8)
    sel = select_tiles(cam, 19)
    assert 0 < len(sel) < 1000
    # within the band where the imagery has finer levels
    assert (sel.pixels[sel.z < 19] <= 384.0).all()
    lon, lat = _ground(cam)
    keep = np.abs(lat) < MAX_LAT - 1e-6
    lon, lat = lon[keep], lat[keep]
    assert lon.size > 20
    mx, my = lonlat_to_merc(lon, lat)
    chosen = set(tile_id_array(sel.z, sel.x, sel.y).tolist())
    found = np.zeros(lon.size, bool)
    for z in np.unique(sel.z):
        x, y = tiles_array(mx, my, int(z))
        ids = tile_id_array(np.full(x.size, z), x, y)
        found |= np.array([i in chosen for i in ids.tolist()])
    assert found.all(), (name, int((~found).sum()))


def test_a_tile_falls_back_to_its_nearest_resident_ancestor() -> None:
    z = np.array([5, 5, 3, 0])
    x = np.array([17, 16, 4, 0])
    y = np.array([9, 8, 2, 0])
    resident = np.sort(
        texture_key_array(tile_id_array([5, 3, 2], [17, 4, 1], [9, 2, 0]), 1).astype(np.uint64)
    )
    # its own; (16, 8) at 5 has (4, 2) at 3 two levels up; (4, 2) at 3 its own; the root none
    assert resident_ancestors(z, x, y, 1, resident).tolist() == [0, 2, 0, -1]
    # another layer's tiles are not this one's
    assert resident_ancestors(z, x, y, 2, resident).tolist() == [-1, -1, -1, -1]


# --- on the GPU, with a real tile server on loopback ----------------------------------------


@pytest.fixture(scope="module")
def server() -> Iterator[TileServer]:
    s = TileServer()
    yield s
    s.close()


@pytest.fixture
def magenta_base(monkeypatch: pytest.MonkeyPatch) -> None:
    """A magenta base image: any pixel of it left in a picture is a hole in the imagery."""
    from lodscape.globe import Globe

    def base(self: object) -> np.ndarray:
        return np.tile(MAGENTA.astype(np.uint8), (90, 180, 1))

    monkeypatch.setattr(Globe, "base_image", base)


def _layer(server: TileServer, tmp_path: Path, max_zoom: int | None = None) -> object:
    from lodscape.imagery.layers import open_layer

    return open_layer(server.template, 1, cache_dir=tmp_path, max_zoom=max_zoom)


def _pink(rgb: np.ndarray) -> np.ndarray:
    """The base's magenta as the globe shades it: red and blue equal, no green (a server tile's
    colour, three bytes of a hash, is that by a chance of 1 in 65,536)."""
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return (r > 150) & (r == b) & (g == 0)


@pytest.mark.gl
@pytest.mark.parametrize("name", ["orbit", "1000 km", "100 km", "1.5 km", "100 m grazing"])
def test_the_server_tiles_cover_the_globe_with_no_hole(
    name: str, server: TileServer, tmp_path: Path, magenta_base: None
) -> None:
    from lodscape.globe import Globe

    cam = VIEWS[name]
    g = Globe(None, layers=[_layer(server, tmp_path)])
    try:
        rgb, dist = g.render(cam)
        last = dict(g.last)
    finally:
        g.close()
    assert last["imagery_missing"] == 0
    assert last["imagery_tiles"] > 0
    earth = np.isfinite(dist)
    assert earth.mean() > 0.1
    assert not _pink(rgb)[earth].any(), int(_pink(rgb)[earth].sum())
    # the middle of the picture shows the server's tile at the level selected there
    lon, lat = _ground(cam, 1)
    sel = select_tiles(g.camera(cam), 19)
    mx, my = lonlat_to_merc(lon, lat)
    colours = []
    for z in np.unique(sel.z):
        x, y = tiles_array(mx, my, int(z))
        if ((sel.z == z) & (sel.x == x[0]) & (sel.y == y[0])).any():
            colours.append(tile_colour(int(z), int(x[0]), int(y[0])))
    assert len(colours) == 1
    h, w = rgb.shape[:2]
    centre = rgb[h // 2 - 1 : h // 2 + 1, w // 2 - 1 : w // 2 + 1].reshape(-1, 3).astype(int)
    assert (np.abs(centre - np.array(colours[0])).max(axis=1) <= 3).any(), (centre, colours)


@pytest.mark.gl
def test_the_polar_caps_beyond_mercator_show_the_base(
    server: TileServer, tmp_path: Path, magenta_base: None
) -> None:
    from lodscape.globe import Globe

    g = Globe(None, layers=[_layer(server, tmp_path)])
    try:
        rgb, dist = g.render(VIEWS["polar"])
    finally:
        g.close()
    pink = _pink(rgb) & np.isfinite(dist)
    # the cap north of 85.05° is the base image's, and nothing else is
    assert pink.sum() > 100
    _lon, lat = _ground(VIEWS["polar"], 64)
    assert (lat > MAX_LAT).any()
    rows = np.nonzero(pink.any(axis=1))[0]
    assert rows.min() > 0.3 * rgb.shape[0]  # not the limb: the cap, in the middle


@pytest.mark.gl
def test_a_failing_server_leaves_the_base_and_says_so(
    tmp_path: Path, magenta_base: None, capsys: pytest.CaptureFixture[str]
) -> None:
    from lodscape.globe import Globe
    from lodscape.imagery.layers import open_layer

    s = TileServer()
    s.default_fault = "500"
    try:
        layer = open_layer(s.template, 1, cache_dir=tmp_path, timeout=2.0)
        g = Globe(None, layers=[layer])
        try:
            rgb, dist = g.render(VIEWS["1000 km"])
            last = dict(g.last)
        finally:
            g.close()
    finally:
        s.close()
    assert last["imagery_tiles"] == 0
    assert last["imagery_missing"] > 0
    assert _pink(rgb)[np.isfinite(dist)].all()  # the base, not invented imagery
    err = capsys.readouterr().err
    assert err.count("error answers") == 1, err


# --- from the command line: the one frame loop ------------------------------------------------


@pytest.mark.gl
def test_fly_over_the_globe_streams_imagery_on_the_one_loop(
    server: TileServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out, stats = tmp_path / "g.mp4", tmp_path / "g.csv"
    argv = ["fly", "none", "--globe", "--line", "-98,33,-96,34,300000", "--speed", "30000"]
    argv += ["--fps", "8", "--size", "160x96", "--pitch", "-45", "-o", str(out)]
    argv += ["--imagery", server.template, "--imagery-cache", str(tmp_path)]
    argv += ["--stats", str(stats), "--duration", "2"]
    code, text, err = run_cli(argv, capsys)
    assert code == 0, err
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 17
    # frame 0 never waits: its tiles are asked for; they come on the simulated clock
    assert int(rows[0]["imagery_missing"]) > 0
    assert int(rows[-1]["imagery_missing"]) == 0
    assert int(rows[-1]["imagery_tiles"]) > 0
    assert [float(r["time_s"]) for r in rows[:3]] == [0.0, 0.125, 0.25]
    assert int(rows[-1]["http_requests"]) > 0
    assert "globe facets per frame" in text


@pytest.mark.gl
def test_render_a_dem_on_the_globe_with_imagery(
    server: TileServer, tmp_path: Path, capsys: pytest.CaptureFixture[str], magenta_base: None
) -> None:
    """The DEM's own tiles (with the layer draped on them) where it has data, the layer on the
    globe around it: neither the base image nor a gap anywhere."""
    dem = tmp_path / "dem.tif"
    heights = fbm_heights(257, seed=3, relief=400.0)
    write_dem(str(dem), heights, crs="EPSG:4326", west=-78.8, north=36.6, res=2e-4)
    out = tmp_path / "g.png"
    # 8 km south of the DEM's middle, 8 km up, looking north at it
    view = ["--lon", "-78.775", "--lat", "36.50", "--alt", "8000", "--pitch", "-45"]
    view += ["--size", "240x160", "-o", str(out)]
    view += ["--imagery", server.template, "--imagery-cache", str(tmp_path)]
    code, text, err = run_cli(["render", str(dem), "--globe", *view], capsys)
    assert code == 0, err
    assert int(text.split("terrain_pixels:")[1].split()[0]) > 1000
    assert int(text.split("imagery_tiles:")[1].split()[0]) > 0
    from PIL import Image

    rgb = np.asarray(Image.open(out))
    assert not _pink(rgb).any()
