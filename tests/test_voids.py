"""Voids inside the data look like the ground around them: a build fills them from their rims by
default (no well, no curtain), says how much it filled, and keeps the world outside the data at
the ellipsoid; ``--fill ellipsoid`` still puts a void's floor at 0 m when asked."""

from __future__ import annotations

import json
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from pyproj import Transformer
from scipy.ndimage import binary_dilation

from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.geo.tiles import Tile, bounds
from lodscape.store.quantized_mesh import decode
from lodscape.terrain.source import FilledSource, RasterSource, parse_fill

EAST, NORTH, RES, NODATA = 700000.0, 4060000.0, 10.0, -9999.0


@pytest.fixture(scope="module")
def holed(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, np.ndarray, np.ndarray]:
    """A 257² DEM (300..1200 m) with two voids inside it, one of them in a valley side, and a
    nodata collar along its west edge (the world outside, not a void)."""
    h = fbm_heights(257, seed=21).astype(np.float32)
    void = np.zeros(h.shape, bool)
    void[100:140, 90:120] = True
    void[190:200, 30:60] = True
    collar = np.zeros(h.shape, bool)
    collar[:, :12] = True
    data = np.where(void | collar, np.float32(NODATA), h)
    path = tmp_path_factory.mktemp("voids") / "holed.tif"
    write_dem(str(path), data, crs="EPSG:32617", west=EAST, north=NORTH, res=RES, nodata=NODATA)
    return str(path), h, void


def _vertices(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every stored vertex of the finest terrain level as (column, row) of the DEM and height."""
    to_utm = Transformer.from_crs("EPSG:4326", "EPSG:32617", always_xy=True)
    cols, rows, hs = [], [], []
    with closing(sqlite3.connect(path)) as db:
        zmax = db.execute("SELECT MAX(z) FROM terrain").fetchone()[0]
        for z, x, y, data in db.execute("SELECT z, x, y, data FROM terrain WHERE z = ?", (zmax,)):
            import gzip

            qm = decode(gzip.decompress(bytes(data)))
            b = bounds(Tile(x, y, z))
            lon, lat, h = qm.positions(b.left, b.bottom, b.right, b.top)
            e, n = to_utm.transform(lon, lat)
            cols.append((np.asarray(e) - EAST) / RES)
            rows.append((NORTH - np.asarray(n)) / RES)
            hs.append(h)
    return np.concatenate(cols), np.concatenate(rows), np.concatenate(hs)


def _in_void(void: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Vertices whose pixel and every neighbour are void (the straddling cell is the rim's)."""
    core = void & ~binary_dilation(~void, np.ones((5, 5), bool))
    i, j = np.floor(row).astype(int), np.floor(col).astype(int)
    ok = (i >= 0) & (i < void.shape[0]) & (j >= 0) & (j < void.shape[1])
    out = np.zeros(col.shape, bool)
    out[ok] = core[i[ok], j[ok]]
    return out


def test_a_default_build_fills_voids_from_their_rims(
    holed: tuple[str, np.ndarray, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, h, void = holed
    out = tmp_path / "site.lods"
    code, _, err = run_cli(["build", path, "-o", str(out), "-q"], capsys)
    assert code == 0, err
    col, row, height = _vertices(out)
    inside = _in_void(void, col, row)
    assert inside.sum() > 20, "no vertex fell inside the voids"
    rim = binary_dilation(void, np.ones((3, 3), bool)) & ~void
    lo, hi = float(h[rim].min()), float(h[rim].max())
    assert height[inside].min() >= lo - 5.0
    assert height[inside].max() <= hi + 5.0
    # the collar stays the world outside: height 0 there, not a stretched copy of the data
    collar = (col > 0.5) & (col < 11.0) & (row > 2) & (row < 250)
    assert collar.sum() > 0
    assert np.abs(height[collar]).max() < 1.0
    with closing(sqlite3.connect(out)) as db:
        manifest = json.loads(
            db.execute("SELECT value FROM metadata WHERE name = 'lodscape'").fetchone()[0]
        )
    assert manifest["options"]["fill"] == "interpolate"
    want = void.sum() / void.size
    assert manifest["void_share"] == pytest.approx(want, rel=0.02)
    code, text, _ = run_cli(["info", str(out)], capsys)
    assert f"{100 * want:.2f} % of the raster inside the data, filled from their rims" in text
    code, text, _ = run_cli(["info", path], capsys)
    assert f"voids: {100 * want:.2f} % of the raster inside the data" in text


def test_the_ellipsoid_fill_still_puts_a_voids_floor_at_zero(
    holed: tuple[str, np.ndarray, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, _, void = holed
    out = tmp_path / "ellipsoid.lods"
    code, _, err = run_cli(["build", path, "-o", str(out), "-q", "--fill", "ellipsoid"], capsys)
    assert code == 0, err
    col, row, height = _vertices(out)
    inside = _in_void(void, col, row)
    assert inside.sum() > 20
    assert np.abs(height[inside]).max() < 1.0


def test_interpolate_is_a_fill_for_rendering_too(
    holed: tuple[str, np.ndarray, np.ndarray],
) -> None:
    """The same fill from the source a render reads: bounded by the rim, the collar at 0."""
    path, h, void = holed
    with RasterSource(path) as raw:
        src = FilledSource(raw, parse_fill("interpolate"))
        to_merc = Transformer.from_crs("EPSG:32617", "EPSG:3857", always_xy=True)
        rows, cols = np.nonzero(void)
        xm, ym = to_merc.transform(EAST + (cols + 0.5) * RES, NORTH - (rows + 0.5) * RES)
        got, valid = src.sample(np.asarray(xm), np.asarray(ym), RES)
        assert not valid.any()
        rim = binary_dilation(void, np.ones((3, 3), bool)) & ~void
        assert got.min() >= h[rim].min() - 1.0
        assert got.max() <= h[rim].max() + 1.0
        xm, ym = to_merc.transform(EAST + 5 * RES, NORTH - 128 * RES)  # in the collar
        got, valid = src.sample(np.array([xm]), np.array([ym]), RES)
        assert not valid[0]
        assert got[0] == 0.0
