"""The embedded tileset: one SQLite file (paper 000's relational store).

Tables:
- ``metadata`` (name, value): the MBTiles metadata (name, format, bounds, center, minzoom,
  maxzoom, type, version, description, attribution) and, under ``lodscape``, a JSON document:
  schema version, levels, CRS, height range, provenance, build options, whether it is complete;
- ``tiles`` (zoom_level, tile_column, tile_row, tile_data): imagery as PNG, rows counted from the
  south as MBTiles has them, so any MBTiles reader opens the file;
- ``terrain`` (z, x, y, error, min_h, max_h, data): quantized-mesh-1.0 tiles, rows from the north
  (OSM), each with its measured geometric error and height range;
- ``plan`` (z, x, y, done): every tile the build will make, and which are finished.

A build writes each batch of finished tiles, their imagery and their ``done`` marks in one
transaction, so a build killed at any moment loses at most the batch in flight and never leaves a
partial tile; started again, it makes only what ``plan`` has not marked done. A reader refuses a
file whose build has not completed.
"""

from __future__ import annotations

import io
import json
import math
import os
import sqlite3
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape._lru import ByteLRU
from lodscape.errors import SourceError
from lodscape.geo.keys import is_texture, tile_of
from lodscape.geo.tiles import (
    ORIGIN,
    Bbox,
    Tile,
    bounds,
    lonlat_to_merc,
    merc_to_lonlat,
    tiles_array,
)
from lodscape.store.manifest import (
    TilesetError,
    being_written,
    connect_readonly,
    fold_wal,
    hold_for_writing,
    is_tileset,
    read_manifest,
)
from lodscape.store.quantized_mesh import QuantizedMeshError, decode
from lodscape.terrain.mesh import TileMesh, tin_mesh
from lodscape.terrain.pyramid import Level, TileTree

__all__ = [
    "SCHEMA_VERSION",
    "TileRecord",
    "TilesetError",
    "TilesetProvider",
    "TilesetWriter",
    "is_tileset",
    "read_manifest",
    "read_tree",
]

SCHEMA_VERSION = 1
#: The grid size a tileset's meshes are cut from (and what Selection counts triangles by).
TIN_GRID = 64

_SCHEMA = """
CREATE TABLE IF NOT EXISTS metadata (name TEXT PRIMARY KEY, value TEXT);
CREATE TABLE IF NOT EXISTS tiles (
    zoom_level INTEGER NOT NULL, tile_column INTEGER NOT NULL, tile_row INTEGER NOT NULL,
    tile_data BLOB NOT NULL, PRIMARY KEY (zoom_level, tile_column, tile_row));
CREATE TABLE IF NOT EXISTS terrain (
    z INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL, error REAL NOT NULL,
    min_h REAL NOT NULL, max_h REAL NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY (z, x, y)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS plan (
    z INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL, done INTEGER NOT NULL DEFAULT 0,
    PRIMARY KEY (z, x, y)) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS blocks (
    z INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL, tiles INTEGER NOT NULL,
    PRIMARY KEY (z, x, y)) WITHOUT ROWID;
"""

#: The tables a build's shard holds: the tileset's own, and what the next band needs of the
#: tiles it is made from: which of their grid points stand on data (NULL: all), their error
#: bound per grid cell and the heights their meshes were cut from (float32; NULL: none).
SHARD_SCHEMA = (
    _SCHEMA
    + """
CREATE TABLE IF NOT EXISTS surface (
    z INTEGER NOT NULL, x INTEGER NOT NULL, y INTEGER NOT NULL, valid BLOB, errors BLOB,
    grid BLOB, PRIMARY KEY (z, x, y)) WITHOUT ROWID;
"""
)


@dataclass(frozen=True)
class TileRecord:
    """One finished tile, as a build worker returns it."""

    z: int
    x: int
    y: int
    #: None when the tile holds no valid data (it is marked done and left out).
    error: float | None = None
    min_h: float = 0.0
    max_h: float = 0.0
    terrain: bytes = b""
    #: PNG bytes, for tiles down to the finest texture level.
    imagery: bytes | None = None


