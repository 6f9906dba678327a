"""A tileset as PMTiles v3 archives (one file a static host serves by HTTP range requests): its
imagery as PNG/JPEG tiles, and its terrain as Terrarium PNG tiles (height = R·256 + G + B/256
− 32768 metres), each a separate archive since an archive holds one tile type.

Terrarium tiles (``TerrariumTiles``) are 256² heights of the stored surface of their level at
the pixels' centres, every level from 0 to the data's own; where the tileset has no data a pixel
is transparent (alpha 0) at the fill's height (stated in the metadata; never −32,768 m, which
readers that ignore alpha, as MapLibre does, would draw as a shaft).

Tiles are written in Hilbert order of their tile ids (a clustered archive); identical tiles
(the sea, an empty area) are stored once, by their SHA-256, and consecutive ones run-length
coded. The directories come from the ``pmtiles`` package's serialisation; what does not fit the
first 16 KiB goes to leaf directories. An archive is written under a temporary name and renamed
when complete: a failed export leaves nothing.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import json
import os
import sqlite3
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pmtiles.tile import (
    Compression,
    Entry,
    TileType,
    serialize_directory,
    serialize_header,
    zxy_to_tileid,
)

from lodscape._tmp import temp_beside
from lodscape.errors import LodscapeError
from lodscape.geo.tiles import Tile, merc_to_lonlat, tile_range, xy_bounds
from lodscape.store.export import ImageryTiles
from lodscape.store.manifest import connect_readonly
from lodscape.store.tileset import TilesetError, TilesetProvider

__all__ = ["TerrariumTiles", "export_pmtiles", "terrarium", "write_archive"]

#: Header plus root directory: what a client reads first.
_ROOT_BYTES = 16384 - 127


def export_pmtiles(
    tileset: str | os.PathLike[str],
    imagery: str | os.PathLike[str] | None = None,
    terrain: str | os.PathLike[str] | None = None,
) -> dict[str, int]:
    """Write ``tileset``'s imagery to ``imagery`` and its terrain (Terrarium) to ``terrain``,
    each a PMTiles v3 archive; returns the tiles written per archive."""
    if imagery is None and terrain is None:
        raise TilesetError("nothing to export: give an imagery archive, a terrain one, or both")
    for out in (imagery, terrain):
        if out is not None:
            _check_target(Path(out))
    provider = TilesetProvider(tileset)  # refuses what is not a complete tileset
    db = connect_readonly(tileset)
    written: dict[str, int] = {}
    staged: list[tuple[Path, Path]] = []
    try:
        name = Path(tileset).stem
        if imagery is not None:
            written["imagery"], tmp = _imagery(db, name, Path(imagery))
            staged.append((tmp, Path(imagery)))
        if terrain is not None:
            written["terrain"], tmp = _terrain(db, provider, name, Path(terrain))
            staged.append((tmp, Path(terrain)))
        # both archives complete before either is put in place: a failure leaves neither
        for tmp, out in staged:
            try:
                os.replace(tmp, out)
            except OSError as exc:
                raise TilesetError(f"{out}: cannot write ({exc.strerror or exc})") from None
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        db.close()
        provider.close()
    return written


def _check_target(path: Path) -> None:
    if path.exists() and path.is_dir():
        raise TilesetError(f"{path}: is a folder, not a file to write")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise TilesetError(f"{path}: folder {parent} does not exist")


def _imagery(db: sqlite3.Connection, name: str, out: Path) -> tuple[int, Path]:
    """The tileset's MBTiles imagery (TMS rows) as XYZ tiles."""
    meta = dict(db.execute("SELECT name, value FROM metadata").fetchall())
    fmt = str(meta.get("format", "png")).lower()
    keys = [
        (int(z), int(x), (1 << int(z)) - 1 - int(row))
        for z, x, row in db.execute("SELECT zoom_level, tile_column, tile_row FROM tiles")
    ]
    if not keys:
        raise TilesetError(f"{name}: the tileset holds no imagery to export")
    # every tile of the advertised range: overviews above the stored levels, those without
    # data transparent (stored once)
    every = ImageryTiles(
        lambda: db, int(json.loads(meta.get("lodscape", "{}")).get("tile_size", 256))
    )
    keys += list(every.missing())

    def data(z: int, x: int, y: int) -> bytes:
        made = every.tile(z, x, y)
        if made is None:
            raise TilesetError(f"{name}: imagery tile {z}/{x}/{y} outside its range")
        return made

    metadata = {
        "name": str(meta.get("name", name)),
        "description": str(meta.get("description", "")),
        "attribution": str(meta.get("attribution", "")),
        "type": "baselayer",
        "format": fmt,
    }
    return _stage(out, keys, data, tile_type=3 if fmt in ("jpg", "jpeg") else 2, metadata=metadata)


