"""What a Cesium client reads from ``lodscape export``, in both tilings (geographic, the default,
and Web Mercator): every tile decoded by an independent decoder (PyPI ``quantized-mesh-tile``,
normals included), the world outside the data the ellipsoid itself to the poles, the data's
surface as the stored tiles have it, and nodata holes left out of the meshes."""

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
from lodscape.store.geographic import rect
from lodscape.store.quantized_mesh import decode
from lodscape.store.tileset import TilesetProvider

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0
#: The nodata hole: rows and columns of the 257² DEM.
HOLE = (slice(90, 170), slice(100, 180))


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    h = fbm_heights(257, seed=11)
    h[HOLE] = -9999.0
    path = tmp_path_factory.mktemp("client") / "hole.tif"
    return write_dem(str(path), h, crs="EPSG:32617", west=EAST, north=NORTH, res=RES, nodata=-9999)


TILINGS = ("geographic", "mercator")


@pytest.fixture(scope="module")
def exported(dem: str, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Each fill's tileset exported in each tiling: "fill" (geographic) and "fill-mercator"."""
    folder = tmp_path_factory.mktemp("export")
    out = {}
    for fill in ("ellipsoid", "none"):
        lods = folder / f"{fill}.lods"
        build([dem], lods, BuildOptions(fill=fill))
        for tiling in TILINGS:
            name = fill if tiling == "geographic" else f"{fill}-mercator"
            export_cesium(lods, folder / name, tiling=tiling)
            out[name] = folder / name
    return out


def _tiling(folder: Path) -> str:
    projection = json.loads((folder / "layer.json").read_text())["projection"]
    return {"EPSG:4326": "geographic", "EPSG:3857": "mercator"}[projection]


def _tiles(folder: Path) -> list[tuple[int, int, int, Path]]:
    """(z, x, TMS row, file) of every exported terrain tile."""
    out = []
    for f in folder.glob("*/*/*.terrain"):
        z, x, tms = int(f.parent.parent.name), int(f.parent.name), int(f.stem)
        out.append((z, x, tms, f))
    return sorted(out)


def _rect(folder: Path, z: int, x: int, tms: int) -> tuple[float, float, float, float]:
    """Tile z/x/TMS row's (west, south, east, north) in the folder's tiling."""
    if _tiling(folder) == "geographic":
        return rect(z, x, tms)
    b = bounds(Tile(x, (1 << z) - 1 - tms, z))
    return b.left, b.bottom, b.right, b.top


def _read(folder: Path, f: Path, z: int, x: int, tms: int) -> TerrainTile:
    w, s, e, n = _rect(folder, z, x, tms)
    tile = TerrainTile(west=w, south=s, east=e, north=n)
    tile.fromFile(str(f), hasLighting=True)
    return tile


def _up(lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    lo, la = np.radians(lon), np.radians(lat)
    return np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])


@pytest.mark.parametrize("name", ["ellipsoid", "none", "ellipsoid-mercator", "none-mercator"])
def test_every_tile_reads_in_an_independent_decoder(exported: dict[str, Path], name: str) -> None:
    folder = exported[name]
    layer = json.loads((folder / "layer.json").read_text())
    assert layer["extensions"] == ["octvertexnormals"]
    tiles = _tiles(folder)
    assert {t[0] for t in tiles} >= {0, 1, 2}
    # exactly the tiles layer.json says are available
    said = {
        (z, x, r)
        for z, ranges in enumerate(layer["available"])
        for a in ranges
        for x in range(a["startX"], a["endX"] + 1)
        for r in range(a["startY"], a["endY"] + 1)
    }
    assert said == {t[:3] for t in tiles}
    for z, x, y, f in tiles:
        theirs = _read(folder, f, z, x, y)
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
        _lon, _lat, h = ours.positions(*_rect(folder, z, x, y))
        assert theirs.header["minimumHeight"] <= h.min() + 1e-3
        assert theirs.header["maximumHeight"] >= h.max() - 1e-3
        occlusion = [theirs.header[f"horizonOcclusionPoint{c}"] for c in "XYZ"]
        if z >= 1:
            assert all(math.isfinite(c) for c in occlusion), (z, x, y, occlusion)


