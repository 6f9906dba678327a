"""Telling the truth about the data: nodata is a hole (or a stated fill), sea level is water,
DEMs with impossible heights or several bands are refused, and a build's finest level keeps to
its budget or says why not."""

from __future__ import annotations

import math
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.enums import ColorInterp
from rasterio.transform import Affine

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem
from lodscape import Camera, SceneOptions
from lodscape.build import build
from lodscape.build.tiles import level_budget
from lodscape.errors import SourceError
from lodscape.imagery.tint import tint
from lodscape.store.tileset import TIN_GRID, TilesetProvider
from lodscape.terrain.source import RasterSource, parse_fill

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0
MAGENTA = (1.0, 0.0, 1.0)
BACKGROUND = (0.25, 0.5, 0.75)


def _dem(path: Path, values: np.ndarray, nodata: float | None = None) -> str:
    return write_dem(
        str(path), values, crs="EPSG:32617", west=EAST, north=NORTH, res=RES, nodata=nodata
    )


@pytest.mark.parametrize("bad", [1e30, -3.4e38, 1e7, -20000.0, 32767.0])
def test_absurd_heights_are_refused_until_declared(tmp_path: Path, bad: float) -> None:
    h = fbm_heights(65, seed=1)
    h[10:14, 20:30] = np.float32(bad)
    path = _dem(tmp_path / "bad.tif", h)
    with pytest.raises(SourceError) as err:
        RasterSource(path)
    text = str(err.value)
    assert path in text
    assert "--nodata" in text
    assert f"{np.float32(bad):.6g}"[:4] in text
    with RasterSource(path, nodata=float(np.float32(bad))) as src:
        lo, hi = src.data_range
        assert 300.0 <= lo <= hi <= 1200.0


