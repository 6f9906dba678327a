"""What a Cesium client reads from ``lodscape export``: every tile decoded by an independent
decoder (PyPI ``quantized-mesh-tile``, normals included), the world outside the data the
ellipsoid itself, and nodata holes left out of the meshes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from quantized_mesh_tile.terrain import TerrainTile

from _synthetic import fbm_heights, write_dem
from lodscape.build import BuildOptions, build
from lodscape.geo.frames import WGS84_A, WGS84_B, geodetic_to_ecef
from lodscape.geo.tiles import Tile, bounds
from lodscape.store.export import export_cesium
from lodscape.store.quantized_mesh import decode

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0
#: The nodata hole: rows and columns of the 257² DEM.
HOLE = (slice(90, 170), slice(100, 180))


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    h = fbm_heights(257, seed=11)
    h[HOLE] = -9999.0
    path = tmp_path_factory.mktemp("client") / "hole.tif"
    return write_dem(str(path), h, crs="EPSG:32617", west=EAST, north=NORTH, res=RES, nodata=-9999)


def _export(dem: str, folder: Path, fill: str) -> Path:
    out = folder / f"{fill}.lods"
    build([dem], out, BuildOptions(fill=fill))
    export_cesium(out, folder / fill)
    return folder / fill


@pytest.fixture(scope="module")
def exported(dem: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("export")
    return {fill: _export(dem, folder, fill) for fill in ("ellipsoid", "none")}


def _tiles(folder: Path) -> list[tuple[int, int, int, Path]]:
    """(z, x, OSM row, file) of every exported terrain tile."""
    out = []
    for f in folder.glob("*/*/*.terrain"):
        z, x, tms = int(f.parent.parent.name), int(f.parent.name), int(f.stem)
        out.append((z, x, (1 << z) - 1 - tms, f))
    return sorted(out)


def _read(f: Path, z: int, x: int, y: int) -> TerrainTile:
    b = bounds(Tile(x, y, z))
    tile = TerrainTile(west=b.left, south=b.bottom, east=b.right, north=b.top)
    tile.fromFile(str(f), hasLighting=True)
    return tile


def _up(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    lo, la = np.radians(lon), np.radians(lat)
    return np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])


@pytest.mark.parametrize("fill", ["ellipsoid", "none"])
def test_every_tile_reads_in_an_independent_decoder(exported: dict[str, Path], fill: str) -> None:
    folder = exported[fill]
    layer = json.loads((folder / "layer.json").read_text())
    assert layer["extensions"] == ["octvertexnormals"]
    tiles = _tiles(folder)
    assert {t[0] for t in tiles} >= {0, 1, 2}
    for z, x, y, f in tiles:
        theirs = _read(f, z, x, y)
        ours = decode(f.read_bytes())
        n = ours.vertex_count
        assert len(theirs.u) == n
        assert n >= 3
        np.testing.assert_array_equal(np.array(theirs.u), ours.u)
        np.testing.assert_array_equal(np.array(theirs.h), ours.h)
        np.testing.assert_array_equal(np.array(theirs.indices), ours.triangles.ravel())
        # what layer.json promises: a normal for every vertex
        assert len(theirs.vLight) == n, (z, x, y)
        # the edge lists hold exactly the vertices on each side
        u, v = np.array(theirs.u), np.array(theirs.v)
        for side, mask in (
            (theirs.westI, u == 0),
            (theirs.southI, v == 0),
            (theirs.eastI, u == 32767),
            (theirs.northI, v == 32767),
        ):
            assert sorted(side) == np.flatnonzero(mask).tolist(), (z, x, y)
        # no vertex that no triangle uses
        assert np.unique(ours.triangles).size == n
        # min/max heights hold every vertex, and the horizon point is finite below level 0
        _lon, _lat, h = ours.positions(*bounds(Tile(x, y, z)))
        assert theirs.header["minimumHeight"] <= h.min() + 1e-3
        assert theirs.header["maximumHeight"] >= h.max() - 1e-3
        occlusion = [theirs.header[f"horizonOcclusionPoint{c}"] for c in "XYZ"]
        if z >= 1:
            assert all(math.isfinite(c) for c in occlusion), (z, x, y, occlusion)


def test_the_world_above_the_data_is_the_ellipsoid(exported: dict[str, Path]) -> None:
    folder = exported["ellipsoid"]
    layer = json.loads((folder / "layer.json").read_text())
    with_data = min(int(z) for z, ranges in enumerate(layer["available"]) if ranges and z > 0)
    fillers = [t for t in _tiles(folder) if t[0] < _zmin(folder)]
    assert fillers
    assert with_data >= 1
    for z, x, y, f in fillers:
        tile = _read(f, z, x, y)
        # at the ellipsoid: height 0, not the data's lowest (the whole planet would move)
        assert tile.header["minimumHeight"] == 0.0
        assert tile.header["maximumHeight"] == 0.0
        lon, lat, h = (np.array(c) for c in zip(*tile.getVerticesCoordinates(), strict=True))
        p = geodetic_to_ecef(lon, lat, h).reshape(-1, 3)
        on = (p[:, 0] ** 2 + p[:, 1] ** 2) / WGS84_A**2 + p[:, 2] ** 2 / WGS84_B**2
        np.testing.assert_allclose(on, 1.0, atol=1e-9)
        # curved: enough vertices to follow the ellipsoid, normals pointing up
        assert len(tile.u) >= 17 * 17
        normals = np.array(tile.vLight, np.float64)
        assert (np.einsum("ij,ij->i", normals, _up(lon, lat)) > 0.99).all()
        # triangles cover the tile: their areas in lon/lat add up to its rectangle
        b = bounds(Tile(x, y, z))
        tri = np.array(tile.indices).reshape(-1, 3)
        a = 0.5 * np.abs(
            (lon[tri[:, 1]] - lon[tri[:, 0]]) * (lat[tri[:, 2]] - lat[tri[:, 0]])
            - (lat[tri[:, 1]] - lat[tri[:, 0]]) * (lon[tri[:, 2]] - lon[tri[:, 0]])
        )
        np.testing.assert_allclose(a.sum(), (b.right - b.left) * (b.top - b.bottom), rtol=1e-6)


def _zmin(folder: Path) -> int:
    lods = folder.parent / f"{folder.name}.lods"
    from lodscape.store.tileset import TilesetProvider

    p = TilesetProvider(lods)
    try:
        return int(p.manifest["levels"]["zmin"])
    finally:
        p.close()


def _hole_lonlat(shrink: float) -> tuple[float, float, float, float]:
    """The hole's box (west, south, east, north) in degrees, shrunk by ``shrink`` pixels."""
    from pyproj import Transformer

    rows, cols = HOLE
    x0, x1 = EAST + (cols.start + shrink) * RES, EAST + (cols.stop - shrink) * RES
    y0, y1 = NORTH - (rows.stop - shrink) * RES, NORTH - (rows.start + shrink) * RES
    t = Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True)
    lon, lat = t.transform([x0, x1, x0, x1], [y0, y0, y1, y1])
    return max(lon[0], lon[2]), max(lat[0], lat[1]), min(lon[1], lon[3]), min(lat[2], lat[3])