@pytest.mark.parametrize("name", ["ellipsoid", "ellipsoid-mercator"])
def test_the_world_above_the_data_is_the_ellipsoid(exported: dict[str, Path], name: str) -> None:
    folder = exported[name]
    # a geographic tile of level z is made from the stored tiles of level z + 1
    zmin = _zmin(folder) - (1 if _tiling(folder) == "geographic" else 0)
    fillers = [t for t in _tiles(folder) if t[0] < zmin]
    assert fillers
    for z, x, y, f in fillers:
        tile = _read(folder, f, z, x, y)
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
        w, s, e, n = _rect(folder, z, x, y)
        tri = np.array(tile.indices).reshape(-1, 3)
        a = 0.5 * np.abs(
            (lon[tri[:, 1]] - lon[tri[:, 0]]) * (lat[tri[:, 2]] - lat[tri[:, 0]])
            - (lat[tri[:, 1]] - lat[tri[:, 0]]) * (lon[tri[:, 2]] - lon[tri[:, 0]])
        )
        np.testing.assert_allclose(a.sum(), (e - w) * (n - s), rtol=1e-6)


def test_the_geographic_tiling_reaches_the_poles(exported: dict[str, Path]) -> None:
    """Level 0 is two tiles that cover the globe to ±90°: a client finds a surface over both
    poles (Web Mercator's stop at ±85.05°, where Cesium drew a white disc)."""
    folder = exported["ellipsoid"]
    layer = json.loads((folder / "layer.json").read_text())
    assert layer["available"][0] == [{"startX": 0, "startY": 0, "endX": 1, "endY": 0}]
    lats = []
    area = 0.0
    for x in (0, 1):
        q = decode((folder / "0" / str(x) / "0.terrain").read_bytes())
        lon, lat, _h = q.positions(*rect(0, x, 0))
        lats.append(lat)
        tri = q.triangles.astype(np.int64)
        area += (
            0.5
            * np.abs(
                (lon[tri[:, 1]] - lon[tri[:, 0]]) * (lat[tri[:, 2]] - lat[tri[:, 0]])
                - (lat[tri[:, 1]] - lat[tri[:, 0]]) * (lon[tri[:, 2]] - lon[tri[:, 0]])
            ).sum()
        )
    assert np.concatenate(lats).max() == 90.0
    assert np.concatenate(lats).min() == -90.0
    np.testing.assert_allclose(area, 360.0 * 180.0, rtol=1e-9)
    mercator = json.loads((exported["ellipsoid-mercator"] / "layer.json").read_text())
    assert mercator["available"][0] == [{"startX": 0, "startY": 0, "endX": 0, "endY": 0}]