class TilesetWriter:
    """Creates or resumes a tileset file; one writer per file (the build's coordinator)."""

    def __init__(self, path: str | os.PathLike[str], manifest: dict[str, Any]) -> None:
        self.path = Path(path)
        folder = self.path.parent if str(self.path.parent) else Path(".")
        if not folder.is_dir():
            raise TilesetError(f"{self.path}: folder {folder} does not exist")
        existed = self.path.exists()
        if existed and not is_tileset(self.path):
            raise TilesetError(f"{self.path}: exists and is not a tileset; choose another name")
        try:
            self.db = sqlite3.connect(self.path, isolation_level=None)
            self.db.execute("PRAGMA schema_version")  # creates the file for the lock below
        except sqlite3.Error as exc:
            raise TilesetError(f"{self.path}: cannot write ({exc})") from None
        try:
            self._hold = hold_for_writing(self.path)
        except TilesetError:
            self.db.close()
            raise
        try:
            has_metadata = self.db.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'metadata'"
            ).fetchone()
            old = self._manifest() if has_metadata else None
            if old is not None and _identity(old) != _identity(manifest):
                self.close()
                raise TilesetError(
                    f"{self.path}: was built from other inputs or options; "
                    "remove it, or build again with the same ones to resume"
                )
            # only a file this build may write is switched to WAL (a refused one is left as is)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute("PRAGMA synchronous=NORMAL")
            self.db.executescript(_SCHEMA)
            # tiles an earlier lodscape planned and did not make (it planned every tile ahead;
            # this one records only what it has made)
            self.db.execute("DELETE FROM plan WHERE done = 0")
            if old is None:
                self._set_manifest({**manifest, "complete": False})
        except sqlite3.Error as exc:
            self.close()
            if not existed:  # nothing half-made left behind: not even an empty SQLite file
                for leftover in ("", "-wal", "-shm", "-journal"):
                    Path(str(self.path) + leftover).unlink(missing_ok=True)
            if "full" in str(exc):
                raise TilesetError(f"{self.path}: the disk is full; nothing was written") from None
            if "I/O" in str(exc):
                raise TilesetError(
                    f"{self.path}: cannot write (disk I/O error: is the disk full, or the file "
                    "over a size limit?); nothing was written"
                ) from None
            raise TilesetError(f"{self.path}: cannot write ({exc})") from None
        self.resumed = old is not None

    # --- blocks --------------------------------------------------------------------------

    def blocks_done(self, z: int, y: int) -> set[int]:
        """The columns of the blocks rooted in row y of level z that are in the file."""
        rows = self.db.execute("SELECT x FROM blocks WHERE z = ? AND y = ?", (z, y))
        return {int(x) for (x,) in rows}

    def blocks_made(self, z: int, x0: int, x1: int, y0: int, y1: int) -> set[tuple[int, int]]:
        """The roots (x, y) of level z within x0 <= x < x1, y0 <= y < y1 of the blocks made
        (those found empty are not)."""
        rows = self.db.execute(
            "SELECT x, y FROM blocks WHERE z = ? AND x >= ? AND x < ? AND y >= ? AND y < ? "
            "AND tiles > 0",
            (z, x0, x1, y0, y1),
        )
        return {(int(x), int(y)) for x, y in rows}

    def counts(self) -> tuple[int, int]:
        """(tiles made, blocks done)."""
        tiles = self.db.execute("SELECT COUNT(*) FROM plan").fetchone()[0]
        blocks = self.db.execute("SELECT COUNT(*) FROM blocks").fetchone()[0]
        return int(tiles or 0), int(blocks or 0)

    def merge(self, shard: Path, block: tuple[int, int, int]) -> int:
        """Copy a finished block's shard into the file and record the block done, all or
        nothing (SQLite copies the rows; none passes through Python); returns its tiles."""
        self.db.execute("ATTACH DATABASE ? AS shard", (f"file:{shard}?mode=ro",))
        try:
            with self._transaction():
                self.db.execute("INSERT OR REPLACE INTO terrain SELECT * FROM shard.terrain")
                self.db.execute("INSERT OR REPLACE INTO tiles SELECT * FROM shard.tiles")
                self.db.execute("INSERT OR REPLACE INTO plan SELECT z, x, y, 1 FROM shard.plan")
                (n,) = self.db.execute("SELECT COUNT(*) FROM shard.plan").fetchone()
                self.db.execute("INSERT OR REPLACE INTO blocks VALUES (?, ?, ?, ?)", (*block, n))
        finally:
            self.db.execute("DETACH DATABASE shard")
        return int(n)

    def skip(self, blocks: Sequence[tuple[int, int, int]]) -> None:
        """Record blocks with nothing to make (no data, and holes where there is none)."""
        with self._transaction():
            self.db.executemany("INSERT OR REPLACE INTO blocks VALUES (?, ?, ?, 0)", blocks)

    def finest(self) -> int:
        """The finest level the file holds terrain at."""
        (z,) = self.db.execute("SELECT MAX(z) FROM terrain").fetchone()
        return -1 if z is None else int(z)

    def finish(self, mbtiles: dict[str, str], zmax: int | None = None) -> None:
        """Mark the build complete, with its MBTiles metadata (and its finest level, where the
        build went below the one it planned), and fold the write-ahead log back into the one
        file."""
        manifest = self._manifest() or {}
        if zmax is not None:
            manifest["levels"] = {**manifest["levels"], "zmax": zmax}
        with self._transaction():
            self.db.executemany(
                "INSERT OR REPLACE INTO metadata (name, value) VALUES (?, ?)", mbtiles.items()
            )
            self._set_manifest({**manifest, "complete": True})
        fold_wal(self.db)

    def close(self) -> None:
        self.db.close()
        self._hold.close()

    # --- internals -----------------------------------------------------------------------

    def _manifest(self) -> dict[str, Any] | None:
        row = self.db.execute("SELECT value FROM metadata WHERE name = 'lodscape'").fetchone()
        return None if row is None else dict(json.loads(row[0]))

    def _set_manifest(self, manifest: dict[str, Any]) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO metadata (name, value) VALUES ('lodscape', ?)",
            (json.dumps(manifest, sort_keys=True),),
        )

    def _transaction(self) -> _Transaction:
        return _Transaction(self.db, self.path)


