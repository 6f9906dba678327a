"""Cesium's geographic tiling (EPSG:4326): what ``export --cesium`` and ``serve`` give Cesium by
default. Level 0 is two tiles of 180° square; level z has 2^(z+1) × 2^z tiles of 180/2^z degrees,
rows counted from the south (TMS). Unlike Web Mercator's, whose tiles stop at ±85.05°, these
reach the poles, so a client finds a surface everywhere on the globe.

A tileset is stored in Web Mercator tiles; a geographic tile is made from them. A geographic tile
of level z spans as many degrees of longitude as a Mercator tile of level z + 1, and their
columns are the same, so it is made from the stored surface of level z + 1 (or the coarser
level where the tree stops sooner): that surface sampled on a grid regular in longitude and
latitude (finer where the tile is taller than wide on the ground, so no row of the data is
skipped), then meshed (RTIN) within the largest error recorded for those Mercator tiles. It is
available where a stored Mercator tile of level z + 1 overlaps it, so availability follows the
stored tree; above the tileset's roots, and at level 0 over the rest of the globe, filler tiles
of the ellipsoid (height 0). Outside the stored tiles a tile is the ellipsoid too; where the
data has a hole (``--fill none``), so does the tile.
"""

from __future__ import annotations

import math
import sqlite3
from collections import defaultdict
from typing import Any

import numpy as np

from lodscape.geo.frames import up_vector
from lodscape.geo.tiles import ORIGIN, lonlat_to_merc, merc_to_lonlat, tiles_array
from lodscape.store.quantized_mesh import encode
from lodscape.terrain.mesh import grid_indices, vertex_normals, without_holes
from lodscape.terrain.rtin import Rtin

__all__ = [
    "GRID",
    "TILINGS",
    "available_tiles",
    "ellipsoid_tile",
    "geographic_tile",
    "rect",
]

#: The tilings ``export --cesium`` and ``serve`` write (``--tiling``).
TILINGS = ("geographic", "mercator")
#: Grid cells a side a geographic tile is sampled on, where it is as wide as tall on the ground
#: (the stored tiles' own); a tile taller than wide (towards the poles) takes up to 4× more.
GRID = 64
#: Added to heights where the data has a hole, so the mesh splits down to the grid there.
_RIM = 1.0e7


def rect(z: int, x: int, tms: int) -> tuple[float, float, float, float]:
    """Tile z/x/TMS row's (west, south, east, north) in degrees."""
    span = 180.0 / (1 << z)
    return -180.0 + x * span, -90.0 + tms * span, -180.0 + (x + 1) * span, -90.0 + (tms + 1) * span


def ellipsoid_tile(z: int, x: int, tms: int) -> bytes:
    """Tile z/x/TMS row of the ellipsoid itself (height 0): a grid regular in longitude and
    latitude, 32 cells a side at level 0 and 16 below (at most 5.6° a cell: chords within a
    fifth of Cesium's geometric error for the level), with the ellipsoid's normals."""
    n = 32 if z == 0 else 16
    w, s, e, north = rect(z, x, tms)
    lon_col = np.linspace(w, e, n + 1)
    lat_row = np.linspace(north, s, n + 1)
    lon_col[0], lon_col[-1], lat_row[0], lat_row[-1] = w, e, north, s
    grid_lon, grid_lat = np.meshgrid(lon_col, lat_row)
    lon, lat = grid_lon.ravel(), grid_lat.ravel()
    tris = grid_indices(n)[: 2 * n * n].astype(np.int64)
    return encode(lon, lat, np.zeros(lon.size), tris, (w, s, e, north), normals=up_vector(lon, lat))


