"""Height sources over real GeoTIFFs: CRSs, overviews, nodata filling, determinism, bad input."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rasterio
from numpy.typing import NDArray
from pyproj import Transformer
from rasterio.enums import Resampling
from rasterio.transform import Affine

from _synthetic import run_cli
from lodscape.data import sample_dem_path
from lodscape.errors import SourceError
from lodscape.geo.tiles import (
    ORIGIN,
    Bbox,
    Tile,
    lonlat_to_merc,
    merc_to_lonlat,
    tile,
    tile_size,
    xy_bounds,
)
from lodscape.terrain import ArraySource, HeightSource, RasterSource

LON0, LAT0 = -81.0, 35.0  # on UTM zone 17's central meridian


def from_origin(west: float, north: float, xsize: float, ysize: float) -> Affine:
    """North-up transform (rasterio's own helper warns about ``*`` on newer affine releases)."""
    return Affine(xsize, 0.0, west, 0.0, -ysize, north)


def surface(lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
    """A smooth paraboloid in lon/lat, 820..1000 m over the test area."""
    return 1000.0 - 4000.0 * ((lon - LON0) ** 2 + (lat - LAT0) ** 2)


def write_tif(
    path: Path,
    data: NDArray[Any],
    transform: Affine,
    crs: str | None = "EPSG:4326",
    nodata: float | None = None,
    **extra: Any,
) -> Path:
    """One-band GeoTIFF of ``data`` (row 0 north)."""
    profile: dict[str, Any] = {
        "driver": "GTiff",
        "width": data.shape[1],
        "height": data.shape[0],
        "count": 1,
        "dtype": data.dtype.name,
        "transform": transform,
        **extra,
    }
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(data, 1)
    return path


def surface_raster(path: Path, crs: str, pixel: float) -> Path:
    """The paraboloid around (LON0, LAT0) ±0.2°, as float32 pixels of ``pixel`` CRS units."""
    to_crs = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    to_ll = Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    lon_c = np.array([LON0 - 0.2, LON0 + 0.2, LON0 - 0.2, LON0 + 0.2])
    lat_c = np.array([LAT0 - 0.2, LAT0 - 0.2, LAT0 + 0.2, LAT0 + 0.2])
    xs, ys = to_crs.transform(lon_c, lat_c)
    west, north = math.floor(min(xs) / pixel) * pixel, math.ceil(max(ys) / pixel) * pixel
    cols = math.ceil((max(xs) - west) / pixel)
    rows = math.ceil((north - min(ys)) / pixel)
    transform = from_origin(west, north, pixel, pixel)
    jj, ii = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    lon, lat = to_ll.transform(west + jj * pixel, north - ii * pixel)
    return write_tif(path, surface(lon, lat).astype(np.float32), transform, crs)


def test_crs_agree_on_one_surface(tmp_path: Path) -> None:
    sources = [
        RasterSource(surface_raster(tmp_path / "ll.tif", "EPSG:4326", 0.001)),
        RasterSource(surface_raster(tmp_path / "utm.tif", "EPSG:32617", 100.0)),
        RasterSource(surface_raster(tmp_path / "merc.tif", "EPSG:3857", 120.0)),
    ]
    rng = np.random.default_rng(1)
    lon = rng.uniform(LON0 - 0.15, LON0 + 0.15, (20, 30))
    lat = rng.uniform(LAT0 - 0.15, LAT0 + 0.15, (20, 30))
    xm, ym = lonlat_to_merc(lon, lat)
    for src in sources:
        b = src.bounds_merc
        assert b.left < xm.min()
        assert xm.max() < b.right
        assert b.bottom < ym.min() < ym.max() < b.top
        h, valid = src.sample(xm, ym, src.resolution_merc)
        assert h.shape == xm.shape
        assert h.dtype == np.float32
        assert valid.shape == xm.shape
        assert valid.all()
        np.testing.assert_allclose(h, surface(lon, lat), atol=0.02)
        src.close()
    # the EPSG:4326 raster's Web Mercator pixel: 0.001° of longitude scaled by 1/cos(lat)
    merc_pixel = math.radians(0.001) * 6378137.0
    assert sources[0].resolution_merc == pytest.approx(merc_pixel, rel=0.01)
    assert "32617" in sources[1].crs_wkt or "UTM zone 17N" in sources[1].crs_wkt


def test_array_source_matches_raster_bit_for_bit(tmp_path: Path) -> None:
    path = surface_raster(tmp_path / "utm.tif", "EPSG:32617", 100.0)
    with rasterio.open(path) as ds:
        data, transform, crs = ds.read(1), ds.transform, ds.crs
    ras, arr = RasterSource(path), ArraySource(data, transform, crs=crs)
    assert arr.name == "array"
    assert ras.name == str(path)
    assert arr.bounds_merc == ras.bounds_merc
    assert arr.resolution_merc == ras.resolution_merc
    b = ras.bounds_merc
    rng = np.random.default_rng(6)
    xm = rng.uniform(b.left - 1000.0, b.right + 1000.0, 500)
    ym = rng.uniform(b.bottom - 1000.0, b.top + 1000.0, 500)
    for spacing in (50.0, 400.0, 3000.0):
        h1, v1 = ras.sample(xm, ym, spacing)
        h2, v2 = arr.sample(xm, ym, spacing)
        assert np.array_equal(h1, h2), spacing
        assert np.array_equal(v1, v2), spacing


def test_overviews_are_used_at_coarse_spacing(tmp_path: Path) -> None:
    path = write_tif(
        tmp_path / "ov.tif",
        np.full((256, 256), 100, dtype=np.int16),
        from_origin(0.0, 256 * 30.0, 30.0, 30.0),
        "EPSG:3857",
        tiled=True,
        blockxsize=64,
        blockysize=64,
    )
    with rasterio.open(path, "r+") as ds:
        ds.build_overviews([2, 4, 8], Resampling.average)
    # the base band changes after the overviews were built: a read tells which one it came from
    with rasterio.open(path, "r+") as ds:
        ds.write(np.zeros((256, 256), dtype=np.int16), 1)
    src = RasterSource(path)
    assert src.resolution_merc == pytest.approx(30.0)
    xm, ym = np.array([2000.0, 5000.0]), np.array([3000.0, 6000.0])
    h, valid = src.sample(xm, ym, 30.0)
    assert valid.all()
    assert np.all(h == 0.0)
    h, valid = src.sample(xm, ym, 4.5 * 30.0)  # level 2: the file's 4× overview
    assert valid.all()
    assert np.all(h == 100.0)
    h, valid = src.sample(xm, ym, 16 * 30.0)  # no 16× overview: block means of the base band
    assert valid.all()
    assert np.all(h == 0.0)
    src.close()


@pytest.mark.parametrize("shape", [(64, 80), (1300, 2100)])
def test_block_means_are_aligned_to_the_pixel_grid(shape: tuple[int, int]) -> None:
    # (1300, 2100) is over the coarse size: level 1 reads the array, level 3 the cached sums
    rng = np.random.default_rng(5)
    data = rng.integers(0, 1000, shape).astype(np.float32)
    src = ArraySource(data, from_origin(1000.0, 9000.0, 10.0, 10.0))
    for k in (1, 2, 3, 5):
        f = 2**k
        # pixel centres of level k: each is the centre of an aligned f×f block of the source
        rows, cols = shape[0] // f, shape[1] // f  # whole blocks only
        r = np.minimum([0, 1, 3, rows // 2, rows - 1], rows - 1)
        c = np.minimum([0, 2, 5, cols // 2, cols - 1], cols - 1)
        xm, ym = 1000.0 + 10.0 * f * (c + 0.5), 9000.0 - 10.0 * f * (r + 0.5)
        h, valid = src.sample(xm, ym, f * 10.0)
        assert valid.all()
        expected = [
            data[i * f : (i + 1) * f, j * f : (j + 1) * f].mean() for i, j in zip(r, c, strict=True)
        ]
        np.testing.assert_allclose(h, expected, atol=1e-3, err_msg=f"level {k}")
    # and at full resolution a pixel centre returns the pixel
    h, _ = src.sample(np.array([1000.0 + 10.0 * 20.5]), np.array([9000.0 - 10.0 * 12.5]), 10.0)
    assert h[0] == data[12, 20]


@pytest.mark.parametrize("kind", ["int16", "float32-nan"])
def test_nodata_holes_are_filled_without_spikes(tmp_path: Path, kind: str) -> None:
    rows, cols = 120, 150
    ii, jj = np.mgrid[0:rows, 0:cols]
    heights = 300.0 + 100.0 * np.sin(ii / 20.0) * np.cos(jj / 25.0)  # 200..400 m
    hole = (abs(ii - 60) < 8) & (abs(jj - 70) < 10)
    corner = (ii < 15) & (jj < 20)
    if kind == "int16":
        data = np.round(heights).astype(np.int16)
        data[hole | corner] = -9999
        nodata: float | None = -9999
    else:
        data = heights.astype(np.float32)
        data[hole | corner] = np.nan
        nodata = None
    path = write_tif(
        tmp_path / "holes.tif", data, from_origin(-80.0, 40.0, 1e-3, 1e-3), nodata=nodata
    )
    src = RasterSource(path)
    b = src.bounds_merc
    pad = 0.1 * (b.right - b.left)
    grid = Bbox(b.left - pad, b.bottom - pad, b.right + pad, b.top + pad)
    for shape in ((211, 233), (40, 37)):
        h, valid = src.read(grid, shape)
        assert np.isfinite(h).all()
        assert h.min() >= 199.0
        assert h.max() <= 401.0
        assert not valid.all()
        assert valid.any()
    # inside the hole and the corner: invalid; away from them inside the raster: valid
    lon = np.array([-80.0 + 70.5e-3, -80.0 + 5e-3, -80.0 + 120e-3, -80.0 - 0.01])
    lat = np.array([40.0 - 60.5e-3, 40.0 - 5e-3, 40.0 - 100e-3, 40.0 - 0.05])
    xm, ym = lonlat_to_merc(lon, lat)
    h, valid = src.sample(xm, ym, src.resolution_merc)
    assert valid.tolist() == [False, False, True, False]
    assert np.all((h >= 199.0) & (h <= 401.0))
    # covers: the raster's extent, nodata holes included (the terrain ends only at the edge)
    assert src.covers(xm, ym).tolist() == [True, True, True, False]
    assert src.covers(xm[:, None], ym[None, :]).shape == (4, 4)
    # a point outside takes the height of the nearest edge of the coarse overview
    h_out, _ = src.sample(*lonlat_to_merc([-80.0 - 0.05], [40.0 - 0.06]), src.resolution_merc)
    h_edge, _ = src.sample(*lonlat_to_merc([-80.0], [40.0 - 0.06]), 1e9)
    assert abs(float(h_out[0]) - float(h_edge[0])) < 30.0


@pytest.mark.parametrize("spacing_factor", [1.0, 2.5, 9.0])
def test_adjacent_windows_share_bit_identical_edges(spacing_factor: float) -> None:
    rng = np.random.default_rng(2)
    rows, cols = 300, 340
    data = rng.normal(500.0, 50.0, (rows, cols)).astype(np.float32)
    data[140:150, :] = np.nan  # nodata running along the shared edges
    data[:, 200:203] = np.nan
    src = ArraySource(data, from_origin(-8.0e6, 4.0e6, 7.3, 7.3), crs="EPSG:3857")
    b = src.bounds_merc
    n = 33
    size = spacing_factor * src.resolution_merc * (n - 1)
    x0, y0 = b.left + 0.37 * (b.right - b.left - 2 * size), b.top - 0.41 * (b.top - b.bottom)
    west = Bbox(x0, y0 - size, x0 + size, y0)
    east = Bbox(x0 + size, y0 - size, x0 + 2 * size, y0)
    south = Bbox(x0, y0 - 2 * size, x0 + size, y0 - size)
    hw, vw = src.read(west, (n, n))
    he, ve = src.read(east, (n, n))
    hs, vs = src.read(south, (n, n))
    assert np.array_equal(hw[:, -1].view(np.uint32), he[:, 0].view(np.uint32))
    assert np.array_equal(vw[:, -1], ve[:, 0])
    assert np.array_equal(hw[-1, :].view(np.uint32), hs[0, :].view(np.uint32))
    assert np.array_equal(vw[-1, :], vs[0, :])
    assert not (vw.all() and ve.all() and vs.all())  # the nodata bands did reach the windows


def test_sample_is_independent_of_the_window_across_levels() -> None:
    # over 1024 px wide: level 1 reads the array and level 4 comes from the cached coarse sums
    rng = np.random.default_rng(3)
    data = rng.normal(0.0, 100.0, (1300, 2100)).astype(np.float32)
    data[rng.random(data.shape) < 0.01] = -32768
    src = ArraySource(data, from_origin(500000.0, 4000000.0, 10.0, 10.0), "EPSG:32617", -32768)
    b = src.bounds_merc
    xm = rng.uniform(b.left - 100.0, b.right + 100.0, 400)
    ym = rng.uniform(b.bottom - 100.0, b.top + 100.0, 400)
    for k in (0, 1, 3, 4, 6):
        spacing = src.resolution_merc * 2**k * 1.01
        h_all, v_all = src.sample(xm, ym, spacing)
        for part in np.array_split(np.arange(400), 7):
            h, v = src.sample(xm[part], ym[part], spacing)
            assert np.array_equal(h.view(np.uint32), h_all[part].view(np.uint32)), k
            assert np.array_equal(v, v_all[part])
        one, _ = src.sample(xm[17:18], ym[17:18], spacing)
        assert one.view(np.uint32)[0] == h_all.view(np.uint32)[17]


def test_osm_tile_neighbours_share_edges_on_the_sample_dem() -> None:
    src = RasterSource(sample_dem_path())
    t = tile(-84.25, 36.6, 12)
    right = Tile(t.x + 1, t.y, t.z)
    h1, _ = src.read(xy_bounds(t), (17, 17))
    h2, _ = src.read(xy_bounds(right), (17, 17))
    assert np.array_equal(h1[:, -1], h2[:, 0])
    src.close()


def test_concurrent_samples_match_serial() -> None:
    src = RasterSource(sample_dem_path())
    b = src.bounds_merc
    boxes = [
        Bbox(b.left + i * 800.0, b.bottom + i * 500.0, b.left + i * 800.0 + 9000.0, b.top)
        for i in range(16)
    ]
    serial = [src.read(box, (65, 65))[0] for box in boxes]
    with ThreadPoolExecutor(8) as pool:
        parallel = list(pool.map(lambda box: src.read(box, (65, 65))[0], boxes))
    assert all(np.array_equal(a, c) for a, c in zip(serial, parallel, strict=True))
    src.close()


def test_scale_and_offset_are_applied(tmp_path: Path) -> None:
    data = np.arange(16, dtype=np.int16).reshape(4, 4) * 10
    path = write_tif(tmp_path / "scaled.tif", data, from_origin(10.0, 50.0, 0.01, 0.01))
    with rasterio.open(path, "r+") as ds:
        ds.scales = (0.5,)
        ds.offsets = (100.0,)
    src = RasterSource(path)
    xm, ym = lonlat_to_merc([10.0 + 0.025], [50.0 - 0.015])  # the centre of pixel (1, 2)
    h, valid = src.sample(xm, ym, 1.0)
    assert valid[0]
    assert h[0] == pytest.approx(data[1, 2] * 0.5 + 100.0, abs=1e-3)


def test_sample_dem() -> None:
    src: HeightSource = RasterSource(sample_dem_path())
    b = src.bounds_merc
    x, y = lonlat_to_merc(-84.25, 36.6)
    assert b.left < x < b.right
    assert b.bottom < y < b.top
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    assert w == pytest.approx(-84.41375)
    assert n == pytest.approx(36.7329167, abs=1e-6)
    assert e == pytest.approx(-84.0779167, abs=1e-6)
    assert s == pytest.approx(36.44625)
    h, valid = src.read(b, (200, 240))
    assert valid.all()
    assert h.min() >= 236.0
    assert h.max() <= 1076.0
    assert h.max() - h.min() > 500.0
    hp, vp = src.sample(np.array([x]), np.array([y]), 100.0)
    assert vp[0]
    assert 236.0 <= hp[0] <= 1076.0
    assert "WGS 84" in src.crs_wkt
    src.close()
    with pytest.raises(SourceError, match="closed"):
        src.sample(np.array([x]), np.array([y]), 100.0)


# --- bad input --------------------------------------------------------------------------


def _one_line_error(path: Path | str, match: str) -> None:
    """Opening ``path`` raises one SourceError line that starts with the path."""
    with pytest.raises(SourceError) as info:
        RasterSource(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ")
    assert "\n" not in msg
    assert match in msg, msg


def test_missing_file(tmp_path: Path) -> None:
    _one_line_error(tmp_path / "nope.tif", "no such file")


def test_text_file(tmp_path: Path) -> None:
    path = tmp_path / "notes.tif"
    path.write_text("these are not heights\n" * 20)
    _one_line_error(path, "not a raster that GDAL can read (")


def test_truncated_geotiff(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    data = rng.normal(100.0, 10.0, (512, 512)).astype(np.float32)
    path = write_tif(tmp_path / "cut.tif", data, from_origin(10.0, 50.0, 1e-3, 1e-3))
    blob = path.read_bytes()
    path.write_bytes(blob[: len(blob) // 2])

    def open_and_read() -> None:
        src = RasterSource(path)  # the coarse overview reads every block at open
        src.read(src.bounds_merc, (64, 64))

    with pytest.raises(SourceError) as info:
        open_and_read()
    msg = str(info.value)
    assert msg.startswith(f"{path}: ")
    assert "\n" not in msg
    assert "read failed: " in msg or "not a raster that GDAL can read" in msg


def test_one_pixel(tmp_path: Path) -> None:
    path = write_tif(tmp_path / "one.tif", np.ones((1, 1), np.float32), from_origin(0, 1, 1, 1))
    _one_line_error(path, "raster is 1×1 pixels; need at least 2×2")


def test_all_nodata(tmp_path: Path) -> None:
    data = np.full((8, 9), -9999, dtype=np.int16)
    path = write_tif(tmp_path / "empty.tif", data, from_origin(0, 1, 0.1, 0.1), nodata=-9999)
    _one_line_error(path, "every pixel is nodata")


def test_no_crs(tmp_path: Path) -> None:
    data = np.ones((8, 9), np.float32)
    path = write_tif(tmp_path / "nocrs.tif", data, from_origin(0, 1, 0.1, 0.1), crs=None)
    _one_line_error(path, "raster has no CRS; georeference it first (e.g. gdal_edit.py -a_srs")


def test_cf_longitudes_and_latitudes_are_wgs84(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A netCDF grid with CF's longitude and latitude axes (degrees_east, degrees_north) and no
    grid mapping is read as WGS 84, as CF says, and said once; one whose axes are not is
    refused, with a fix that works for its format (gdal_edit.py edits GeoTIFFs alone)."""
    xr = pytest.importorskip("xarray")
    rng = np.random.default_rng(3)
    lon = np.arange(10.005, 10.4, 0.01)
    lat = np.arange(45.005, 45.3, 0.01)
    z = rng.uniform(100.0, 900.0, (lat.size, lon.size)).astype(np.float32)
    ds = xr.Dataset({"elevation": (("lat", "lon"), z)}, coords={"lat": lat, "lon": lon})
    ds.lon.attrs["units"] = "degrees_east"
    ds.lat.attrs["units"] = "degrees_north"
    path = tmp_path / "grid.nc"
    ds.to_netcdf(path, engine="scipy")
    try:
        source = RasterSource(str(path))
    except SourceError as exc:
        if "not a raster that GDAL can read" in str(exc):
            pytest.skip("GDAL without its netCDF driver")
        raise
    with source:
        assert source.crs_note is not None
        assert "EPSG:4326" in source.crs_note
        w, s = merc_to_lonlat(source.bounds_merc.left, source.bounds_merc.bottom)
        assert float(w) == pytest.approx(10.0, abs=1e-6)
        assert float(s) == pytest.approx(45.0, abs=1e-6)
        # a cell's centre reads its own value (the file's rows run south to north)
        xm, ym = lonlat_to_merc([lon[7]], [lat[3]])
        h, ok = source.sample(xm, ym, source.resolution_merc)
        assert ok.all()
        assert float(h[0]) == pytest.approx(float(z[3, 7]), abs=1e-3)
    code, _, err = run_cli(["info", str(path)], capsys)
    assert code == 0, err
    assert err.count("read as WGS 84 (EPSG:4326)") == 1
    ds.lon.attrs["units"] = "m"
    ds.lat.attrs["units"] = "m"
    plain = tmp_path / "plain.nc"
    ds.to_netcdf(plain, engine="scipy")
    _one_line_error(
        plain,
        f"raster has no CRS; georeference it first (e.g. gdal_translate -a_srs EPSG:4326 "
        f"{plain} plain.tif)",
    )


def test_ground_control_points(tmp_path: Path) -> None:
    """A raster georeferenced by ground control points alone reads as the same raster with its
    geotransform where an affine map fits them (said once); where none does, it is refused
    with the warp that grids it."""
    import warnings

    import rasterio.errors
    from rasterio.control import GroundControlPoint

    rng = np.random.default_rng(8)
    data = rng.uniform(100.0, 900.0, (60, 80)).astype(np.float32)
    grid = Affine(9.0, 2.0, 700_000.0, 1.5, -10.0, 4_070_000.0)  # turned and sheared
    plain = write_tif(tmp_path / "plain.tif", data, grid, crs="EPSG:32617")

    def with_gcps(name: str, shift: float) -> Path:
        pts = []
        for i, (c, r) in enumerate([(0, 0), (80, 0), (0, 60), (80, 60), (40, 30)]):
            x, y = grid.a * c + grid.b * r + grid.c, grid.d * c + grid.e * r + grid.f
            if i == 4:
                x += shift * grid.a
            pts.append(GroundControlPoint(row=r, col=c, x=x, y=y))
        path = tmp_path / name
        profile = {"driver": "GTiff", "height": 60, "width": 80, "count": 1, "dtype": "float32"}
        with warnings.catch_warnings():
            # rasterio warns of a file with no geotransform before its points are set
            warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
            with rasterio.open(path, "w", **profile) as dst:
                dst.write(data, 1)
                dst.gcps = (pts, rasterio.crs.CRS.from_epsg(32617))
        return path

    with RasterSource(str(plain)) as a, RasterSource(str(with_gcps("gcps.tif", 0.0))) as b:
        assert a.crs_note is None
        assert b.crs_note is not None
        assert "5 ground control points" in b.crs_note
        assert tuple(b.bounds_merc) == pytest.approx(tuple(a.bounds_merc), abs=1e-3)
        bx = a.bounds_merc
        xs = np.linspace(bx.left, bx.right, 61)
        ys = np.linspace(bx.top, bx.bottom, 47)
        ha, va = a.sample_grid(xs, ys, a.resolution_merc)
        hb, vb = b.sample_grid(xs, ys, b.resolution_merc)
        np.testing.assert_array_equal(vb, va)
        np.testing.assert_allclose(hb[vb], ha[va], atol=1e-2)
    _one_line_error(
        with_gcps("bent.tif", 3.0),
        "ground control points that no affine map fits (off by up to",
    )
    # rational polynomial coefficients alone (a satellite scene's): orthorectified first
    from rasterio.rpc import RPC

    rpcs = RPC(
        height_off=500.0, height_scale=500.0, lat_off=36.7, lat_scale=0.05,
        line_den_coeff=[1.0] + [0.0] * 19, line_num_coeff=[0.0, 0.0, -1.0] + [0.0] * 17,
        line_off=30.0, line_scale=30.0,
        long_off=-84.2, long_scale=0.05, samp_den_coeff=[1.0] + [0.0] * 19,
        samp_num_coeff=[0.0, 1.0] + [0.0] * 18, samp_off=40.0, samp_scale=40.0,
    )  # fmt: skip
    path = tmp_path / "rpc.tif"
    profile = {"driver": "GTiff", "height": 60, "width": 80, "count": 1, "dtype": "float32"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", rasterio.errors.NotGeoreferencedWarning)
        with rasterio.open(path, "w", **profile) as dst:
            dst.write(data, 1)
            dst.rpcs = rpcs
    _one_line_error(path, "georeferenced by rational polynomial coefficients (RPCs) alone")


def test_outside_web_mercator(tmp_path: Path) -> None:
    data = np.ones((10, 10), np.float32)
    path = write_tif(tmp_path / "pole.tif", data, from_origin(0.0, 89.9, 0.1, 0.1))
    _one_line_error(path, "outside Web Mercator's latitude range")


def test_across_the_antimeridian(tmp_path: Path) -> None:
    # Fiji: 179.9°E to 180.1°E. Web Mercator tiles cannot span 180°: a clear refusal, not a
    # box the whole world wide (a camera once came out at latitude -275°)
    data = np.ones((64, 64), np.float32)
    path = write_tif(tmp_path / "fiji.tif", data, from_origin(179.9, -16.5, 0.004, 0.004))
    _one_line_error(path, "crosses the antimeridian")
    # round a pole the longitudes wind all the way: that is not a crossing
    pole = write_tif(
        tmp_path / "arctic.tif",
        data,
        from_origin(-1_024_000.0, 1_024_000.0, 32_000.0, 32_000.0),
        crs="EPSG:3413",
    )
    with RasterSource(str(pole)) as source:
        assert source.bounds_merc.right - source.bounds_merc.left > 3.9e7


@pytest.mark.parametrize("turn", [360.0, -360.0])
def test_longitudes_a_whole_turn_off(tmp_path: Path, turn: float) -> None:
    """Data kept in 0..360° longitudes (or below -180°) wholly on one side of the antimeridian
    is where it is a turn away: the same footprint, heights and pixels as the same raster in
    -180..180° (it was refused as crossing the antimeridian)."""
    rng = np.random.default_rng(4)
    data = rng.uniform(0.0, 900.0, (48, 64)).astype(np.float32)
    west = -170.0 if turn > 0 else 170.0
    plain = write_tif(tmp_path / "plain.tif", data, from_origin(west, 58.0, 0.01, 0.01))
    turned = write_tif(tmp_path / "turned.tif", data, from_origin(west + turn, 58.0, 0.01, 0.01))
    with RasterSource(str(plain)) as a, RasterSource(str(turned)) as b:
        assert tuple(b.bounds_merc) == pytest.approx(tuple(a.bounds_merc), abs=1e-6)
        assert b.resolution_merc == pytest.approx(a.resolution_merc)
        bx = a.bounds_merc
        xs = np.linspace(bx.left, bx.right, 97)
        ys = np.linspace(bx.top, bx.bottom, 71)
        ha, va = a.sample_grid(xs, ys, a.resolution_merc)
        hb, vb = b.sample_grid(xs, ys, b.resolution_merc)
        assert va.mean() > 0.9
        np.testing.assert_array_equal(vb, va)
        np.testing.assert_allclose(hb[vb], ha[va], atol=1e-3)
        box = Bbox(bx.left, bx.bottom, (bx.left + bx.right) / 2, bx.top)
        pa = np.concatenate([np.stack(p, 1) for p in a.pixels_in(box)])
        pb = np.concatenate([np.stack(p, 1) for p in b.pixels_in(box)])
        assert pa.shape == pb.shape
        assert pa.shape[0] > 500
        np.testing.assert_allclose(pb, pa, atol=1e-3)


@pytest.mark.parametrize("west", [0.0, -180.5])
def test_a_whole_world_read_from_its_first_turn(tmp_path: Path, west: float) -> None:
    """A whole world in 0..360° longitudes, or -180..180° with a pixel's overlap, spans the
    world (it was refused as crossing the antimeridian), and every longitude reads its pixel
    at its first turn from the raster's west edge, across 0° and 180° alike."""
    rng = np.random.default_rng(6)
    cols = 721 if west < -180.0 else 720
    data = rng.uniform(-4000.0, 5000.0, (300, cols)).astype(np.float32)
    path = write_tif(tmp_path / "world.tif", data, from_origin(west, 75.0, 0.5, 0.5))
    with RasterSource(str(path)) as source:
        b = source.bounds_merc
        assert (b.left, b.right) == (-ORIGIN, ORIGIN)
        r = rng.integers(0, 300, 400)
        c = rng.integers(0, cols, 400)
        lon = np.mod(west + (c + 0.5) * 0.5 + 180.0, 360.0) - 180.0
        lat = 75.0 - (r + 0.5) * 0.5
        first = np.floor((np.mod(lon - west, 360.0)) / 0.5).astype(int)  # its first turn
        xm, ym = lonlat_to_merc(lon, lat)
        h, valid = source.sample(xm, ym, source.resolution_merc)
        assert valid.all()
        np.testing.assert_array_equal(h, data[r, first])


def test_array_source_errors() -> None:
    with pytest.raises(SourceError, match=r"^array: .*not invertible"):
        ArraySource(np.ones((4, 4)), Affine(0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(SourceError, match=r"^array: every pixel is nodata"):
        ArraySource(np.full((4, 4), np.nan), from_origin(0, 0, 1, 1))
    with pytest.raises(SourceError, match=r"^array: raster is 5×1 pixels"):
        ArraySource(np.ones((1, 5)), from_origin(0, 0, 1, 1))
    with pytest.raises(SourceError, match=r"^array: unusable CRS"):
        ArraySource(np.ones((4, 4)), from_origin(0, 0, 1, 1), crs="EPSG:999999")


@pytest.mark.parametrize("crs", ["EPSG:32617", "EPSG:4326", "EPSG:3857"])
def test_sample_grid_matches_sample_within_a_thousandth_of_a_pixel(crs: str) -> None:
    """The lattice projection of large grids (the tile tree's build) stays within its stated
    tolerance of the exact per-point projection."""
    rng = np.random.default_rng(5)
    data = rng.normal(0.0, 1.0, (600, 700)).cumsum(axis=0).cumsum(axis=1).astype(np.float32)
    pixel = 1e-4 if crs == "EPSG:4326" else 10.0
    west, north = (-81.2, 35.1) if crs == "EPSG:4326" else (500000.0, 3900000.0)
    if crs == "EPSG:3857":
        west, north = -9.0e6, 4.2e6
    src = ArraySource(data, from_origin(west, north, pixel, pixel), crs)
    b = src.bounds_merc
    xs = np.linspace(b.left, b.right, 513)
    ys = np.linspace(b.top, b.bottom, 385)
    xx, yy = np.meshgrid(xs, ys)
    h, v = src.sample(xx, yy, src.resolution_merc)
    hg, vg = src.sample_grid(xs, ys, src.resolution_merc)
    assert hg.shape == (385, 513)
    # a height moves by at most the pixel shift times the steepest rise between pixels
    rise = max(np.abs(np.diff(data, axis=0)).max(), np.abs(np.diff(data, axis=1)).max())
    assert np.abs(hg - h).max() <= 1e-3 * rise * 2 + 1e-4
    assert np.mean(v != vg) < 1e-3
    # the grid's edges are projected exactly: a neighbouring grid sharing one (a tile's
    # neighbour, which may choose another lattice step) agrees with it to the bit
    for got, want in ((hg, h), (vg, v)):
        for edge in (np.s_[0], np.s_[-1], np.s_[:, 0], np.s_[:, -1]):
            np.testing.assert_array_equal(got[edge], want[edge])


def test_neighbouring_tiles_share_their_edge_heights_to_the_bit(tmp_path: Path) -> None:
    """A raster's mesh tiles are sampled on a lattice (``sample_grid``): two neighbours still
    read the same heights along their shared edge, and those of the exact projection."""
    from lodscape.geo.keys import mesh_key
    from lodscape.geo.tiles import tile_id
    from lodscape.store.provider import RasterProvider
    from lodscape.terrain.mesh import grid_coordinates

    rng = np.random.default_rng(8)
    data = rng.normal(0.0, 3.0, (900, 900)).cumsum(axis=0).cumsum(axis=1).astype(np.float32)
    path = write_tif(
        tmp_path / "utm.tif", data, from_origin(500000.0, 3900000.0, 4.0, 4.0), crs="EPSG:32617"
    )
    with RasterSource(str(path)) as source:
        provider = RasterProvider(source)
        tree = provider.tree
        z, g = tree.zmax, len(tree.grids) - 1
        segments = tree.grids[g]
        b = source.bounds_merc
        lon, lat = merc_to_lonlat((b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0)
        t = tile(float(lon), float(lat), z)
        x, y = t.x, t.y

        def heights(tx: int) -> np.ndarray:
            raw = provider.fetch(mesh_key(tile_id(Tile(tx, y, z)), g))
            return np.frombuffer(raw, np.float32).reshape(segments + 1, segments + 1)

        west, east = heights(x), heights(x + 1)
        assert np.isfinite(west).all()
        assert np.isfinite(east).all()
        np.testing.assert_array_equal(west[:, -1], east[:, 0])
        xs, ys = grid_coordinates(z, x, y, segments)
        exact, _ = source.sample(*np.meshgrid(xs[-1:], ys), float(tile_size(z)) / segments)
        np.testing.assert_array_equal(west[:, -1], exact[:, 0])