class _Transaction:
    def __init__(self, db: sqlite3.Connection, path: Path) -> None:
        self.db, self.path = db, path

    def __enter__(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: Any, exc: BaseException | None, tb: Any) -> None:
        if exc_type is None:
            try:
                self.db.execute("COMMIT")
                return
            except sqlite3.Error as err:
                exc = err
        # SQLite has already rolled back after some errors (a full disk among them)
        if self.db.in_transaction:
            self.db.execute("ROLLBACK")
        if isinstance(exc, sqlite3.OperationalError) and "full" in str(exc):
            raise TilesetError(
                f"{self.path}: the disk is full; nothing of the last batch was kept, and "
                "the build resumes from there once there is room"
            ) from None
        if isinstance(exc, sqlite3.Error):
            raise TilesetError(f"{self.path}: cannot write ({exc})") from None


def _identity(manifest: dict[str, Any]) -> Any:
    """What must match for a build to resume: the inputs and the options that shape tiles."""
    options = manifest.get("options")
    if isinstance(options, dict):
        # builds written before the mesher was an option were all RTIN's
        options = {"mesher": "rtin", "z_units": None, **options}
    return (
        manifest.get("schema"),
        manifest.get("provenance"),
        options,
        manifest.get("z_factors", {}),
    )


# --- reading ---------------------------------------------------------------------------------