@pytest.mark.parametrize("fill", ["ellipsoid", "none"])
def test_geographic_tiles_hold_the_stored_surface(exported: dict[str, Path], fill: str) -> None:
    """Every geographic tile with data is within its recorded error (twice: the stored tiles',
    then its own re-meshing within it) of the stored surface it was made from, at random
    points where that surface has data."""
    folder = exported[fill]
    provider = TilesetProvider(folder.parent / f"{fill}.lods")
    rng = np.random.default_rng(5)
    checked = 0
    try:
        zmax = int(provider.manifest["levels"]["zmax"])
        for z, x, tms, f in _tiles(folder):
            if z + 1 < _zmin(folder):
                continue
            w, s, e, n = rect(z, x, tms)
            q = decode(f.read_bytes())
            plon, plat, ph = q.positions(w, s, e, n)
            tri = q.triangles.astype(np.int64)
            lon, lat = rng.uniform(w, e, 400), rng.uniform(s, n, 400)
            ours = _heights_at(plon, plat, ph, tri, lon, lat)
            stored, covered = provider.surface(lon, lat, min(z + 1, zmax))
            # outside the stored tiles: the ellipsoid
            outside = ~covered & ~np.isnan(ours)
            np.testing.assert_allclose(ours[outside], 0.0, atol=1e-6)
            stored[~covered] = 0.0
            both = ~np.isnan(ours) & ~np.isnan(stored)
            # leave out points within two grid cells of a wall (the data beside the ellipsoid
            # filling its hole: heights > 100 m beside 0), which each grid cuts where it falls
            d = 2.0 * (e - w) / 64
            for dx, dy in ((-d, 0), (d, 0), (0, -d), (0, d), (-d, -d), (d, d), (-d, d), (d, -d)):
                near, _ = provider.surface(lon + dx, lat + dy, min(z + 1, zmax))
                both &= ~((np.abs(near) < 1.0) ^ (np.abs(stored) < 1.0))
            # a hole in the stored surface is a hole here (but within a grid cell of its rim)
            assert (np.isnan(ours) | ~np.isnan(stored)).mean() > 0.97, (z, x, tms)
            # the stored tiles' recorded error, which the tile was re-meshed within
            err = provider.max_error(min(z + 1, zmax), 0, 1 << 30, 0, 1 << 30) or 0.0
            limit = 2.0 * err + 0.02 * (q.max_height - q.min_height) + 0.5
            assert np.abs(ours[both] - stored[both]).max(initial=0.0) <= limit, (z, x, tms)
            checked += int(both.sum())
    finally:
        provider.close()
    assert checked > 10_000


def _heights_at(
    plon: np.ndarray,
    plat: np.ndarray,
    ph: np.ndarray,
    tri: np.ndarray,
    lon: np.ndarray,
    lat: np.ndarray,
) -> np.ndarray:
    """A decoded tile's mesh heights at points (NaN where no triangle holds one)."""
    out = np.full(lon.size, np.nan)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ax, ay, bx, by, cx, cy = plon[a], plat[a], plon[b], plat[b], plon[c], plat[c]
    det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    for i in range(lon.size):
        with np.errstate(divide="ignore", invalid="ignore"):
            wa = ((by - cy) * (lon[i] - cx) + (cx - bx) * (lat[i] - cy)) / det
            wb = ((cy - ay) * (lon[i] - cx) + (ax - cx) * (lat[i] - cy)) / det
        wc = 1.0 - wa - wb
        hit = np.flatnonzero((wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9) & (det != 0))
        if hit.size:
            k = hit[0]
            out[i] = wa[k] * ph[a[k]] + wb[k] * ph[b[k]] + wc[k] * ph[c[k]]
    return out


def _zmin(folder: Path) -> int:
    lods = folder.parent / f"{folder.name.removesuffix('-mercator')}.lods"
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
        lon, lat, h = q.positions(*_rect(folder, z, x, y))
        tri = q.triangles.astype(np.int64)
        cx, cy = lon[tri].mean(axis=1), lat[tri].mean(axis=1)
        hit = (cx > w) & (cx < e) & (cy > s) & (cy < n)
        inside.append(h[tri[hit]].ravel())
        outside.append(h[tri[~hit]].ravel())
    return [np.concatenate(inside), np.concatenate(outside)]


@pytest.mark.parametrize("suffix", ["", "-mercator"])
def test_a_hole_has_no_triangles_and_the_data_around_it_has(
    exported: dict[str, Path], suffix: str
) -> None:
    box = _hole_lonlat(shrink=2.0)
    zmax = max(t[0] for t in _tiles(exported["none" + suffix]))
    inside, outside = _in_box(exported["none" + suffix], zmax, box)
    assert inside.size == 0
    assert outside.size > 3000
    # the same hole, filled with the ellipsoid: triangles at height 0 there
    inside, _ = _in_box(exported["ellipsoid" + suffix], zmax, box)
    assert inside.size > 0
    assert np.abs(inside).max() < 0.05