def available_tiles(db: sqlite3.Connection) -> dict[int, set[tuple[int, int]]]:
    """The geographic tiles (x, TMS row) of each level a tileset gives: where a stored Mercator
    tile of the next level overlaps one, their ancestors (fillers above the tileset's roots),
    and both level-0 tiles."""
    rows = np.array(db.execute("SELECT z, x, y FROM terrain WHERE z >= 1").fetchall(), np.int64)
    out: dict[int, set[tuple[int, int]]] = defaultdict(set)
    if rows.size:
        zm, xm, ym = rows.T
        zg = zm - 1
        size = 2.0 * ORIGIN / (1 << zm)
        _, north = merc_to_lonlat(0.0, ORIGIN - ym * size)
        _, south = merc_to_lonlat(0.0, ORIGIN - (ym + 1) * size)
        span = 180.0 / (1 << zg)
        top = (1 << zg) - 1
        first = np.clip(np.floor((south + 90.0) / span), 0, top).astype(np.int64)
        # a tile whose north edge is a row's south edge does not reach into that row
        last = np.clip(np.ceil((north + 90.0) / span) - 1, 0, top).astype(np.int64)
        # every row each tile reaches (at most two: a Mercator tile is never taller in
        # latitude than its geographic column is wide), then the distinct tiles per level
        count = last - first + 1
        at = np.repeat(np.arange(len(first)), count)
        rows_of = first[at] + np.arange(at.size) - np.repeat(np.cumsum(count) - count, count)
        tiles = np.unique(np.stack([zg[at], xm[at], rows_of], axis=1), axis=0)
        for z in np.unique(tiles[:, 0]).tolist():
            level = tiles[tiles[:, 0] == z]
            out[z] = set(zip(level[:, 1].tolist(), level[:, 2].tolist(), strict=True))
    out[0].update({(0, 0), (1, 0)})
    for z in range(max(out), 0, -1):
        out[z - 1].update((x >> 1, r >> 1) for x, r in out.get(z, ()))
    return dict(out)


def geographic_tile(provider: Any, z: int, x: int, tms: int, zmax: int) -> bytes | None:
    """Tile z/x/TMS row made from a tileset (``store.tileset.TilesetProvider``) whose finest
    terrain level is ``zmax``: quantized-mesh bytes (not gzipped), or None where every point
    the tile samples is in a hole of the data."""
    w, s, e, n = rect(z, x, tms)
    zm = min(z + 1, zmax)
    # a tile taller than wide on the ground (cos of its latitude nearest a pole) samples more
    # rows, so none of the stored surface's is skipped (and as many columns: RTIN's grid is square)
    widest = min(max(abs(s), abs(n)), 85.0)
    k = int(np.clip(math.ceil(math.log2(1.0 / math.cos(math.radians(widest))) - 1e-9), 0, 2))
    g = GRID << k
    lon_col = np.linspace(w, e, g + 1)
    lat_row = np.linspace(n, s, g + 1)
    lon_col[0], lon_col[-1], lat_row[0], lat_row[-1] = w, e, n, s
    lon, lat = np.meshgrid(lon_col, lat_row)
    h, covered = provider.surface(lon, lat, zm, holes=True)
    if not covered.any():
        return ellipsoid_tile(z, x, tms)
    # outside the stored tiles: the ellipsoid, as the fillers and Mercator's ancestors show
    h = np.where(covered, h, 0.0)
    valid = ~np.isnan(h)
    if not valid.any():
        return None
    error = _recorded_error(provider, zm, w, s, e, n)
    if valid.all():
        rtin = Rtin(h)
        verts, tris = rtin.mesh(error)
    else:
        kept = without_holes(*Rtin(np.where(valid, h, _RIM)).mesh(error), valid)
        if kept is None:
            return None
        verts, tris = kept
    vlon, vlat = lon_col[verts[:, 0]], lat_row[verts[:, 1]]
    vh = h[verts[:, 1], verts[:, 0]].astype(np.float64)
    normals = vertex_normals(vlon, vlat, vh, tris)
    return encode(vlon, vlat, vh, tris, (w, s, e, n), normals=normals)


def _recorded_error(provider: Any, zm: int, w: float, s: float, e: float, n: float) -> float:
    """The largest error recorded for the stored tiles of level ``zm`` (or the finest coarser
    level that has any) that overlap the box."""
    edge = 85.05
    xm, ym = lonlat_to_merc([w + 1e-9, e - 1e-9], [min(n, edge) - 1e-9, max(s, -edge) + 1e-9])
    tx, ty = tiles_array(xm, ym, zm)
    for level in range(zm, -1, -1):
        shift = zm - level
        x0, x1, y0, y1 = (int(v) >> shift for v in (tx[0], tx[1], ty[0], ty[1]))
        found = provider.max_error(level, x0, x1, y0, y1)
        if found is not None:
            return float(found)
    return 0.0