def read_tree(db: sqlite3.Connection, manifest: dict[str, Any]) -> TileTree:
    """The tile tree of a tileset: per level, which tiles exist, their heights and errors."""
    levels = manifest["levels"]
    zmin, zmax = int(levels["zmin"]), int(levels["zmax"])
    rows = np.array(
        db.execute("SELECT z, x, y, error, min_h, max_h FROM terrain").fetchall(), dtype=np.float64
    ).reshape(-1, 6)
    out = []
    for z in range(zmin, zmax + 1):
        r = rows[rows[:, 0] == z]
        if r.size == 0:
            raise TilesetError(f"tileset has no tile at level {z}")
        x = r[:, 1].astype(np.int64)
        y = r[:, 2].astype(np.int64)
        x0, y0 = int(x.min()), int(y.min())
        nx, ny = int(x.max()) - x0 + 1, int(y.max()) - y0 + 1
        exists = np.zeros((ny, nx), dtype=bool)
        min_h = np.zeros((ny, nx), dtype=np.float32)
        max_h = np.zeros((ny, nx), dtype=np.float32)
        error = np.zeros((1, ny, nx), dtype=np.float32)
        exists[y - y0, x - x0] = True
        min_h[y - y0, x - x0] = r[:, 4]
        max_h[y - y0, x - x0] = r[:, 5]
        error[0, y - y0, x - x0] = r[:, 3]
        leaf = None
        if z < zmax:
            # a build refines its finest level only where it missed its budget: elsewhere a
            # tile of the level above has no children and is never split
            kids = rows[rows[:, 0] == z + 1]
            has = np.zeros((ny, nx), dtype=bool)
            px = (kids[:, 1].astype(np.int64) >> 1) - x0
            py = (kids[:, 2].astype(np.int64) >> 1) - y0
            inside = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)
            has[py[inside], px[inside]] = True
            leaf = exists & ~has
            if not leaf.any():
                leaf = None
        out.append(Level(z, x0, y0, exists, min_h, max_h, error, leaf))
    lo, hi = manifest["height_range"]
    return TileTree(
        tuple(out),
        (TIN_GRID,),
        int(manifest["tile_size"]),
        (float(lo), float(hi)),
        0,
        int(levels["texture_zmax"]),
    )


#: A decoded terrain tile: vertex longitudes, latitudes and heights, and triangles.
_Mesh = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]