class TerrariumTiles:
    """A tileset's terrain as Terrarium tiles, for MapLibre, deck.gl and any raster-DEM client:
    every level from 0 to the data's own (``texture_zmax``, where a 256-pixel tile's pixel is as
    fine as the data; finer levels would only cut the same surface smaller), every tile over
    the data's bounds. A tile's pixels are the stored surface of its level (the tileset's roots
    for the levels above them) at their centres; where there is no data (outside the data's
    footprint, or in a hole) they are the fill's height (0 m unless ``--fill value:H``) with
    alpha 0, never −32,768 m (which MapLibre, ignoring alpha, would draw as a shaft)."""

    def __init__(self, provider: TilesetProvider) -> None:
        self.provider = provider
        levels = provider.manifest["levels"]
        self.zmin, self.zmax = int(levels["zmin"]), int(levels["zmax"])
        top = levels.get("texture_zmax")
        self.maxzoom = int(self.zmax if top is None else min(int(top), self.zmax))
        fill = str(provider.manifest.get("options", {}).get("fill", "none"))
        kind, _, value = fill.partition(":")
        #: The fill the tileset was built with, and the height a pixel without data holds.
        self.fill = fill
        self.nodata_height = float(value) if kind == "value" and value else 0.0
        b = provider.bounds_merc
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        self.bounds = (float(w), float(s), float(e), float(n))

    def _range(self, z: int) -> tuple[int, int, int, int]:
        (x0, x1), (y0, y1) = tile_range(self.provider.bounds_merc, z)
        return x0, x1, y0, y1

    def keys(self) -> list[tuple[int, int, int]]:
        """Every tile (z, x, OSM row) of levels 0..maxzoom over the data's bounds."""
        out: list[tuple[int, int, int]] = []
        for z in range(self.maxzoom + 1):
            x0, x1, y0, y1 = self._range(z)
            out.extend((z, x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1))
        return out

    def contains(self, z: int, x: int, y: int) -> bool:
        if not 0 <= z <= self.maxzoom:
            return False
        x0, x1, y0, y1 = self._range(z)
        return x0 <= x <= x1 and y0 <= y <= y1

    def tile(self, z: int, x: int, y: int) -> bytes:
        """Terrarium PNG of tile z/x/y (OSM rows)."""
        level = min(max(z, self.zmin), self.zmax)

        def heights(lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
            h: NDArray[np.float64] = self.provider.surface(
                lon, lat, level, footprint=True, holes=True
            )[0]
            return h

        return terrarium(heights, z, x, y, nodata=self.nodata_height)

    def metadata(self, name: str) -> dict[str, object]:
        return {
            "name": f"{name} terrain",
            "description": "Terrarium: height = R*256 + G + B/256 - 32768 m; alpha 0: no data "
            f"(there the fill's height, {self.nodata_height:g} m)",
            "attribution": str(self.provider.metadata().get("attribution", "")),
            "type": "baselayer",
            "format": "png",
            "encoding": "terrarium",
            "fill": self.fill,
            "nodata_height": self.nodata_height,
            "minzoom": 0,
            "maxzoom": self.maxzoom,
        }


def _terrain(
    db: sqlite3.Connection, provider: TilesetProvider, name: str, out: Path
) -> tuple[int, Path]:
    (count,) = db.execute("SELECT COUNT(*) FROM terrain").fetchone()
    if not count:
        raise TilesetError(f"{name}: the tileset holds no terrain to export")
    tiles = TerrariumTiles(provider)
    return _stage(out, tiles.keys(), tiles.tile, tile_type=2, metadata=tiles.metadata(name))


def terrarium(
    heights: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]],
    z: int,
    x: int,
    y: int,
    size: int = 256,
    *,
    nodata: float = 0.0,
) -> bytes:
    """A Terrarium PNG of tile z/x/y: ``heights(lon, lat)`` at its pixels' centres (NaN: no
    data, transparent, at height ``nodata``)."""
    from PIL import Image

    b = xy_bounds(Tile(x, y, z))
    f = (np.arange(size) + 0.5) / size
    xm = b.left + f * (b.right - b.left)
    ym = b.top - f * (b.top - b.bottom)
    lon, lat = merc_to_lonlat(*np.meshgrid(xm, ym))
    h = np.asarray(heights(np.asarray(lon), np.asarray(lat)), np.float64).reshape(size, size)
    ok = np.isfinite(h)
    v = np.clip(np.where(ok, h, nodata) + 32768.0, 0.0, 65535.99)
    r = np.floor(v / 256.0)
    g = np.floor(v - r * 256.0)
    bl = np.floor((v - r * 256.0 - g) * 256.0)
    rgba = np.stack([r, g, bl, np.where(ok, 255.0, 0.0)], axis=-1).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(buf, "PNG", optimize=False)
    return buf.getvalue()


