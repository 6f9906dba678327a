"""A tileset as a folder a Cesium client streams: ``layer.json``, ``{z}/{x}/{y}.terrain`` (TMS
rows, the layer's default scheme) in the geographic tiling (EPSG:4326, ``store.geographic``: to
the poles, the default) or the stored Web Mercator one, the imagery as
``imagery/{z}/{x}/{y}.png`` (OSM rows) with its TileJSON (``imagery.json``: levels, bounds,
attribution), and the stored cities' buildings as 3D Tiles (``3dtiles/tileset.json``,
``3dtiles/{i}.glb``).

Cesium starts from the tiling scheme's level 0, so the levels above the tileset's roots get
filler tiles over the roots' ancestors: the ellipsoid (height 0) itself, curved meshes with
enough vertices to follow it at their level, with normals. Where a tile is not available a
client draws its ancestor's surface, so the world outside the data is the ellipsoid, never the
data's lowest height. The folder is written under a temporary name and renamed when complete,
so a failed export leaves nothing behind.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import sqlite3
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from lodscape._tmp import temp_beside
from lodscape.geo.frames import up_vector
from lodscape.geo.tiles import Bbox, Tile, bounds, lonlat_to_merc, merc_to_lonlat, tile_range
from lodscape.imagery.pyramid import halve_rgba
from lodscape.store.city_tiles import city_tiles
from lodscape.store.geographic import TILINGS, available_tiles, geographic_tile
from lodscape.store.manifest import connect_readonly
from lodscape.store.quantized_mesh import encode, ungzip
from lodscape.store.tileset import TilesetError, TilesetProvider, lonlat_bounds
from lodscape.terrain.mesh import grid_coordinates, grid_indices

__all__ = [
    "ImageryTiles",
    "Mapper",
    "cesium_layer",
    "ellipsoid_tile",
    "empty_png",
    "export_cesium",
    "geographic_layer",
    "imagery_range",
    "imagery_tilejson",
    "write_chunk",
    "write_geographic",
]


class Mapper(Protocol):
    """What runs an export's chunks: ``imap(fn, args)`` yields ``fn(*a)`` for every ``a`` as
    they finish (a build's executor: threads, processes or a Dask cluster)."""

    def imap(self, fn: Callable[..., Any], args: Iterable[tuple[Any, ...]]) -> Iterator[Any]: ...


#: Tiles per chunk of a parallel export.
_CHUNK = 2048


def export_cesium(
    tileset: str | os.PathLike[str],
    folder: str | os.PathLike[str],
    executor: Mapper | None = None,
    *,
    base_url: str | None = None,
    tiling: str = "geographic",
) -> int:
    """Write ``tileset`` into ``folder`` (new, or empty); returns the terrain tiles written.
    With an ``executor``, its workers write the tiles, a chunk of columns each (the folder's
    parent must be one they reach). ``base_url``: where the folder will be served from, so the
    imagery's TileJSON names its tiles absolutely (else relative to the TileJSON). ``tiling``:
    "geographic" (EPSG:4326, to the poles; ``store.geographic``) or "mercator" (EPSG:3857, the
    stored tiles as they are)."""
    if tiling not in TILINGS:
        raise TilesetError(f"tiling {tiling!r}: expected one of {', '.join(TILINGS)}")
    target = Path(folder)
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise TilesetError(f"{target}: exists and is not an empty folder")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise TilesetError(f"{target}: folder {parent} does not exist")
    provider = TilesetProvider(tileset)  # refuses what is not a complete tileset
    manifest = provider.manifest
    provider.close()
    tmp = temp_beside(parent / target.name)
    shutil.rmtree(tmp, ignore_errors=True)
    db = connect_readonly(tileset)
    try:
        if tiling == "geographic":
            available = available_tiles(db)
            pieces = [(str(tileset), str(tmp), *c) for c in _geographic_chunks(available)]
            done = (
                executor.imap(write_geographic, pieces)
                if executor is not None
                else (write_geographic(*a) for a in pieces)
            )
            count = 0
            for made, missing in done:
                count += made
                for z, x, tms in missing:
                    available[z].discard((x, tms))
            layer = geographic_layer(db, manifest, Path(tileset).stem, available)
        else:
            if executor is None:
                count = write_chunk(str(tileset), str(tmp), "terrain", -1, 0, 0)
            else:
                args = [(str(tileset), str(tmp), *c) for c in _chunks(db, ("terrain",))]
                count = sum(executor.imap(write_chunk, args))
            layer, flat = cesium_layer(db, manifest, Path(tileset).stem)
            for (z, x, tms), data in flat.items():
                _write(tmp / str(z) / str(x) / f"{tms}.terrain", data)
                count += 1
        if executor is None:
            write_chunk(str(tileset), str(tmp), "tiles", -1, 0, 0)
        else:
            args = [(str(tileset), str(tmp), *c) for c in _chunks(db, ("tiles",))]
            sum(executor.imap(write_chunk, args))
        size: Any = manifest.get("tile_size", 256)
        every = ImageryTiles(lambda: db, int(size))
        for z, x, y in every.missing():
            made = every.tile(z, x, y)
            if made is not None:
                _write(tmp / "imagery" / str(z) / str(x) / f"{y}.png", made)
        (tmp / "layer.json").write_text(json.dumps(layer, indent=1))
        tiles = "imagery/{z}/{x}/{y}.png"
        if base_url is not None:
            tiles = base_url.rstrip("/") + "/" + tiles
        tilejson = imagery_tilejson(db, Path(tileset).stem, tiles)
        (tmp / "imagery.json").write_text(json.dumps(tilejson, indent=1))
        provider = TilesetProvider(tileset)
        try:
            made = city_tiles(provider)  # as city add made and stored them
        finally:
            provider.close()
        if made is not None:
            (tmp / "3dtiles").mkdir()
            (tmp / "3dtiles" / "tileset.json").write_bytes(made[0])
            for i, glb in enumerate(made[1]):
                (tmp / "3dtiles" / f"{i}.glb").write_bytes(glb)
        if target.exists():
            target.rmdir()
        os.replace(tmp, target)
    except OSError as exc:
        raise TilesetError(f"{target}: cannot write ({exc.strerror or exc})") from None
    finally:
        db.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return count


def _chunks(db: sqlite3.Connection, tables: Sequence[str]) -> Iterator[tuple[str, int, int, int]]:
    """The tiles of ``tables`` ("terrain", "tiles") in chunks of whole columns, about _CHUNK
    tiles each: (table, level, first column, column after the last)."""
    columns = {"terrain": ("z", "x"), "tiles": ("zoom_level", "tile_column")}
    for table in tables:
        z_col, x_col = columns[table]
        rows = db.execute(
            f"SELECT {z_col}, {x_col}, COUNT(*) FROM {table} GROUP BY {z_col}, {x_col} "
            f"ORDER BY {z_col}, {x_col}"
        )
        start: tuple[int, int] | None = None
        last = (0, 0)
        n = 0
        for z, x, count in rows:
            if start is not None and (z != start[0] or n >= _CHUNK):
                yield table, start[0], start[1], last[1] + 1
                start, n = None, 0
            if start is None:
                start = (z, x)
            last = (z, x)
            n += count
        if start is not None:
            yield table, start[0], start[1], last[1] + 1


def write_chunk(tileset: str, folder: str, table: str, z: int, x0: int, x1: int) -> int:
    """Write the tiles of ``table`` of level z, columns x0 <= x < x1 (z < 0: every tile) into
    the export's ``folder``; returns how many."""
    tmp = Path(folder)
    where, params = ("", ()) if z < 0 else (" WHERE {z} = ? AND {x} >= ? AND {x} < ?", (z, x0, x1))
    db = connect_readonly(tileset)
    count = 0
    try:
        if table == "terrain":
            query = "SELECT z, x, y, data FROM terrain" + where.format(z="z", x="x")
            for tz, tx, ty, data in db.execute(query, params):
                tms = (1 << tz) - 1 - ty
                # plain bytes: a static server need not add Content-Encoding headers
                _write(tmp / str(tz) / str(tx) / f"{tms}.terrain", ungzip(bytes(data)))
                count += 1
        else:
            query = "SELECT zoom_level, tile_column, tile_row, tile_data FROM tiles" + where.format(
                z="zoom_level", x="tile_column"
            )
            for tz, tx, row, data in db.execute(query, params):
                _write(
                    tmp / "imagery" / str(tz) / str(tx) / f"{(1 << tz) - 1 - row}.png", bytes(data)
                )
    finally:
        db.close()
    return count


def _geographic_chunks(
    available: dict[int, set[tuple[int, int]]],
) -> Iterator[tuple[int, list[tuple[int, int]]]]:
    """The available geographic tiles in chunks of about _CHUNK: (level, [(x, TMS row)])."""
    for z in sorted(available):
        tiles = sorted(available[z])
        for i in range(0, len(tiles), _CHUNK):
            yield z, tiles[i : i + _CHUNK]


def write_geographic(
    tileset: str, folder: str, z: int, tiles: Sequence[tuple[int, int]]
) -> tuple[int, list[tuple[int, int, int]]]:
    """Write geographic tiles z/x/TMS row (``store.geographic``) of ``tileset`` into the
    export's ``folder``: (how many, those not written: in a hole of the data throughout)."""
    provider = TilesetProvider(tileset)
    zmax = int(provider.manifest["levels"]["zmax"])
    missing: list[tuple[int, int, int]] = []
    count = 0
    try:
        for x, tms in tiles:
            data = geographic_tile(provider, z, x, tms, zmax)
            if data is None:
                missing.append((z, x, tms))
                continue
            _write(Path(folder) / str(z) / str(x) / f"{tms}.terrain", data)
            count += 1
    finally:
        provider.close()
    return count, missing


def geographic_layer(
    db: sqlite3.Connection,
    manifest: dict[str, object],
    name: str,
    available: dict[int, set[tuple[int, int]]],
) -> dict[str, object]:
    """A tileset's Cesium ``layer.json`` in the geographic tiling, ``available`` (x, TMS row)
    by level."""
    layer = _layer(db, manifest, name, available)
    layer["projection"] = "EPSG:4326"
    return layer


def _layer(
    db: sqlite3.Connection,
    manifest: dict[str, object],
    name: str,
    available: dict[int, set[tuple[int, int]]],
) -> dict[str, object]:
    bounds_merc: Any = manifest["bounds_merc"]
    w, s, e, n = lonlat_bounds(Bbox(*bounds_merc))
    top = max(z for z, tiles in available.items() if tiles)
    layer: dict[str, object] = {
        "tilejson": "2.1.0",
        "name": name,
        "description": "terrain built by lodscape",
        "version": "1.0.0",
        "format": "quantized-mesh-1.0",
        "scheme": "tms",
        "projection": "EPSG:3857",
        "extensions": ["octvertexnormals"],
        "tiles": ["{z}/{x}/{y}.terrain?v={version}"],
        "minzoom": 0,
        "maxzoom": top,
        "bounds": [w, s, e, n],
        "available": [_ranges(available.get(z, set())) for z in range(top + 1)],
    }
    row = db.execute("SELECT value FROM metadata WHERE name = 'attribution'").fetchone()
    if row is not None and row[0]:
        layer["attribution"] = str(row[0])
    return layer


def imagery_range(db: sqlite3.Connection) -> tuple[int, int, tuple[float, float, float, float]]:
    """What the imagery's TileJSON advertises: (minzoom, maxzoom, (west, south, east, north)):
    from level 0 (``ImageryTiles`` makes the levels above the stored ones) to the finest
    stored, over the data's bounds."""
    meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    (hi,) = db.execute("SELECT MAX(zoom_level) FROM tiles").fetchone()
    w, s, e, n = (float(v) for v in str(meta.get("bounds", "-180,-85,180,85")).split(","))
    hi = int(hi if hi is not None else meta.get("maxzoom", 0))
    return 0, hi, (w, s, e, n)


def _range_at(
    box: tuple[float, float, float, float], z: int
) -> tuple[tuple[int, int], tuple[int, int]]:
    """The columns and rows (OSM) of level z that the (west, south, east, north) box touches,
    first and last."""
    w, s, e, n = box
    edge = 85.05112878
    (x0, x1), (y0, y1) = lonlat_to_merc([w, e], [max(s, -edge), min(n, edge)])
    return tile_range(Bbox(float(x0), float(y0), float(x1), float(y1)), z)


class ImageryTiles:
    """Every imagery tile of the advertised range (``imagery_range``): the stored ones as they
    are; above the coarsest stored level, overviews made from the four tiles beneath (the
    alpha-weighted mean of each 2×2 texels; MapLibre draws nothing of a raster source below its
    minzoom); where a stored level has no tile (all outside the data: a nodata collar, a rotated
    raster's corners), a transparent one, so a client never meets a 404 it was promised."""

    def __init__(
        self,
        connect: Callable[[], sqlite3.Connection],
        tile_size: int = 256,
        db: sqlite3.Connection | None = None,
    ) -> None:
        """``connect()``: the calling thread's connection to the tileset; ``db``: one to read
        the range from now (else ``connect()``'s)."""
        self._connect = connect
        db = db if db is not None else connect()
        self.range = imagery_range(db)
        (lo,) = db.execute("SELECT MIN(zoom_level) FROM tiles").fetchone()
        self.stored_min = int(lo if lo is not None else 0)
        self.size = tile_size
        self.empty = empty_png(tile_size)
        self._made: dict[tuple[int, int, int], bytes] = {}

    def contains(self, z: int, x: int, y: int) -> bool:
        """Whether tile z/x/y (OSM rows) is inside the advertised range."""
        lo, hi, box = self.range
        if not lo <= z <= hi:
            return False
        (x0, x1), (y0, y1) = _range_at(box, z)
        return x0 <= x <= x1 and y0 <= y <= y1

    def _stored(self, z: int, x: int, y: int) -> bytes | None:
        row = (
            self._connect()
            .execute(
                "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                "AND tile_row = ?",
                (z, x, (1 << z) - 1 - y),
            )
            .fetchone()
        )
        return None if row is None else bytes(row[0])

    def tile(self, z: int, x: int, y: int) -> bytes | None:
        """PNG of tile z/x/y (OSM rows): a stored one (some lie past the bounds: the fill's
        beside the data), else one of the advertised range; None outside it."""
        stored = self._stored(z, x, y)
        if stored is not None:
            return stored
        if not self.contains(z, x, y):
            return None
        if z >= self.stored_min:
            return self.empty
        made = self._made.get((z, x, y))
        if made is None:
            children = [self.tile(z + 1, 2 * x + i % 2, 2 * y + i // 2) for i in range(4)]
            made = _overview(children, self.size)
            self._made[(z, x, y)] = made
        return made

    def missing(self) -> Iterator[tuple[int, int, int]]:
        """The tiles (z, x, OSM row) of the advertised range the tileset does not store."""
        lo, hi, box = self.range
        db = self._connect()
        for z in range(lo, hi + 1):
            (x0, x1), (y0, y1) = _range_at(box, z)
            stored = {
                (x, (1 << z) - 1 - row)
                for x, row in db.execute(
                    "SELECT tile_column, tile_row FROM tiles WHERE zoom_level = ?", (z,)
                )
            }
            for x in range(x0, x1 + 1):
                for y in range(y0, y1 + 1):
                    if (x, y) not in stored:
                        yield z, x, y


def _overview(children: Sequence[bytes | None], size: int) -> bytes:
    """A tile from its four children's PNGs (west-north, east-north, west-south, east-south;
    None: transparent), halved (``imagery.pyramid.halve_rgba``)."""
    from PIL import Image

    big = np.zeros((2 * size, 2 * size, 4), np.float64)
    for i, data in enumerate(children):
        if data is None:
            continue
        img = Image.open(io.BytesIO(data)).convert("RGBA")
        if img.size != (size, size):
            img = img.resize((size, size), Image.Resampling.BILINEAR)
        dx, dy = i % 2, i // 2
        big[dy * size : (dy + 1) * size, dx * size : (dx + 1) * size] = np.asarray(img)
    buf = io.BytesIO()
    rgba = halve_rgba(big)
    Image.fromarray(rgba, "RGBA").save(buf, "PNG", compress_level=6)
    return buf.getvalue()


def empty_png(size: int) -> bytes:
    """A transparent PNG tile, ``size`` pixels a side."""
    from PIL import Image

    buf = io.BytesIO()
    Image.new("RGBA", (size, size), (0, 0, 0, 0)).save(buf, "PNG", optimize=True)
    return buf.getvalue()


def imagery_tilejson(db: sqlite3.Connection, name: str, tiles: str) -> dict[str, object]:
    """TileJSON 3.0.0 of a tileset's imagery (its MBTiles metadata: levels, bounds,
    attribution), its tiles at the URL template ``tiles``."""
    meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    lo, hi, (w, s, e, n) = imagery_range(db)
    return {
        "tilejson": "3.0.0",
        "name": str(meta.get("name", name)),
        "description": str(meta.get("description", "")),
        "attribution": str(meta.get("attribution", "")),
        "scheme": "xyz",
        "format": str(meta.get("format", "png")),
        "tiles": [tiles],
        # the 3.0.0 schema asks for it; a raster source has no vector layers
        "vector_layers": [],
        "minzoom": lo,
        "maxzoom": hi,
        "bounds": [w, s, e, n],
        "center": [(w + e) / 2.0, (s + n) / 2.0, lo],
    }


def cesium_layer(
    db: sqlite3.Connection, manifest: dict[str, object], name: str
) -> tuple[dict[str, object], dict[tuple[int, int, int], bytes]]:
    """A tileset's Cesium ``layer.json`` and the flat tiles (keyed z, x, TMS row) that stand
    above its roots, from the tiling scheme's level 0 down."""
    available: dict[int, set[tuple[int, int]]] = defaultdict(set)
    for z, x, y in db.execute("SELECT z, x, y FROM terrain"):
        available[z].add((x, (1 << z) - 1 - y))
    levels: Any = manifest["levels"]
    zmin = int(levels["zmin"])
    roots = [(x, y) for x, tms in available[zmin] for y in [(1 << zmin) - 1 - tms]]
    flat: dict[tuple[int, int, int], bytes] = {}
    for z in range(zmin):
        for x, y in {(rx >> (zmin - z), ry >> (zmin - z)) for rx, ry in roots}:
            tms = (1 << z) - 1 - y
            flat[(z, x, tms)] = ellipsoid_tile(z, x, y)
            available[z].add((x, tms))
    layer = _layer(db, manifest, name, available)
    return layer, flat


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)


def ellipsoid_tile(z: int, x: int, y: int) -> bytes:
    """Tile z/x/y (OSM rows) of the ellipsoid itself, height 0: a grid regular in Web Mercator
    (so it is cut where the tiling cuts), 32 cells a side at level 0 and 16 below (each cell
    then spans at most 11.25° and its chords sag by at most 1/5 of the level's geometric error
    in Cesium's terms), with the ellipsoid's normals."""
    n = 32 if z == 0 else 16
    b = bounds(Tile(x, y, z))
    xs, ys = grid_coordinates(z, x, y, n)
    lon_col, _ = merc_to_lonlat(xs, np.zeros_like(xs))
    _, lat_row = merc_to_lonlat(np.zeros_like(ys), ys)
    # the sides exactly on the tile's edges, as the edge lists require
    lon_col[0], lon_col[-1], lat_row[0], lat_row[-1] = b.left, b.right, b.top, b.bottom
    grid_lon, grid_lat = np.meshgrid(lon_col, lat_row)
    lon, lat = grid_lon.ravel(), grid_lat.ravel()
    tris = grid_indices(n)[: 2 * n * n].astype(np.int64)
    rect = (b.left, b.bottom, b.right, b.top)
    return encode(lon, lat, np.zeros(lon.size), tris, rect, normals=up_vector(lon, lat))


def _ranges(tiles: set[tuple[int, int]]) -> list[dict[str, int]]:
    """Availability rectangles: runs of consecutive columns, row by row (TMS rows)."""
    out: list[dict[str, int]] = []
    rows: dict[int, list[int]] = defaultdict(list)
    for x, y in tiles:
        rows[y].append(x)
    for y in sorted(rows):
        xs = sorted(rows[y])
        # a run ends where the next column is not the one after it
        breaks = np.flatnonzero(np.diff(xs) != 1)
        starts = [xs[0], *(xs[i + 1] for i in breaks)]
        ends = [*(xs[i] for i in breaks), xs[-1]]
        out.extend(
            {"startX": a, "startY": y, "endX": b, "endY": y}
            for a, b in zip(starts, ends, strict=True)
        )
    return out