class TilesetProvider:
    """A tileset file as a Scene's provider: every tile is one indexed query away."""

    textures = "imagery"
    layers: tuple[Any, ...] = ()
    network = False

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.name = str(path)
        if not self.path.exists():
            raise SourceError(f"{self.name}: no such file")
        self._local = threading.local()
        self._lock = threading.Lock()
        self._connections: list[sqlite3.Connection] = []
        self._connect: Callable[[], sqlite3.Connection] | None = None
        self._meshes: ByteLRU[tuple[int, int, int], _Mesh | None] = ByteLRU()
        try:
            db = self._db()
            self.manifest = read_manifest(db, self.name)
        except (sqlite3.Error, TilesetError) as exc:
            self.close()
            if isinstance(exc, TilesetError):
                raise
            raise TilesetError(f"{self.name}: not a lodscape tileset ({exc})") from None
        if self.manifest.get("schema") != SCHEMA_VERSION:
            self.close()
            raise TilesetError(
                f"{self.name}: tileset schema {self.manifest.get('schema')} is not the "
                f"{SCHEMA_VERSION} this lodscape reads"
            )
        if not self.manifest.get("complete"):
            (done,) = db.execute("SELECT COUNT(*) FROM plan").fetchone()
            self.close()
            if being_written(self.path):
                raise TilesetError(
                    f"{self.name}: a build is writing it now ({int(done or 0)} tiles made); "
                    "open it when the build has finished"
                )
            raise TilesetError(
                f"{self.name}: its build stopped at {int(done or 0)} tiles made; run the same "
                "lodscape build again to finish it"
            )
        self.tree = read_tree(db, self.manifest)
        fill = str(self.manifest.get("options", {}).get("fill", "none")).partition(":")[0]
        #: The fill stands in wherever the tiles reach (not none or nearest): every texel drawn.
        self._fill_drawn = fill not in ("none", "nearest")
        b = self.manifest["bounds_merc"]
        self.bounds_merc = Bbox(*(float(v) for v in b))

    def read_with(self, connect: Callable[[], sqlite3.Connection]) -> None:
        """Read through the connections ``connect`` gives (this thread's, to the file as it was
        opened: a server keeps reading the file it loaded when another is renamed over it)."""
        self._connect = connect

    def connection(self) -> sqlite3.Connection:
        """This thread's read-only connection to the tileset."""
        return self._db()

    def _db(self) -> sqlite3.Connection:
        """This thread's read-only connection (SQLite connections are not shared by threads)."""
        if self._connect is not None:
            return self._connect()
        db: sqlite3.Connection | None = getattr(self._local, "db", None)
        if db is None:
            db = connect_readonly(self.path)
            self._local.db = db
            with self._lock:
                self._connections.append(db)
        return db

    def _terrain(self, z: int, x: int, y: int) -> bytes | None:
        row = (
            self._db()
            .execute("SELECT data FROM terrain WHERE z = ? AND x = ? AND y = ?", (z, x, y))
            .fetchone()
        )
        return None if row is None else bytes(row[0])

    def metadata(self) -> dict[str, str]:
        """The MBTiles metadata (name, bounds, attribution, …; the manifest under lodscape)."""
        rows = self._db().execute("SELECT name, value FROM metadata").fetchall()
        return {str(k): str(v) for k, v in rows}

    def max_error(self, z: int, x0: int, x1: int, y0: int, y1: int) -> float | None:
        """The largest recorded error of the stored terrain tiles of level z in columns x0..x1
        and rows y0..y1 (OSM rows, both inclusive); None where there is none."""
        row = (
            self._db()
            .execute(
                "SELECT MAX(error) FROM terrain WHERE z = ? AND x BETWEEN ? AND ? "
                "AND y BETWEEN ? AND ?",
                (z, x0, x1, y0, y1),
            )
            .fetchone()
        )
        return None if row[0] is None else float(row[0])

    def fetch(self, key: int) -> bytes:
        """A tile's stored bytes: gzipped quantized-mesh for a mesh key, PNG for a texture key."""
        t = tile_of(key)
        if is_texture(key):
            row = (
                self._db()
                .execute(
                    "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                    "AND tile_row = ?",
                    (t.z, t.x, (1 << t.z) - 1 - t.y),
                )
                .fetchone()
            )
            if row is None:
                raise TilesetError(f"{self.name}: no imagery tile {t.z}/{t.x}/{t.y}")
            return bytes(row[0])
        data = self._terrain(t.z, t.x, t.y)
        if data is None:
            raise TilesetError(f"{self.name}: no terrain tile {t.z}/{t.x}/{t.y}")
        return data

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        """The stored bytes made ready to upload: a TileMesh with skirts, or RGBA pixels."""
        t = tile_of(key)
        if is_texture(key):
            from PIL import Image

            try:
                rgba = np.array(Image.open(io.BytesIO(data)).convert("RGBA"))
            except Exception as exc:  # Pillow raises several unrelated classes on bad data
                raise TilesetError(f"{self.name}: imagery tile {t.z}/{t.x}/{t.y}: {exc}") from None
            if self._fill_drawn:
                # alpha says where there is data (for clients' base maps); a fill's ground is
                # drawn everywhere the tiles reach, so nothing is cut
                rgba[..., 3] = 255
            return np.ascontiguousarray(rgba)
        try:
            qm = decode(data)
        except QuantizedMeshError as exc:
            raise TilesetError(f"{self.name}: terrain tile {t.z}/{t.x}/{t.y}: {exc}") from None
        b = bounds(t)
        lon, lat, h = qm.positions(b.left, b.bottom, b.right, b.top)
        # the quantized sides are exact: put the edge vertices exactly on the tile's edges
        lon[qm.west], lon[qm.east] = b.left, b.right
        lat[qm.south], lat[qm.north] = b.bottom, b.top
        sides = (qm.west, qm.south, qm.east, qm.north)
        return tin_mesh(key, t.z, t.x, t.y, lon, lat, h, qm.triangles, sides)

    def mesh(self, key: int) -> TileMesh:
        from lodscape.store.provider import mesh_of

        return mesh_of(self, key)

    def texture(self, key: int) -> NDArray[np.uint8]:
        from lodscape.store.provider import texture_of

        return texture_of(self, key)

    @property
    def texture_levels(self) -> tuple[int, ...]:
        """The finest level of the stored imagery (a baked orthophoto's own, which may be
        below the terrain's finest level)."""
        levels = self.manifest.get("levels", {})
        z = levels.get("imagery_zmax", self.tree.texture_zmax)
        return (int(self.tree.zmax if z is None else z),)

    @property
    def resolution_merc(self) -> float | None:
        """The source's cell size the tileset was built from, Web Mercator metres."""
        r = self.manifest.get("resolution_merc")
        return float(r) if r else None

    def ground_height(self, lon: float, lat: float) -> float | None:
        """The height of the finest tile's mesh under the point."""
        h = float(self.heights(np.array([lon]), np.array([lat]))[0])
        return None if np.isnan(h) else h

    def heights_at(self, lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
        """Terrain heights at many points (degrees), NaN outside the data."""
        return self.heights(lon, lat)

    def heights(self, lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
        """Heights of the finest stored meshes at many points (NaN outside the data): each
        tile is read and decoded once per call (and kept for the next few calls)."""
        return self.surface(lon, lat, footprint=True)[0]

    def surface(
        self,
        lon: ArrayLike,
        lat: ArrayLike,
        zmax: int | None = None,
        *,
        footprint: bool = False,
        holes: bool = False,
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """(heights, covered) at many points: the heights of the finest stored meshes of level
        ``zmax`` or coarser (NaN where none has a surface; ``footprint``: NaN outside the
        data's footprint too, where a fill stands in), and whether a stored tile covers the
        point at all (False: outside the tileset's tiles; True and NaN: a hole). A point in a
        hole of the finest tile that covers it is looked for in coarser ones, whose meshes'
        rims may reach it; ``holes``: it stays a hole (NaN)."""
        lon = np.asarray(lon, np.float64)
        lat = np.asarray(lat, np.float64)
        shape = lon.shape
        lon, lat = lon.ravel(), lat.ravel()
        out = np.full(len(lon), np.nan)
        covered = np.zeros(len(lon), bool)
        xm, ym = lonlat_to_merc(lon, lat)
        todo = (np.abs(xm) <= ORIGIN) & (np.abs(ym) <= ORIGIN)  # beyond ±85.05°: no tile
        if footprint:
            b = self.bounds_merc
            todo &= (xm >= b.left) & (xm <= b.right) & (ym >= b.bottom) & (ym <= b.top)
        for lv in reversed(self.tree.levels):
            if zmax is not None and lv.z > zmax:
                continue
            if not todo.any():
                break
            idx = np.nonzero(todo)[0]
            tx, ty = tiles_array(xm[idx], ym[idx], lv.z)
            ok, _ = lv.index(tx, ty)
            idx, tx, ty = idx[ok], tx[ok], ty[ok]
            if not len(idx):
                continue
            covered[idx] = True
            # the points grouped by tile: tile k's are idx[order[ends[k]:ends[k + 1]]]
            key = (tx << 32) | ty
            order = np.argsort(key)
            sorted_key = key[order]
            ends = np.flatnonzero(np.diff(sorted_key, prepend=-1, append=-1))
            for k, cell in enumerate(sorted_key[ends[:-1]].tolist()):
                # a loop over tiles, each a vectorised lookup
                mesh = self._decoded(lv.z, cell >> 32, cell & 0xFFFFFFFF)
                if mesh is None:
                    continue
                at = idx[order[ends[k] : ends[k + 1]]]
                h = _heights_in(mesh, lon[at], lat[at])
                out[at] = h
                todo[at if holes else at[~np.isnan(h)]] = False
        return out.reshape(shape), covered.reshape(shape)

    def tile_heights(
        self, z: int, x: int, y: int, lon: ArrayLike, lat: ArrayLike
    ) -> NDArray[np.float64]:
        """Heights of stored tile z/x/y's own mesh (its level's surface) at points inside it;
        NaN where it has none (a hole, outside the data, or no such tile)."""
        lon = np.asarray(lon, np.float64)
        lat = np.asarray(lat, np.float64)
        mesh = self._decoded(z, x, y)
        if mesh is None:
            return np.full(lon.shape, np.nan)
        h: NDArray[np.float64] = _heights_in(mesh, lon.ravel(), lat.ravel()).reshape(lon.shape)
        return h

    #: Bytes of decoded meshes kept for ``heights`` (a city's footprints, a globe's facets ask
    #: the same tiles again and again; a tile is some 60 KiB).
    DECODED_BYTES = 64 * 2**20

    def _decoded(self, z: int, x: int, y: int) -> _Mesh | None:
        key = (z, x, y)
        cache = self._meshes
        with self._lock:
            if key in cache:
                return cache.get(key)
        data = self._terrain(z, x, y)
        made = None
        if data is not None:
            b = bounds(Tile(x, y, z))
            qm = decode(data)
            plon, plat, h = qm.positions(b.left, b.bottom, b.right, b.top)
            made = (plon, plat, h, qm.triangles.astype(np.int64))
        size = sum(a.nbytes for a in made) if made is not None else 0
        with self._lock:
            if key not in cache:
                cache.put(key, made, size)
            cache.shrink(self.DECODED_BYTES, keep={key})
        return made

    def city(self, names: list[str] | None = None) -> Any:
        """The cities stored in this tileset (``lodscape city add``) as one ``City``, or None."""
        from lodscape.store.city import read_city

        return read_city(self._db(), self.name, names=names)

    def cities(self) -> list[dict[str, object]]:
        """Name, source and counts of each stored city."""
        from lodscape.store.city import list_cities

        return list_cities(self._db())

    def close(self) -> None:
        with self._lock:
            for db in self._connections:
                db.close()
            self._connections = []


def _heights_in(
    mesh: _Mesh, lon: NDArray[np.float64], lat: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Heights of a tile's mesh (lon, lat, height per vertex; triangles) at points inside the
    tile, by the triangle that holds each (NaN where none does).

    The points are bucketed on a grid of cells; each triangle is tested only against the points
    of the cells its box touches (a few per point), not against every point: a 65² grid of
    points on a 4,000-triangle tile costs milliseconds, not the 400 ms of testing every pair."""
    plon, plat, h, tri = mesh
    n = len(lon)
    out = np.full(n, np.nan)
    if n == 0 or len(tri) == 0:
        return out
    x0, x1, y0, y1 = float(lon.min()), float(lon.max()), float(lat.min()), float(lat.max())
    g = int(np.clip(math.isqrt(n) // 2, 1, 256))
    sx, sy = g / max(x1 - x0, 1e-12), g / max(y1 - y0, 1e-12)
    cell = np.clip(((lat - y0) * sy).astype(np.int64), 0, g - 1) * g + np.clip(
        ((lon - x0) * sx).astype(np.int64), 0, g - 1
    )
    order = np.argsort(cell, kind="stable")
    first = np.searchsorted(cell[order], np.arange(g * g))
    count = np.searchsorted(cell[order], np.arange(g * g), side="right") - first
    tx, ty = plon[tri], plat[tri]
    near = (tx.max(1) >= x0) & (tx.min(1) <= x1) & (ty.max(1) >= y0) & (ty.min(1) <= y1)
    t = np.nonzero(near)[0]
    if not t.size:
        return out
    i0 = np.clip(np.floor((tx[t].min(1) - x0) * sx), 0, g - 1).astype(np.int64)
    i1 = np.clip(np.floor((tx[t].max(1) - x0) * sx), 0, g - 1).astype(np.int64)
    j0 = np.clip(np.floor((ty[t].min(1) - y0) * sy), 0, g - 1).astype(np.int64)
    j1 = np.clip(np.floor((ty[t].max(1) - y0) * sy), 0, g - 1).astype(np.int64)
    w = i1 - i0 + 1
    cells = w * (j1 - j0 + 1)
    # every (triangle, cell) its box touches, then every (triangle, point) in those cells
    pair = np.repeat(np.arange(t.size), cells)
    k = np.arange(pair.size) - np.repeat(np.cumsum(cells) - cells, cells)
    cid = (j0[pair] + k // w[pair]) * g + i0[pair] + k % w[pair]
    m = count[cid]
    tri_of = t[np.repeat(pair, m)]
    q = np.arange(tri_of.size) - np.repeat(np.cumsum(m) - m, m)
    pt = order[np.repeat(first[cid], m) + q]
    a, b, c = tri[tri_of, 0], tri[tri_of, 1], tri[tri_of, 2]
    ax, ay, bx, by, cx, cy = plon[a], plat[a], plon[b], plat[b], plon[c], plat[c]
    px, py = lon[pt], lat[pt]
    det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    with np.errstate(divide="ignore", invalid="ignore"):
        wa = ((by - cy) * (px - cx) + (cx - bx) * (py - cy)) / det
        wb = ((cy - ay) * (px - cx) + (ax - cx) * (py - cy)) / det
    wc = 1.0 - wa - wb
    inside = (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9) & (det != 0)
    v = wa * h[a] + wb * h[b] + wc * h[c]
    out[pt[inside]] = v[inside]
    return out


def lonlat_bounds(b: Bbox) -> tuple[float, float, float, float]:
    """An EPSG:3857 box as (west, south, east, north) degrees."""
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    return float(w), float(s), float(e), float(n)
