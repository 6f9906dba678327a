"""A build's unit of work: a block, the tiles under one root tile over DEPTH + 1 levels.

A build goes up the tree in bands of levels. In the first, each block's finest tiles are made
from the data (a bounded read: their pixels are about as fine as their texels), and each tile
above from its four children; in every later band, the block's finest tiles are made from the
roots of the band below, read back from those blocks' shards. So no task reads more pixels than
its finest tiles cover, whatever its level, and a coarse tile costs what a fine one does.

A worker writes its block to a shard of its own (one SQLite file, renamed into place when it is
whole); the coordinator only merges finished shards into the tileset, SQLite copying the rows.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import sqlite3
import zlib
from collections.abc import Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from lodscape._tmp import temp_beside
from lodscape.build.tiles import (
    Job,
    Made,
    _source,
    made_from_children,
    made_from_data,
    made_without_data,
    tile_budget,
)
from lodscape.geo.tiles import MAX_ZOOM, ORIGIN, Bbox, bounds_array
from lodscape.store.tileset import SHARD_SCHEMA, TIN_GRID, TileRecord, TilesetError
from lodscape.terrain.source import HeightSource, rasters_of

__all__ = [
    "DEPTH",
    "Band",
    "Block",
    "bands",
    "clear_shards",
    "make_block",
    "plan_blocks",
    "root_path",
    "shard_path",
    "touching",
]

#: Levels a block reaches below its root: up to 4^DEPTH tiles at its finest level.
DEPTH = 3


@dataclass(frozen=True)
class Band:
    """Levels ``root`` .. ``leaf`` of the tree, made together block by block."""

    leaf: int
    root: int


def bands(finest: int, zmin: int) -> list[Band]:
    """The bands from the finest level up to ``zmin``, finest first."""
    out = []
    leaf = finest
    while leaf >= zmin:
        root = max(leaf - DEPTH, zmin)
        out.append(Band(leaf, root))
        leaf = root - 1
    return out


@dataclass(frozen=True)
class Block:
    """The tiles under root z/x/y down to level ``leaf``. ``empty``: the plan found no data in
    it (it is not made). ``below``: the roots of the band below that this block's finest tiles
    are made from, those that were made (None: its finest tiles are made from the data), so a
    shard that should be there and is not is an error, never a silent hole."""

    z: int
    x: int
    y: int
    leaf: int
    empty: bool = False
    below: frozenset[tuple[int, int]] | None = None

    @property
    def key(self) -> tuple[int, int, int]:
        return (self.z, self.x, self.y)


def shard_path(folder: str | os.PathLike[str], z: int, x: int, y: int) -> Path:
    """Where the block rooted at z/x/y waits to be merged into the tileset (then removed)."""
    return Path(folder) / f"{z}-{x}-{y}.sqlite"


def root_path(folder: str | os.PathLike[str], z: int, x: int, y: int) -> Path:
    """Where the root of the block z/x/y is kept, for the band above, until the build ends."""
    return Path(folder) / f"{z}-{x}-{y}.root.sqlite"


_SHARD = re.compile(r"^\.?\d+-\d+-\d+(\.root)?\.sqlite(\.\d+\.tmp)?$")


def clear_shards(folder: str | os.PathLike[str]) -> None:
    """Remove a build's shards (and their temporaries) from ``folder``, then the folder if
    nothing else is in it: a folder the user named may hold other files, never touched."""
    path = Path(folder)
    try:
        names = os.listdir(path)
    except OSError:
        return
    for name in names:
        if _SHARD.match(name):
            (path / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        path.rmdir()  # only if empty


def touching(
    source: HeightSource, z: int, x: NDArray[np.int64], y: NDArray[np.int64]
) -> NDArray[np.bool_]:
    """Which tiles of level z touch the data's footprint: a 5×5 lattice over each tile, and the
    tile's point nearest the centre of each footprint the data is made of (a footprint smaller
    than the lattice's spacing falls between its points; a mosaic's members far apart leave
    their joint box's centre on none of them)."""
    if x.size == 0:
        return np.zeros(0, bool)
    f = np.linspace(0.0, 1.0, 5)
    left, bottom, right, top = bounds_array(z, x, y)
    px = left[:, None, None] + f[None, None, :] * (right - left)[:, None, None]
    py = bottom[:, None, None] + f[None, :, None] * (top - bottom)[:, None, None]
    pxb, pyb = np.broadcast_arrays(px, py)
    lattice = np.asarray(source.covers(pxb, pyb), bool).reshape(x.size, -1)
    hit: NDArray[np.bool_] = np.any(lattice, axis=1)
    for b in footprints(source):
        cx, cy = (b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0
        near = np.asarray(source.covers(np.clip(cx, left, right), np.clip(cy, bottom, top)), bool)
        hit = hit | near
    return hit


def footprints(source: HeightSource) -> list[Bbox]:
    """The boxes (Web Mercator) of the data ``source`` is made of: each raster's under it
    (``terrain.source.rasters_of``: a mosaic's members, through its fill); else its own."""
    return [r.bounds_merc for r in rasters_of(source)] or [source.bounds_merc]


def planned(source: HeightSource, block: Block) -> dict[int, NDArray[np.int64]]:
    """The block's tiles per level, (n, 2) columns and rows: those touching the data's
    footprint where the coarse overview finds data, and every parent of one."""
    has_data = getattr(source, "has_data", None)
    out: dict[int, NDArray[np.int64]] = {}
    below: NDArray[np.int64] | None = None
    for z in range(block.leaf, block.z - 1, -1):
        d = z - block.z
        side = 1 << d
        yy, xx = np.mgrid[0:side, 0:side]
        x = (block.x << d) + xx.ravel().astype(np.int64)
        y = (block.y << d) + yy.ravel().astype(np.int64)
        hit = touching(source, z, x, y)
        if has_data is not None and hit.any():
            hit[hit] = has_data(*bounds_array(z, x[hit], y[hit]))
        if below is not None and below.size:
            parents = np.zeros((side, side), bool)
            parents[(below[:, 1] >> 1) - (block.y << d), (below[:, 0] >> 1) - (block.x << d)] = True
            hit |= parents.ravel()
        out[z] = np.stack([x[hit], y[hit]], axis=1)
        below = out[z]
    return out


class _Shard:
    """A block's shard being written: a temporary SQLite file renamed into place when whole,
    its root's own file (with what the band above is made from) put in place just before."""

    def __init__(self, folder: str, block: Block) -> None:
        self.path = shard_path(folder, *block.key)
        self.root_path = root_path(folder, *block.key)
        self.tmp = temp_beside(self.path)
        self.tiles = 0
        self.root: Made | None = None
        with self._writing():
            self.tmp.unlink(missing_ok=True)
            self.db = sqlite3.connect(self.tmp, isolation_level=None)
            self.db.execute("PRAGMA journal_mode=OFF")
            self.db.execute("PRAGMA synchronous=OFF")
            self.db.executescript(SHARD_SCHEMA)
            self.db.execute("BEGIN")

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """SQLite's and the OS's write errors as one line that names the shard."""
        try:
            yield
        except (sqlite3.Error, OSError) as exc:
            text = str(exc)
            if "full" in text or getattr(exc, "errno", None) == errno.ENOSPC:
                why = "the disk is full"
            elif "I/O" in text or isinstance(exc, OSError):
                why = f"{text}: is the disk full, or the file over a size limit?"
            else:
                why = text
            raise TilesetError(f"{self.path}: cannot write ({why})") from None

    def add(self, made: Made, *, root: bool = False) -> None:
        with self._writing():
            _insert(self.db, made, surface=False)
        if root:
            self.root = made
        self.tiles += 1

    def close(self) -> None:
        """The root's file, then the shard committed, synced and renamed into place: a shard
        that exists is whole, and so is its root's file."""
        with self._writing():
            if self.root is not None:
                tmp = temp_beside(self.root_path)
                tmp.unlink(missing_ok=True)
                with closing(sqlite3.connect(tmp, isolation_level=None)) as db:
                    db.executescript(SHARD_SCHEMA)
                    db.execute("BEGIN")
                    _insert(db, self.root, surface=True)
                    db.execute("COMMIT")
                os.replace(tmp, self.root_path)
            self.db.execute("COMMIT")
            self.db.close()
            with open(self.tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(self.tmp, self.path)

    def abandon(self) -> None:
        db = getattr(self, "db", None)
        if db is not None:
            db.close()
        self.tmp.unlink(missing_ok=True)


def _insert(db: sqlite3.Connection, made: Made, *, surface: bool) -> None:
    """A made tile's rows (and, ``surface``, what its parent is made from)."""
    r = made.record
    if r.error is not None:
        db.execute(
            "INSERT OR REPLACE INTO terrain VALUES (?, ?, ?, ?, ?, ?, ?)",
            (r.z, r.x, r.y, r.error, r.min_h, r.max_h, r.terrain),
        )
    if r.imagery is not None:
        db.execute(
            "INSERT OR REPLACE INTO tiles VALUES (?, ?, ?, ?)",
            (r.z, r.x, (1 << r.z) - 1 - r.y, r.imagery),
        )
    db.execute("INSERT OR REPLACE INTO plan VALUES (?, ?, ?, 1)", (r.z, r.x, r.y))
    if surface:
        valid = errors = grid = None
        if made.valid is not None:
            valid = zlib.compress(np.packbits(made.valid.ravel()).tobytes())
        if made.errors is not None:
            errors = zlib.compress(made.errors.astype("<f4").tobytes())
        if made.grid is not None:
            grid = zlib.compress(made.grid.astype("<f4").tobytes())
        db.execute(
            "INSERT OR REPLACE INTO surface VALUES (?, ?, ?, ?, ?, ?)",
            (r.z, r.x, r.y, valid, errors, grid),
        )


def read_root(folder: str, z: int, x: int, y: int) -> Made | None:
    """The root tile of the block z/x/y from its file (None: no such block)."""
    path = root_path(folder, z, x, y)
    if not path.exists():
        return None
    with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
        t = db.execute(
            "SELECT error, min_h, max_h, data FROM terrain WHERE z = ? AND x = ? AND y = ?",
            (z, x, y),
        ).fetchone()
        i = db.execute(
            "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? AND tile_row = ?",
            (z, x, (1 << z) - 1 - y),
        ).fetchone()
        s = db.execute(
            "SELECT valid, errors, grid FROM surface WHERE z = ? AND x = ? AND y = ?", (z, x, y)
        ).fetchone()
    db.close()
    imagery = None if i is None else bytes(i[0])
    if t is None:
        record = TileRecord(z, x, y, imagery=imagery)
    else:
        record = TileRecord(z, x, y, float(t[0]), float(t[1]), float(t[2]), bytes(t[3]), imagery)
    valid = errors = grid = None
    if s is not None and s[2] is not None:
        points = np.frombuffer(zlib.decompress(s[2]), "<f4")
        grid = points.astype(np.float32).reshape(TIN_GRID + 1, TIN_GRID + 1)
    if s is not None and s[0] is not None:
        n = (TIN_GRID + 1) ** 2
        bits = np.unpackbits(np.frombuffer(zlib.decompress(s[0]), np.uint8))[:n]
        valid = bits.astype(bool).reshape(TIN_GRID + 1, TIN_GRID + 1)
    if s is not None and s[1] is not None:
        cells = np.frombuffer(zlib.decompress(s[1]), "<f4")
        errors = cells.astype(np.float32).reshape(TIN_GRID, TIN_GRID)
    return Made(record, valid, errors, grid)


def make_block(job: Job, block: Block, folder: str, deepen: bool) -> tuple[int, int, int, int]:
    """Make one block and write its shard (the task every executor runs); returns its root
    and the tiles it made. ``deepen``: a tile of the finest terrain level that misses its budget
    gets children, a level at a time, until none does or the grid is twice as fine as the
    data."""
    src = _source(job)
    shard = _Shard(folder, block)
    # where a fill stands in for missing data, a tile with children has all four (those
    # without data from the fill), so a client that splits it never finds a hole
    stand_in = job.fill != "none"
    try:
        levels = planned(src, block)
        below: dict[tuple[int, int], Made] = {}
        for z in range(block.leaf, block.z - 1, -1):
            here: dict[tuple[int, int], Made] = {}
            for x, y in levels[z].tolist():
                if z >= job.zmax:
                    made = made_from_data(job, z, x, y)
                    if deepen and z == job.zmax:
                        _deepen(job, made, shard)
                else:
                    kids = []
                    for i in range(4):
                        key = (2 * x + (i & 1), 2 * y + (i >> 1))
                        kid = _child(folder, below, z + 1, *key, block, z == block.leaf)
                        if kid is None:
                            kid = made_without_data(job, z + 1, *key)
                            if stand_in:
                                shard.add(kid)
                        kids.append(kid)
                    made = made_from_children(job, z, x, y, kids)
                here[(x, y)] = made
                shard.add(made, root=z == block.z)
            below = here
        shard.close()
    except BaseException:
        shard.abandon()
        raise
    return (*block.key, shard.tiles)


def _child(
    folder: str,
    below: dict[tuple[int, int], Made],
    z: int,
    x: int,
    y: int,
    block: Block,
    from_shard: bool,
) -> Made | None:
    """A child a tile is made from: made in this block, or a root of the band below (None:
    outside the data, or a block found empty)."""
    if not from_shard:
        return below.get((x, y))
    made = read_root(folder, z, x, y)
    if made is None and block.below is not None and (x, y) in block.below:
        raise TilesetError(
            f"{root_path(folder, z, x, y)}: the block this build made is gone (was the shards "
            "folder removed?); remove the tileset and build it again"
        )
    return made


def _deepen(job: Job, made: Made, shard: _Shard) -> None:
    """Where a tile misses its budget, its four children from the data, and theirs."""
    r = made.record
    z = r.z
    if r.error is None or z >= MAX_ZOOM:
        return
    if not 2.0 * ORIGIN / (1 << z) / TIN_GRID > job.resolution / 2.0:
        return
    if not r.error > tile_budget(job, z, r.y) * (1.0 + 1e-9):
        return
    finer = replace(job, zmax=z + 1)
    for i in range(4):
        child = made_from_data(finer, z + 1, 2 * r.x + (i & 1), 2 * r.y + (i >> 1))
        shard.add(child)
        _deepen(finer, child, shard)


def plan_blocks(source: HeightSource, band: Band, rows: int = 1) -> Iterator[list[Block]]:
    """The band's blocks touching the data's footprint, a row of roots at a time (so the plan
    is never whole in memory); a block the coarse overview finds no data in is ``empty``."""
    from lodscape.terrain.pyramid import level_range

    # each footprint's tiles (a mosaic's members far apart: not every tile of their joint box)
    ranges = np.array([level_range(b, band.root) for b in footprints(source)], np.int64)
    _, y0, _, ny = level_range(source.bounds_merc, band.root)
    has_data = getattr(source, "has_data", None)
    for y in range(y0, y0 + ny, rows):
        cols, lines = [], []
        for r in range(y, min(y + rows, y0 + ny)):
            on = (ranges[:, 1] <= r) & (r < ranges[:, 1] + ranges[:, 3])
            if not on.any():
                continue
            xs = np.unique(
                np.concatenate(
                    [np.arange(a, a + n, dtype=np.int64) for a, n in ranges[on][:, [0, 2]]]
                )
            )
            cols.append(xs)
            lines.append(np.full(xs.size, r, np.int64))
        if not cols:
            continue
        xx, yy = np.concatenate(cols), np.concatenate(lines)
        hit = touching(source, band.root, xx, yy)
        xx, yy = xx[hit], yy[hit]
        empty = np.zeros(xx.size, bool)
        if has_data is not None and xx.size:
            empty = ~has_data(*bounds_array(band.root, xx, yy))
        yield [
            Block(band.root, int(a), int(b), band.leaf, bool(e))
            for a, b, e in zip(xx.tolist(), yy.tolist(), empty.tolist(), strict=True)
        ]