def test_a_multiband_raster_needs_a_band(tmp_path: Path) -> None:
    h = fbm_heights(33, seed=2)
    path = tmp_path / "three.tif"
    profile = {
        "driver": "GTiff",
        "width": 33,
        "height": 33,
        "count": 3,
        "dtype": "float32",
        "crs": "EPSG:32617",
        "transform": Affine(RES, 0.0, EAST, 0.0, -RES, NORTH),
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(np.stack([h, h + 1000.0, h + 2000.0]))
    with pytest.raises(SourceError, match=r"3 bands.*--band"):
        RasterSource(path)
    with RasterSource(path, band=2) as src:
        assert src.data_range[0] == pytest.approx(float(h.min()) + 1000.0)
    # a height band and an alpha band: the alpha is a mask, not a second choice
    masked = tmp_path / "alpha.tif"
    with rasterio.open(masked, "w", **{**profile, "count": 2}, alpha="YES") as dst:
        dst.write(np.stack([h, np.full_like(h, 255.0)]))
    with rasterio.open(masked) as ds:
        assert ds.colorinterp[1] == ColorInterp.alpha
    with RasterSource(masked) as src:
        assert src.data_range[1] == pytest.approx(float(h.max()))


def test_cli_refuses_absurd_heights_in_one_line_and_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    h = fbm_heights(65, seed=1)
    h[0:5, 0:5] = -3.4e38
    path = _dem(tmp_path / "bad.tif", h)
    out = tmp_path / "view.png"
    code, _, err = run_cli(["render", path, "-o", str(out), "--size", "64x48"], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    assert "--nodata" in err
    assert not out.exists()
    code, _, err = run_cli(
        ["render", path, "-o", str(out), "--size", "64x48", "--nodata", "-3.4e38", "-q"], capsys
    )
    assert code == 0, err
    assert out.exists()
    code, _, err = run_cli(["render", path, "-o", str(out), "--fill", "lava"], capsys)
    assert code == 2
    assert "--fill" in err


def test_fill_parses() -> None:
    assert parse_fill("none").kind == "none"
    assert parse_fill("value:-12.5").height == -12.5
    assert str(parse_fill("value:3")) == "value:3"
    for bad in ("value:", "value:nan", "ellipsoid:1", "zero"):
        with pytest.raises(SourceError):
            parse_fill(bad)


# --- holes ------------------------------------------------------------------------------------

#: The nodata hole, rows and columns of the 257² DEM.
HOLE = (slice(80, 180), slice(90, 170))


@pytest.fixture(scope="module")
def holed(tmp_path_factory: pytest.TempPathFactory) -> str:
    h = fbm_heights(257, seed=4)
    h[HOLE] = -9999.0
    return _dem(tmp_path_factory.mktemp("hole") / "hole.tif", h, nodata=-9999.0)


def _hole_camera(path: str, size: int = 96) -> Camera:
    """Straight down over the hole's centre, seeing only the hole."""
    from pyproj import Transformer

    rows, cols = HOLE
    x = EAST + (cols.start + cols.stop) / 2 * RES
    y = NORTH - (rows.start + rows.stop) / 2 * RES
    lon, lat = Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True).transform(x, y)
    # the hole is 2.4 km wide: from 3 km up a 30° view sees 1.6 km of it
    return Camera(lon, lat, 3000.0, pitch=-90.0, fov_y=30.0, width=size, height=size)


@pytest.mark.gl
@pytest.mark.parametrize("mode", ["cpu", "gpu"])
def test_a_nodata_hole_is_drawn_as_a_hole(holed: str, mode: str) -> None:
    cam = _hole_camera(holed)
    seen = {}
    for fill in ("none", "nearest", "ellipsoid", "value:100"):
        # the terrain alone: the ellipsoid the renderer draws behind it is off
        opts = SceneOptions(background=BACKGROUND, terrain_mode=mode, ellipsoid=False)
        with lodscape.open(holed, opts, fill=fill) as scene:
            rgb, depth = scene.render(cam)
            assert scene.ground_height(cam.lon, cam.lat) is None  # no data here, whatever fill
        seen[fill] = (rgb, depth)
    # none: nothing of the terrain, nothing invented
    rgb, depth = seen["none"]
    sky = np.all(np.abs(rgb.astype(int) - np.array(BACKGROUND) * 255) <= 1, axis=2)
    assert sky.mean() > 0.99
    assert np.isinf(depth).mean() > 0.99
    # and by default the ellipsoid through it, 3 km below the camera, in the no-data grey
    with lodscape.open(holed, SceneOptions(terrain_mode=mode)) as scene:
        rgb, depth = scene.render(cam)
    assert np.isfinite(depth).all()
    assert float(np.median(depth)) == pytest.approx(3000.0, abs=5.0)
    assert np.ptp(rgb.reshape(-1, 3).astype(int), axis=1).max() <= 2
    # nearest: the old stretched surface (hundreds of metres up: 300..1200 m data)
    _, depth = seen["nearest"]
    assert np.isfinite(depth).all()
    assert float(np.median(depth)) < 2800.0
    # the ellipsoid and a level: the stated height, in the no-data grey
    for fill, height in (("ellipsoid", 0.0), ("value:100", 100.0)):
        rgb, depth = seen[fill]
        assert np.isfinite(depth).all()
        assert float(np.median(depth)) == pytest.approx(3000.0 - height, abs=5.0)
        assert np.ptp(rgb.reshape(-1, 3), axis=1).max() <= 2  # grey: no colour means no data


@pytest.mark.gl
def test_a_tileset_keeps_its_fill_and_meshes_its_holes_out(
    holed: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cam = _hole_camera(holed)
    depth_at = {}
    for fill in ("none", "ellipsoid"):
        out = tmp_path / f"{fill}.lods"
        code, _, err = run_cli(["build", holed, "-o", str(out), "--fill", fill, "-q"], capsys)
        assert code == 0, err
        provider = TilesetProvider(out)
        assert provider.manifest["options"]["fill"] == fill
        provider.close()
        code, text, _ = run_cli(["info", str(out)], capsys)
        assert code == 0
        assert f"fill: {fill} where the data has none" in text
        with lodscape.open(out, SceneOptions(background=BACKGROUND, ellipsoid=False)) as scene:
            _, depth = scene.render(cam)
        depth_at[fill] = depth
        # a tileset keeps the fill it was built with
        code, _, err = run_cli(["render", str(out), "--fill", "nearest", "-q"], capsys)
        assert code == 2
        assert "fill it was built with" in err
    assert np.isinf(depth_at["none"]).mean() > 0.99
    # the raw DEM says how much of it is nodata: the hole is 100×80 of 257² pixels
    code, text, _ = run_cli(["info", holed], capsys)
    assert code == 0
    assert f"nodata: {100 * 100 * 80 / 257**2:.1f} % of the raster" in text
    assert float(np.median(depth_at["ellipsoid"])) == pytest.approx(3000.0, abs=5.0)


# --- sea level ----------------------------------------------------------------------------------


def test_heights_below_sea_level_are_water_shaded_by_depth() -> None:
    h = np.repeat(np.linspace(-2000.0, 1000.0, 34)[None, :], 34, axis=0).astype(np.float32)
    ok = np.ones_like(h, bool)
    rgb = tint(h, ok, 30.0, (-2000.0, 1000.0)).astype(int)
    cols = np.linspace(-2000.0, 1000.0, 34)[1:-1]
    wet, dry = cols < 0.0, cols > 0.0
    row = rgb[16]
    assert (row[wet, 2] > row[wet, 0] + 40).all()  # blue under the sea
    assert (row[dry, 2] < row[dry, 0] + 40).all()  # the land ramp above it
    # deeper is darker
    assert row[0].sum() < row[np.flatnonzero(wet)[-1]].sum()
    # no sea: the ramp from the data's lowest
    plain = tint(h, ok, 30.0, (-2000.0, 1000.0), sea_level=None).astype(int)[16]
    assert (plain[wet, 2] < plain[wet, 1]).all()
    # a DEM that stays above the sea is tinted as before
    high = tint(h + 3000.0, ok, 30.0, (1000.0, 4000.0)).astype(int)
    same = tint(h + 3000.0, ok, 30.0, (1000.0, 4000.0), sea_level=None).astype(int)
    np.testing.assert_array_equal(high, same)


# --- the finest level ---------------------------------------------------------------------------


def test_the_finest_level_keeps_its_budget_or_is_twice_as_fine_as_the_data(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a coarse (3 km), rough topo-bathymetric DEM: the level whose texels match its pixels
    # misses its one-texel budget
    h = (fbm_heights(129, seed=3, relief=6000.0) - 3300.0).astype(np.float32)
    dem = write_dem(
        str(tmp_path / "coarse.tif"), h, crs="EPSG:4326", west=-30.0, north=45.0, res=0.03
    )
    out = tmp_path / "coarse.lods"
    report = build([dem], out)
    _, tex, zmax = report.levels
    assert zmax > tex + 2  # went below the planned finest level
    provider = TilesetProvider(out)
    res = float(provider.manifest["resolution_merc"])
    assert provider.manifest["levels"]["zmax"] == zmax
    provider.close()
    with closing(sqlite3.connect(out)) as db:
        for z in (zmax - 1, zmax):
            rows = db.execute("SELECT x, y, error FROM terrain WHERE z = ?", (z,)).fetchall()
            # the default budget: one of the level's 256 texels a tile
            over = [(x, y) for x, y, e in rows if e > level_budget(1.0, 256, z, y) * (1 + 1e-9)]
            if z == zmax - 1:
                # the level above: children exactly under the tiles over budget
                kids = {
                    (x >> 1, y >> 1)
                    for x, y, _ in db.execute(
                        "SELECT x, y, error FROM terrain WHERE z = ?", (zmax,)
                    )
                }
                assert kids == set(over)
            elif over:
                # what is left is the data's own relief: the grid is twice as fine as the data
                assert 2.0 * 6378137.0 * math.pi / (1 << z) / TIN_GRID <= res / 2.0
    code, text, _ = run_cli(["info", str(out)], capsys)
    assert code == 0
    assert "over their budget" in text
    # an orthophoto finer than the refined terrain: the stored surface is cut finer under it
    # (below leaves too), the layer worn at its own level, no holes
    from _synthetic import write_ortho

    rng = np.random.default_rng(0)
    ortho = write_ortho(
        str(tmp_path / "ortho.tif"),
        rng.integers(0, 255, (600, 600, 3), dtype=np.uint8),
        crs="EPSG:4326",
        west=-29.9,
        north=41.9,
        res=0.0005,
    )
    opts = SceneOptions(background=MAGENTA, ellipsoid=False)
    with lodscape.open(out, opts, imagery=[ortho]) as scene:
        from lodscape.imagery.raster import RasterImagery

        finest = RasterImagery(ortho).max_zoom
        assert finest > zmax
        assert scene.tree.zmax == finest
        # over a tile of the level above the finest that has no children
        import mercantile

        t = mercantile.tile(-29.75, 41.75, zmax - 1)
        stored = TilesetProvider(out)
        base = stored.tree.level(zmax - 1)
        stored.close()
        assert base.leaf is not None
        assert base.leaf[t.y - base.y0, t.x - base.x0]
        g = scene.ground_height(-29.75, 41.75)
        assert g is not None
        cam = Camera(-29.75, 41.75, max(g, 0.0) + 1500.0, pitch=-90.0, width=96, height=96)
        rgb, _ = scene.render(cam)
        assert not np.all(rgb == (255, 0, 255), axis=2).any()
        sel = scene.view.previous
        assert sel is not None
        assert int((sel.z - sel.layer_up[0]).max()) == finest
    # tiles without children are never split: close up, no holes
    with lodscape.open(out, SceneOptions(background=MAGENTA, ellipsoid=False)) as scene:
        b = scene.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        g = scene.ground_height(lon, lat)
        assert g is not None
        for cam in (
            Camera(lon, lat, g + 3000.0, pitch=-90.0, width=160, height=120),
            Camera(lon, lat - 0.2, max(g, 0.0) + 6000.0, pitch=-20.0, width=160, height=120),
        ):
            rgb, _ = scene.render(cam)
            magenta = np.all(rgb == (255, 0, 255), axis=2)
            below = np.maximum.accumulate(~magenta, axis=0)
            assert int((magenta & below).sum()) == 0


@pytest.mark.gl
@pytest.mark.parametrize("mode", ["cpu", "gpu"])
def test_the_underside_seen_from_a_hole_is_a_dark_curtain(holed: str, mode: str) -> None:
    # from inside the hole, below the data around it, looking level: the terrain's underside
    above = _hole_camera(holed)
    low = Camera(above.lon, above.lat, 150.0, pitch=5.0, fov_y=50.0, width=160, height=100)
    opts = SceneOptions(background=BACKGROUND, terrain_mode=mode, ellipsoid=False)
    with lodscape.open(holed, opts) as scene:
        rgb, depth = scene.render(low)
        seen = np.isfinite(depth)
        assert seen.mean() > 0.05
        dark = np.all(np.abs(rgb.astype(int) - np.array([41, 41, 46])) <= 2, axis=2)
        assert dark[seen].mean() > 0.9
        # from above, the same terrain wears its imagery: no curtain
        rgb, depth = scene.render(above.moved(lat=above.lat - 0.03))
        dark = np.all(np.abs(rgb.astype(int) - np.array([41, 41, 46])) <= 2, axis=2)
        assert dark[np.isfinite(depth)].mean() < 0.01


def test_a_sea_stored_as_exactly_zero_is_water(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """SRTM-style coasts: the sea is 0 m exactly. Where such a flat reaches the data's edge it is
    sea (said once); a level area at 0 m inside the land, and land just above 0, are land."""
    from rasterio.warp import transform as to_ll

    from lodscape.geo.tiles import lonlat_to_merc, tile
    from lodscape.imagery.tint import WATER, TintImagery

    h = fbm_heights(129, seed=3).astype(np.float32) + 50.0  # land, 50..950 m
    h[90:, :] = 0.0  # the sea: the south part, to the edge
    h[20:30, 20:30] = 0.0  # a level patch inland: land
    path = _dem(tmp_path / "coast.tif", h)
    with RasterSource(path) as src:
        assert src.sea_share(0.0) == pytest.approx(39 * 129 / 129**2, rel=0.01)
        imagery = TintImagery(src, (0.0, 1000.0), sea_level=0.0)
        shallows = WATER[0, 1:4]
        for (row, col), wet in (((110, 64), True), ((25, 25), False), ((60, 64), False)):
            (lon,), (lat,) = to_ll(
                "EPSG:32617", "EPSG:4326", [EAST + (col + 0.5) * RES], [NORTH - (row + 0.5) * RES]
            )
            t = tile(lon, lat, 15)
            rgb = imagery.rgb(t.z, t.x, t.y)
            b = lonlat_to_merc([lon], [lat])
            left, bottom, right, top = (float(v) for v in imagery.sample_bounds(t.z, t.x, t.y))
            n = imagery.tile_size
            i = int((top - float(b[1][0])) / (top - bottom) * n)
            j = int((float(b[0][0]) - left) / (right - left) * n)
            px = rgb[min(i, n - 1), min(j, n - 1)].astype(float)
            # water: blue over red, the shallows' hue; land: the ramp's greens and browns
            assert (px[2] > px[0] + 30) == wet, (row, col, px)
            if wet:
                assert np.allclose(px / px.max(), shallows / shallows.max(), atol=0.08)
    code, _, err = run_cli(["render", path, "--size", "64x48", "-o", str(tmp_path / "o.png")],
                           capsys)  # fmt: skip
    assert code == 0, err
    assert err.count("drawn as sea") == 1, err
    code, _, err = run_cli(
        ["render", path, "--sea-level", "none", "--size", "64x48", "-o", str(tmp_path / "o.png")],
        capsys,
    )
    assert "drawn as sea" not in err
