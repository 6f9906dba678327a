"""Imagery layers apart from the terrain: a local orthophoto finer than its DEM drawn at its own
level, layers composited bottom to top with their alpha, an orthophoto in another CRS landing
where its georeference says, and every failure of a real loopback tile server said on stderr,
counted, bounded in time, and an error with --imagery-strict."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem, write_ortho
from _tileserver import TileServer
from lodscape import Camera
from lodscape.geo.tiles import merc_to_lonlat

pytestmark = pytest.mark.gl

#: The DEM: 65² cells of 90 m in UTM 16N; the orthophoto 8× finer.
DEM_RES = 90.0
WEST, NORTH = 500_000.0, 4_000_000.0
N = 65


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("site")
    dem = write_dem(
        str(d / "dem.tif"),
        fbm_heights(N, seed=5, relief=150.0),
        crs="EPSG:32616",
        west=WEST,
        north=NORTH,
        res=DEM_RES,
    )
    n = N * 8
    yy, xx = np.mgrid[0:n, 0:n]
    # a checkerboard of two orthophoto pixels: only drawn near its own level does it show
    fine = ((xx // 2 + yy // 2) % 2).astype(bool)
    rgb = np.zeros((n, n, 3), np.uint8)
    rgb[fine] = (250, 250, 250)
    ortho = write_ortho(
        str(d / "ortho.tif"),
        rgb,
        crs="EPSG:32616",
        west=WEST - DEM_RES / 2,
        north=NORTH + DEM_RES / 2,
        res=DEM_RES / 8,
    )
    red = np.zeros((n, n, 3), np.uint8)
    red[..., 0] = 255
    base = write_ortho(
        str(d / "red.tif"), red, crs="EPSG:32616", west=WEST, north=NORTH, res=DEM_RES / 8
    )
    # blue over the east half, transparent over the west half
    blue = np.zeros((n, n, 3), np.uint8)
    blue[..., 2] = 255
    alpha = np.where(xx >= n // 2, 255, 0).astype(np.uint8)
    top = write_ortho(
        str(d / "blue.tif"),
        blue,
        crs="EPSG:32616",
        west=WEST,
        north=NORTH,
        res=DEM_RES / 8,
        alpha=alpha,
    )
    return {"dem": dem, "ortho": ortho, "red": base, "blue": top, "dir": str(d)}


def _centre(scene: lodscape.Scene) -> tuple[float, float]:
    b = scene.provider.bounds_merc
    lon, lat = merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
    return float(lon), float(lat)


def _down(scene: lodscape.Scene, lon: float, lat: float, above: float, w: int = 96) -> Camera:
    g = scene.ground_height(lon, lat)
    assert g is not None
    return Camera(lon, lat, g + above, pitch=-90, width=w, height=w)


def _contrast(rgb: NDArray[np.uint8]) -> float:
    """Mean absolute difference between horizontal neighbours (a checkerboard drawn texel for
    texel is all edges; averaged away it is none)."""
    g = rgb.astype(np.float64).mean(axis=2)
    return float(np.abs(np.diff(g, axis=1)).mean())


def test_an_orthophoto_finer_than_its_dem_is_drawn_at_its_own_level(site: dict[str, str]) -> None:
    from lodscape.imagery.raster import RasterImagery

    ortho = RasterImagery(site["ortho"])
    with lodscape.open(site["dem"]) as plain:
        dem_level = plain.provider.texture_levels[0]
        dem_zmax = plain.tree.zmax
    # 8× finer is three levels finer, beyond the DEM tree's geometry levels too
    assert ortho.max_zoom == dem_level + 3
    assert ortho.max_zoom > dem_zmax
    with lodscape.open(site["dem"], imagery=[site["ortho"]]) as scene:
        assert scene.provider.texture_levels == (dem_level, ortho.max_zoom)
        assert scene.tree.zmax >= ortho.max_zoom
        lon, lat = _centre(scene)
        # top down from where a pixel is 0.8 of a texel of the orthophoto's finest level: the
        # band keeps every drawn layer tile inside it, at that level
        texel_m = 2 * 20037508.342789244 / 256 / 2**ortho.max_zoom * math.cos(math.radians(lat))
        above = 0.8 * 96 * texel_m / 2 / math.tan(math.radians(30))
        rgb, _ = scene.render(_down(scene, lon, lat, above))
        sel = scene.view.previous
        assert sel is not None
        density = sel.layer_px_per_texel(1)
        assert np.isfinite(density).all()
        assert float(density.min()) >= 0.5, density
        assert float(density.max()) <= 1.5, density
        assert int((sel.z - sel.layer_up[0]).max()) == ortho.max_zoom
        # the geometry there is the DEM's surface refined: the same heights, none made up
        assert scene.ground_height(lon, lat) == pytest.approx(plain_height(site, lon, lat))
        sharp = _contrast(rgb)
    # the same view with the imagery cut at the DEM's texture level: the checkerboard is gone
    with lodscape.open(site["dem"], imagery=[site["ortho"]], imagery_maxzoom=dem_level) as capped:
        blurred = _contrast(capped.render(_down(capped, lon, lat, above))[0])
    assert sharp > 30.0, (sharp, blurred, scene.imagery_failures())
    assert blurred < 0.25 * sharp, (sharp, blurred)


def plain_height(site: dict[str, str], lon: float, lat: float) -> float:
    with lodscape.open(site["dem"]) as scene:
        h = scene.ground_height(lon, lat)
    assert h is not None
    return h


def test_layers_composite_bottom_to_top_with_their_alpha(site: dict[str, str]) -> None:
    with lodscape.open(site["dem"], imagery=[site["red"], site["blue"]]) as scene:
        lon, lat = _centre(scene)
        rgb, _ = scene.render(_down(scene, lon, lat, 3000.0, 64))
        west, east = rgb[:, :24].reshape(-1, 3).mean(0), rgb[:, 40:].reshape(-1, 3).mean(0)
        # red shows through the blue layer's transparent west half; the east half is blue
        assert west[0] > 200, west
        assert west[2] < 40, west
        assert east[2] > 200, east
        assert east[0] < 40, east
    with lodscape.open(site["dem"], imagery=[site["blue"], site["red"]]) as scene:
        rgb, _ = scene.render(_down(scene, lon, lat, 3000.0, 64))
        # the opaque red on top hides the blue everywhere
        assert (rgb[..., 0] > 200).mean() > 0.95


def test_layers_change_the_textures_not_how_the_meshes_are_made(site: dict[str, str]) -> None:
    """Over a raster, a picture's tiles are meshed by error and a streamed scene's grids
    split before their finest, layers or not."""
    from lodscape.stream import StreamOptions
    from lodscape.terrain.tin_tiles import ErrorLadder, SplitBeforeFinest

    with lodscape.open(site["dem"]) as plain:
        level = plain.provider.texture_levels[0]
    # no finer than the DEM's textures (finer imagery carries the raster on below its data)
    layer = {"imagery": [site["red"]], "imagery_maxzoom": level}
    with lodscape.open(site["dem"], **layer) as scene:
        assert isinstance(scene.tree, ErrorLadder)
        assert scene.tree is scene.provider.base.tree
        lon, lat = _centre(scene)
        rgb, _ = scene.render(_down(scene, lon, lat, 3000.0, 64))
        assert (rgb[..., 0] > 200).mean() > 0.95
    opts = lodscape.SceneOptions(stream=StreamOptions())
    with lodscape.open(site["dem"], opts, **layer) as scene:
        assert isinstance(scene.tree, SplitBeforeFinest)


def test_an_orthophoto_in_another_crs_lands_where_its_georeference_says(
    site: dict[str, str], tmp_path: Path
) -> None:
    with lodscape.open(site["dem"]) as scene:
        lon, lat = _centre(scene)
    # a geographic orthophoto whose white west half ends exactly at the camera's longitude
    res = 1e-4
    n = 400
    west = lon - n / 2 * res
    rgb = np.zeros((n, n, 3), np.uint8)
    rgb[:, : n // 2] = 255
    path = write_ortho(
        str(tmp_path / "geo.tif"), rgb, crs="EPSG:4326", west=west, north=lat + n / 2 * res, res=res
    )
    with lodscape.open(site["dem"], imagery=[path]) as scene:
        rgb_out, _ = scene.render(_down(scene, lon, lat, 400.0, 128))
        sel = scene.view.previous
        assert sel is not None
        px_per_texel = float(np.nanmax(sel.layer_px_per_texel(1)))
    row = rgb_out[64].astype(float).mean(axis=1)
    edge = int(np.argmax(row < 128))  # the first dark pixel from the west
    assert row[:edge].min() > 128
    # the camera's longitude is the picture's middle (between columns 63 and 64)
    assert abs(edge - 64) <= max(1.0, px_per_texel) + 0.5, (edge, px_per_texel)


# --- failures ----------------------------------------------------------------------------------


@pytest.fixture
def server() -> Iterator[TileServer]:
    s = TileServer()
    yield s
    s.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


FAULTS = {
    "404": ("404", "missing"),
    "500": ("500", "error answers"),
    "html": ("garbage", "not images"),
    "truncated png": ("truncated-png", "not images"),
    "cut short": ("truncated", "cut short"),
    "never answers": ("slow", "no answer in time"),
}


@pytest.mark.parametrize("name", [*FAULTS, "nothing listening"])
def test_each_imagery_failure_is_said_counted_bounded_and_strict(
    name: str,
    server: TileServer,
    site: dict[str, str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    if name == "nothing listening":
        template = f"http://127.0.0.1:{_free_port()}/{{z}}/{{x}}/{{y}}.png"
        said = "cannot connect"
    else:
        fault, said = FAULTS[name]
        server.default_fault = fault
        server.delay = 60.0  # "never answers": longer than anything here waits
        template = server.template
    out = tmp_path / "v.png"
    argv = [
        "render",
        site["dem"],
        "--size",
        "64x48",
        "-o",
        str(out),
        "--imagery",
        template,
        "--imagery-cache",
        str(tmp_path),
        "--imagery-timeout",
        "2",
    ]
    t = time.perf_counter()
    code, stdout, err = run_cli(argv, capsys)
    took = time.perf_counter() - t
    assert code == 0, err
    assert out.exists()
    # said once on stderr, naming the layer and the kind; counted in the stats
    warnings = [line for line in err.splitlines() if "imagery layer 1" in line]
    assert len(warnings) == 1, err
    assert said in warnings[0]
    assert "imagery_failed" in stdout
    failed = int(stdout.split("imagery_failed:")[1].split()[0])
    assert failed > 0 or "had not come" in err
    # a server that never answers costs the render its imagery timeout, not one per tile
    assert took < 20.0, took
    out.unlink()
    code, _, err = run_cli([*argv, "--imagery-strict"], capsys)
    assert code == 2
    assert "imagery" in err.splitlines()[-1]
    assert not out.exists()


def test_a_flight_never_waits_for_a_server_that_never_answers(
    server: TileServer, site: dict[str, str]
) -> None:
    from lodscape.flight import fly
    from lodscape.scene import SceneOptions
    from lodscape.stream import SimClock, StreamOptions

    server.default_fault = "slow"
    server.delay = 60.0
    opts = SceneOptions(stream=StreamOptions(in_flight=8), imagery_timeout=1.0)
    messages: list[str] = []
    with lodscape.open(site["dem"], opts, clock=SimClock(), imagery=[server.template]) as scene:
        scene.provider.layers[0].warn = messages.append
        lon, lat = _centre(scene)
        cams = [_down(scene, lon + 1e-4 * i, lat, 1500.0, 64) for i in range(30)]
        t = time.perf_counter()
        rows = fly(scene, iter(cams), 30.0)
        took = time.perf_counter() - t
        # the requests time out on their own threads, after the frames that asked went on
        deadline = time.monotonic() + 10.0
        while not messages and time.monotonic() < deadline:
            time.sleep(0.05)
    assert len(rows) == 30
    assert all(r["stall_ms"] == 0 for r in rows[1:])
    # the terrain's own texture stands in for the layer, counted as a fallback every frame
    assert all(r["layer_fallbacks"] > 0 for r in rows)
    assert took < 30.0, took
    assert any("no answer in time" in m for m in messages)


# --- tilesets -----------------------------------------------------------------------------------


def _close_view(scene: lodscape.Scene, zoom: int) -> Camera:
    """Top down, a pixel 0.8 of a texel of level ``zoom``, 96 px square."""
    lon, lat = _centre(scene)
    texel_m = 2 * 20037508.342789244 / 256 / 2**zoom * math.cos(math.radians(lat))
    return _down(scene, lon, lat, 0.8 * 96 * texel_m / 2 / math.tan(math.radians(30)))


def test_a_tileset_wears_imagery_finer_than_its_terrain(
    site: dict[str, str], tmp_path: Path
) -> None:
    from lodscape.build import BuildOptions, build
    from lodscape.imagery.raster import RasterImagery

    lods = tmp_path / "site.lods"
    # a budget the planned finest level keeps, so the build adds no level below it
    build([site["dem"]], lods, BuildOptions(error_texels=4.0))
    finest = RasterImagery(site["ortho"]).max_zoom
    with lodscape.open(lods) as plain:
        stored = plain.tree.zmax
        h = plain.ground_height(*_centre(plain))
    assert finest > stored
    with lodscape.open(lods, imagery=[site["ortho"]]) as scene:
        # the tileset's stored surface, cut finer down to the imagery's level: the same ground
        assert scene.tree.zmax == finest
        assert scene.ground_height(*_centre(scene)) == pytest.approx(h)
        rgb, _ = scene.render(_close_view(scene, finest))
        sel = scene.view.previous
        assert sel is not None
        assert int((sel.z - sel.layer_up[0]).max()) == finest
        assert _contrast(rgb) > 30.0


def test_build_bakes_imagery_at_its_own_levels(
    site: dict[str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3
    from contextlib import closing

    from lodscape.imagery.raster import RasterImagery

    lods = tmp_path / "baked.lods"
    code, _, err = run_cli(
        ["build", site["dem"], "-o", str(lods), "--imagery", site["ortho"], "-q"], capsys
    )
    assert code == 0, err
    finest = RasterImagery(site["ortho"]).max_zoom
    with closing(sqlite3.connect(lods)) as db:
        levels = dict(db.execute("SELECT zoom_level, COUNT(*) FROM tiles GROUP BY 1").fetchall())
        meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    assert max(levels) == finest
    assert meta["maxzoom"] == str(finest)
    assert "ortho.tif" in meta["description"]
    code, out, _ = run_cli(["info", str(lods)], capsys)
    assert code == 0
    assert f"imagery: levels {min(levels)} .. {finest}" in out
    with lodscape.open(lods) as scene:
        assert scene.provider.texture_levels == (finest,)
        rgb, _ = scene.render(_close_view(scene, finest))
        sel = scene.view.previous
        assert sel is not None
        assert int((sel.z - sel.texture_up).max()) == finest
        assert _contrast(rgb) > 30.0
    # a build bakes local imagery only
    code, _, err = run_cli(
        ["build", site["dem"], "-o", str(tmp_path / "x.lods"), "--imagery", "http://h/{z}/{x}/{y}"],
        capsys,
    )
    assert code == 2
    assert "bakes local imagery" in err
    assert not (tmp_path / "x.lods").exists()


# --- what a raster layer can be, and what it must refuse ---------------------------------------


def _tile_over(r: Any, lon: float, lat: float, z: int) -> NDArray[np.uint8]:
    from lodscape.geo.tiles import tile

    t = tile(lon, lat, z)
    return r.decode(r.fetch(t.z, t.x, t.y), 256)


def test_palette_grey_and_overview_rasters(tmp_path: Path) -> None:
    import rasterio
    from rasterio.enums import Resampling
    from rasterio.transform import Affine

    from lodscape.imagery.raster import RasterImagery

    t = Affine(10.0, 0.0, WEST, 0.0, -10.0, NORTH)
    common = {"driver": "GTiff", "height": 512, "width": 512, "crs": "EPSG:32616", "transform": t}
    with rasterio.open(tmp_path / "pal.tif", "w", count=1, dtype="uint8", **common) as d:
        d.write(np.full((1, 512, 512), 3, np.uint8))
        d.write_colormap(1, {3: (10, 200, 30, 255)})
    with rasterio.open(tmp_path / "grey.tif", "w", count=1, dtype="uint16", **common) as d:
        # a 16-bit band: stretched between its 2nd and 98th percentiles
        d.write(np.tile(np.linspace(1000, 3000, 512, dtype=np.uint16), (512, 1))[None])
    with rasterio.open(
        tmp_path / "cog.tif", "w", count=3, dtype="uint8", tiled=True, **common
    ) as d:
        d.write(np.full((3, 512, 512), 90, np.uint8))
        d.build_overviews([2, 4, 8], Resampling.average)
    from rasterio.warp import transform_bounds

    with rasterio.open(tmp_path / "grey.tif") as src:
        (w, s, e, n) = transform_bounds(src.crs, "EPSG:4326", *src.bounds)
    lon, lat = (w + e) / 2, (s + n) / 2
    pal = _tile_over(RasterImagery(tmp_path / "pal.tif"), lon, lat, 14)
    inside = pal[..., 3] == 255
    assert inside.mean() > 0.2
    assert tuple(pal[inside][0][:3]) == (10, 200, 30)
    grey = _tile_over(RasterImagery(tmp_path / "grey.tif"), lon, lat, 12)
    row = grey[128, :, 0][grey[128, :, 3] == 255].astype(int)
    # stretched, and west to east it brightens
    assert row.min() < 60
    assert row.max() > 200
    assert (np.diff(row) >= -2).all()
    # a coarse level of a raster with overviews: still its colour, only coarser
    cog = RasterImagery(tmp_path / "cog.tif")
    coarse = _tile_over(cog, lon, lat, 9)
    covered = coarse[..., 3] > 250
    assert covered.any()
    assert np.abs(coarse[covered][:, :3].astype(int) - 90).max() <= 1


def test_an_orthophoto_placed_by_ground_control_points(tmp_path: Path) -> None:
    """A scanned map placed by ground control points alone (no grid) draws as the same raster
    with its grid where an affine map fits its points, said once; where none does, it is
    refused with the gdalwarp that grids it (both were refused for having no CRS)."""
    import warnings

    import rasterio
    import rasterio.errors
    from rasterio.control import GroundControlPoint
    from rasterio.transform import Affine

    from lodscape.imagery.raster import RasterImagery
    from lodscape.imagery.sources import ImageryError

    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, (3, 200, 300), dtype=np.uint8)
    grid = Affine(9.0, 1.5, WEST, 2.0, -10.0, NORTH)  # turned and sheared
    common = {"driver": "GTiff", "height": 200, "width": 300, "count": 3, "dtype": "uint8"}
    with rasterio.open(tmp_path / "grid.tif", "w", crs="EPSG:32616", transform=grid, **common) as d:
        d.write(rgb)

    def placed(name: str, shift: float) -> Path:
        pts = []
        for i, (c, r) in enumerate([(0, 0), (300, 0), (0, 200), (300, 200), (150, 100)]):
            x, y = grid.a * c + grid.b * r + grid.c, grid.d * c + grid.e * r + grid.f
            pts.append(GroundControlPoint(row=r, col=c, x=x + (shift if i == 4 else 0.0), y=y))
        with warnings.catch_warnings():
            # rasterio warns of a file with no geotransform before its points are set
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(tmp_path / name, "w", **common) as d:
                d.write(rgb)
                d.gcps = (pts, rasterio.crs.CRS.from_epsg(32616))
        return tmp_path / name

    a, b = RasterImagery(tmp_path / "grid.tif"), RasterImagery(placed("gcps.tif", 0.0))
    assert a.place_note is None
    assert b.place_note is not None
    assert "5 ground control points" in b.place_note
    assert tuple(b.bounds_merc) == pytest.approx(tuple(a.bounds_merc), abs=1e-3)
    lon, lat = (
        float(v)
        for v in merc_to_lonlat(
            (a.bounds_merc.left + a.bounds_merc.right) / 2,
            (a.bounds_merc.bottom + a.bounds_merc.top) / 2,
        )
    )
    for z in (14, 16):
        ta, tb = _tile_over(a, lon, lat, z), _tile_over(b, lon, lat, z)
        assert (ta[..., 3] == 255).mean() > 0.3
        assert np.abs(ta.astype(int) - tb.astype(int)).max() <= 1
    with pytest.raises(ImageryError, match="ground control points that no affine map fits"):
        RasterImagery(placed("bent.tif", 30.0))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("broken", "not a raster GDAL can read"),
        ("nocrs", "has no CRS"),
        ("nodata", "nodata everywhere"),
        ("badmbtiles", "not an MBTiles file"),
        ("missing", "no such file or folder"),
        ("emptyfolder", "no z/x/y tile folders"),
    ],
)
def test_bad_imagery_is_refused_in_one_line(
    content: str,
    message: str,
    site: dict[str, str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    import rasterio
    from rasterio.transform import Affine

    path = tmp_path / "layer.tif"
    t = Affine(10.0, 0.0, WEST, 0.0, -10.0, NORTH)
    if content == "broken":
        path.write_bytes(b"II*\x00 not really a tiff")
    elif content == "nocrs":
        with rasterio.open(
            path, "w", driver="GTiff", height=8, width=8, count=3, dtype="uint8", transform=t
        ) as d:
            d.write(np.zeros((3, 8, 8), np.uint8))
    elif content == "nodata":
        with rasterio.open(
            path, "w", driver="GTiff", height=8, width=8, count=1, dtype="float32",
            crs="EPSG:32616", transform=t, nodata=-1.0,
        ) as d:  # fmt: skip
            d.write(np.full((1, 8, 8), -1.0, np.float32))
    elif content == "badmbtiles":
        path = tmp_path / "layer.mbtiles"
        path.write_bytes(b"garbage, not sqlite")
    elif content == "emptyfolder":
        path = tmp_path / "tiles"
        path.mkdir()
    out = tmp_path / "v.png"
    code, _, err = run_cli(
        ["render", site["dem"], "--size", "32x24", "-o", str(out), "--imagery", str(path)],
        capsys,
    )
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert message in lines[0]
    assert not out.exists()


def test_the_gpu_terrain_mode_composites_layers_too(site: dict[str, str]) -> None:
    from lodscape.scene import SceneOptions

    opts = SceneOptions(terrain_mode="gpu")
    with lodscape.open(site["dem"], opts, imagery=[site["red"], site["blue"]]) as scene:
        lon, lat = _centre(scene)
        rgb, _ = scene.render(_down(scene, lon, lat, 3000.0, 64))
        if scene.terrain_mode != "gpu":
            pytest.skip(scene.terrain_mode_note or "no tessellation here")
        west, east = rgb[:, :24].reshape(-1, 3).mean(0), rgb[:, 40:].reshape(-1, 3).mean(0)
        assert west[0] > 200, west
        assert east[2] > 200, east


def test_an_mbtiles_layer_is_transparent_outside_its_bounds_not_failing(
    site: dict[str, str], tmp_path: Path
) -> None:
    import io
    import sqlite3
    from contextlib import closing

    from PIL import Image

    from lodscape.geo.tiles import Tile, tiles_array, xy_bounds

    with lodscape.open(site["dem"]) as scene:
        _, lat = _centre(scene)
        b = scene.provider.bounds_merc
        z = scene.provider.texture_levels[0] + 2
    # red tiles of level z wholly west of the DEM's middle, and bounds that say just that
    buf = io.BytesIO()
    Image.new("RGB", (256, 256), (255, 0, 0)).save(buf, format="PNG")
    mid = (b.left + b.right) / 2
    xs, ys = np.meshgrid(np.linspace(b.left, mid, 32), np.linspace(b.bottom, b.top, 32))
    tx, ty = tiles_array(xs.ravel(), ys.ravel(), z)
    tiles = {(int(a), int(c)) for a, c in zip(tx, ty, strict=True)}
    tiles = {t for t in tiles if xy_bounds(Tile(t[0], t[1], z)).right <= mid}
    east = max(xy_bounds(Tile(x, y, z)).right for x, y in tiles)
    (w, e), (s, n) = merc_to_lonlat([b.left - 1e4, east], [b.bottom - 1e4, b.top + 1e4])
    path = tmp_path / "west.mbtiles"
    with closing(sqlite3.connect(path)) as db:
        db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        db.execute(
            "CREATE TABLE tiles (zoom_level INT, tile_column INT, tile_row INT, tile_data BLOB)"
        )
        db.execute("INSERT INTO metadata VALUES ('bounds', ?)", (f"{w},{s},{e},{n}",))
        for x, y in tiles:
            db.execute(
                "INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, x, (1 << z) - 1 - y, buf.getvalue())
            )
        db.commit()
    east_lon = float(merc_to_lonlat((east + b.right) / 2, 0.0)[0])
    west_lon = float(merc_to_lonlat((b.left + east) / 2, 0.0)[0])
    with lodscape.open(site["dem"], imagery=[path]) as scene:
        over_east, _ = scene.render(_down(scene, east_lon, lat, 600.0, 32))
        over_west, _ = scene.render(_down(scene, west_lon, lat, 600.0, 32))
        # east of its bounds the layer is transparent: no tile asked for, none missing
        assert scene.imagery_failures() == {}
    assert (over_west[..., 0] > 200).mean() > 0.9
    assert (over_west[..., 1] < 60).mean() > 0.9
    assert (over_east[..., 0] > 200).mean() < 0.1