def _in_box(folder: Path, z: int, box: tuple[float, float, float, float]) -> list[np.ndarray]:
    """Per level-z tile, the heights of the vertices of the triangles whose centres are in
    ``box`` (west, south, east, north), and of the others: [inside, outside] arrays."""
    w, s, e, n = box
    inside, outside = [], []
    for zt, x, y, f in _tiles(folder):
        if zt != z:
            continue
        q = decode(f.read_bytes())
        lon, lat, h = q.positions(*bounds(Tile(x, y, z)))
        tri = q.triangles.astype(np.int64)
        cx, cy = lon[tri].mean(axis=1), lat[tri].mean(axis=1)
        hit = (cx > w) & (cx < e) & (cy > s) & (cy < n)
        inside.append(h[tri[hit]].ravel())
        outside.append(h[tri[~hit]].ravel())
    return [np.concatenate(inside), np.concatenate(outside)]


def test_a_hole_has_no_triangles_and_the_data_around_it_has(exported: dict[str, Path]) -> None:
    box = _hole_lonlat(shrink=2.0)
    zmax = max(t[0] for t in _tiles(exported["none"]))
    inside, outside = _in_box(exported["none"], zmax, box)
    assert inside.size == 0
    assert outside.size > 3000
    # the same hole, filled with the ellipsoid: triangles at height 0 there
    inside, _ = _in_box(exported["ellipsoid"], zmax, box)
    assert inside.size > 0
    assert np.abs(inside).max() < 0.05
