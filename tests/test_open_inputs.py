"""What Python users hand ``lodscape.open`` and ``Scene.render``: an open rasterio dataset, an
xarray DataArray through rioxarray, and one-line errors for what cannot be placed on the Earth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lodscape

pytestmark = pytest.mark.gl


def _dem_file(tmp_path: Path) -> tuple[str, np.ndarray]:
    from _synthetic import fbm_heights, write_dem

    h = fbm_heights(129, seed=5) + 100.0
    h[10:20, 10:20] = -9999.0
    path = write_dem(
        str(tmp_path / "dem.tif"), h, crs="EPSG:32633", west=500000.0, north=5100000.0,
        res=30.0, nodata=-9999,
    )  # fmt: skip
    return path, h


def _camera_over(scene: lodscape.Scene) -> lodscape.Camera:
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.provider.bounds_merc
    lon, lat = merc_to_lonlat((b.left + b.right) / 2, (b.bottom + b.top) / 2)
    g = scene.ground_height(float(lon), float(lat)) or 0.0
    return lodscape.Camera(float(lon), float(lat) - 0.01, g + 1500.0, pitch=-35.0,
                           width=96, height=64)  # fmt: skip


# rioxarray 0.19 multiplies affines with * (affine's PendingDeprecationWarning): theirs
@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")
def test_open_takes_a_rasterio_dataset_and_a_rioxarray_dataarray(tmp_path: Path) -> None:
    """What GIS users hold: an open rasterio dataset, and an xarray DataArray read by
    rioxarray (its transform, CRS and nodata from ``.rio``): the same terrain as the file."""
    import rasterio

    rioxarray = pytest.importorskip("rioxarray")
    path, _h = _dem_file(tmp_path)
    with lodscape.open(path) as scene:
        cam = _camera_over(scene)
        want, want_d = scene.render(cam)
        ground = scene.ground_height(cam.lon, cam.lat + 0.01)
    with rasterio.open(path) as ds, lodscape.open(ds) as scene:
        rgb, d = scene.render(cam)
        np.testing.assert_array_equal(rgb, want)
    da = rioxarray.open_rasterio(path)  # (band, y, x), its nodata from the file
    assert da.rio.nodata == -9999
    with lodscape.open(da) as scene:
        assert scene.ground_height(cam.lon, cam.lat + 0.01) == pytest.approx(ground, abs=0.01)
        rgb, d = scene.render(cam)
        both = np.isfinite(d) & np.isfinite(want_d)
        assert both.mean() > 0.5
        np.testing.assert_allclose(d[both], want_d[both], rtol=1e-3)
        # the nodata hole is not a height of -9999 m
        assert np.nanmin(scene.provider.heights_at(*_corner(path))) > 0.0


def _corner(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Points of the DEM's nodata block and beside it (lon, lat)."""
    from pyproj import Transformer

    t = Transformer.from_crs("EPSG:32633", "EPSG:4326", always_xy=True)
    x = 500000.0 + 30.0 * np.array([15.0, 40.0])
    y = 5100000.0 - 30.0 * np.array([15.0, 40.0])
    lon, lat = t.transform(x, y)
    return np.asarray(lon), np.asarray(lat)


def test_what_open_and_render_cannot_take_is_one_line(tmp_path: Path) -> None:
    import xarray as xr

    with pytest.raises(lodscape.LodscapeError, match="transform=") as info:
        lodscape.open(np.zeros((10, 10)))
    assert "\n" not in str(info.value)
    with pytest.raises(lodscape.LodscapeError, match=r"rioxarray|CRS") as info:
        lodscape.open(xr.DataArray(np.zeros((10, 10)), dims=("y", "x")))
    assert "\n" not in str(info.value)
    path, _h = _dem_file(tmp_path)
    with lodscape.open(path) as scene, pytest.raises(lodscape.LodscapeError, match="Camera"):
        scene.render(None)  # type: ignore[arg-type]