def write_archive(
    out: Path,
    keys: Iterable[tuple[int, int, int]],
    data: Callable[[int, int, int], bytes],
    *,
    tile_type: int,
    metadata: Mapping[str, object],
) -> int:
    """A PMTiles v3 archive at ``out`` of the tiles ``keys`` (z, x, y; XYZ rows), each read by
    ``data`` in Hilbert order; returns the tiles written."""
    count, tmp = _stage(out, keys, data, tile_type=tile_type, metadata=metadata)
    try:
        os.replace(tmp, out)
    except OSError as exc:
        raise TilesetError(f"{out}: cannot write ({exc.strerror or exc})") from None
    finally:
        tmp.unlink(missing_ok=True)
    return count


def _stage(
    out: Path,
    keys: Iterable[tuple[int, int, int]],
    data: Callable[[int, int, int], bytes],
    *,
    tile_type: int,
    metadata: Mapping[str, object],
) -> tuple[int, Path]:
    """``write_archive``'s archive complete under a temporary name beside ``out``: (tiles
    written, that name); the caller renames it into place (or removes it)."""
    ordered = sorted((zxy_to_tileid(z, x, y), z, x, y) for z, x, y in set(keys))
    if not ordered:
        raise TilesetError(f"{out}: no tiles to write")
    parent = out.parent if str(out.parent) else Path(".")
    tmp = temp_beside(parent / out.name)
    entries: list[Entry] = []
    where: dict[bytes, int] = {}
    lo = [180.0, 90.0, -180.0, -90.0]
    try:
        with tempfile.TemporaryFile(dir=parent) as blobs:
            offset = 0
            for tid, z, x, y in ordered:
                blob = data(z, x, y)
                if not blob:
                    raise LodscapeError(f"tile {z}/{x}/{y}: empty")
                digest = hashlib.sha256(blob).digest()
                at = where.get(digest)
                if at is None:
                    at = where[digest] = offset
                    blobs.write(blob)
                    offset += len(blob)
                last = entries[-1] if entries else None
                if last is not None and last.offset == at and last.tile_id + last.run_length == tid:
                    last.run_length += 1
                else:
                    entries.append(Entry(tid, at, len(blob), 1))
                b = xy_bounds(Tile(x, y, z))
                (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
                lo = [min(lo[0], w), min(lo[1], s), max(lo[2], e), max(lo[3], n)]
            root, leaves = _directories(entries)
            meta = gzip.compress(json.dumps(metadata).encode(), mtime=0)
            zooms = [z for _, z, _, _ in ordered]
            e7 = [round(v * 1e7) for v in lo]
            header = {
                "root_offset": 127,
                "root_length": len(root),
                "metadata_offset": 127 + len(root),
                "metadata_length": len(meta),
                "leaf_directory_offset": 127 + len(root) + len(meta),
                "leaf_directory_length": len(leaves),
                "tile_data_offset": 127 + len(root) + len(meta) + len(leaves),
                "tile_data_length": offset,
                "addressed_tiles_count": len(ordered),
                "tile_entries_count": len(entries),
                "tile_contents_count": len(where),
                "clustered": True,
                "internal_compression": Compression.GZIP,
                "tile_compression": Compression.NONE,
                "tile_type": TileType(tile_type),
                "min_zoom": min(zooms),
                "max_zoom": max(zooms),
                "min_lon_e7": e7[0],
                "min_lat_e7": e7[1],
                "max_lon_e7": e7[2],
                "max_lat_e7": e7[3],
                "center_zoom": min(zooms),
            }
            with tmp.open("wb") as f:
                f.write(serialize_header(header))  # type: ignore[arg-type]
                f.write(root)
                f.write(meta)
                f.write(leaves)
                blobs.seek(0)
                while chunk := blobs.read(1 << 20):
                    f.write(chunk)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise TilesetError(f"{out}: cannot write ({exc.strerror or exc})") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return len(ordered), tmp


def _directories(entries: list[Entry]) -> tuple[bytes, bytes]:
    """(root, leaves): all entries in the root if they fit the first 16 KiB, else leaf
    directories of a growing number of entries, the root pointing at them."""
    root: bytes = serialize_directory(entries)
    if len(root) <= _ROOT_BYTES:
        return root, b""
    size = 4096
    while True:
        leaves = io.BytesIO()
        pointers = []
        for i in range(0, len(entries), size):
            leaf = serialize_directory(entries[i : i + size])
            pointers.append(Entry(entries[i].tile_id, leaves.tell(), len(leaf), 0))
            leaves.write(leaf)
        root = serialize_directory(pointers)
        if len(root) <= _ROOT_BYTES:
            return root, leaves.getvalue()
        size *= 2
