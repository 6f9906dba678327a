"""A tile tree made as the selection reaches it: the cost of opening a DEM follows the view.

``build_tree`` walks the whole raster at its own resolution before the first picture. This
tree makes a tile's statistics (existence, height range, geometric error of each grid) the
first time a selection asks for them, in *chunks*: a tile of level r = zmin + 3i with its
descendants down to r + 2, from the source sampled over that tile alone at levels r .. r + 5
(16·2^k + 1 points a side at level r + k, 513² at most; each level read from the overview
whose pixels fit it, as the meshes are). Within a chunk the statistics are ``build_tree``'s,
by the same steps: a tile's 16-segment error is measured against the chunk's finest sampled
level (exactly: the finer triangles nest in the coarser), plus that level's own error (below),
and saturated by its children's. The chunk samples one level below its last level's finest
grid: that grid's error is then a measured step plus a tail, not a tail alone (the 4097² fBm
of ``bench_spine``: 18-27 % fewer triangles on three of its views than sampling to the grid;
``bench_peers``' first picture of it 3.4 s instead of 2.4: four times the samples a chunk).

What a chunk cannot see is the detail below its finest sampled level L = r + 5, where that is
coarser than the truth (the level whose grid samples the data's own resolution). That *tail*
is bounded by a measurement made once when the tree is opened, over tiles t of each such L
spread evenly over the data (``TAIL_SAMPLES`` of them): T_t = TAIL_MARGIN · D_t(L, L') plus
the tail of t's tiles of L', D_t the largest deviation between level L's grid and the grid of
L', the next such level below it (the last step, onto the truth, from two levels above it at
most: 65² samples a tile at the data's resolution; exact, as in a chunk). A tile's tail is
then an upper envelope of the samples' T_t against their own last step d_t (the deviation of
their parent level's grid from their own): base + slope·d, at most the largest T_t
(``Tail``): rough ground hides more below it than smooth ground does, and a plain beside
mountains is not charged the mountains' detail. It is a measured bound, not a proof: detail
finer than L that is sharper anywhere than everywhere the samples fell (one cliff in a plain)
is underestimated by it. Height ranges are widened by it too. On DEMs whose chunks all reach
the truth (small ones) the tree equals ``build_tree``'s.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape._cache import user_cache
from lodscape.errors import SourceError
from lodscape.terrain.mesh import GRIDS
from lodscape.terrain.pyramid import (
    _BASE,
    SampleSource,
    TileStats,
    _blocks,
    _level_grid,
    _Reference,
    _upsample,
    build_tree,
    deviation,
    level_range,
    level_span,
    measured_error,
    sag,
)
from lodscape.terrain.source import identity

__all__ = [
    "CHUNK_LEVELS",
    "EAGER_SAMPLES",
    "TAIL_MARGIN",
    "TAIL_SAMPLES",
    "LazyTree",
    "Tail",
    "open_tree",
]

F32 = NDArray[np.float32]
I64 = NDArray[np.int64]

#: Levels of tiles one chunk holds (its root's and the two below it).
CHUNK_LEVELS = 3
#: Tiles of a level sampled to measure the detail below the chunks' finest levels.
TAIL_SAMPLES = 64
#: Factor on the measured tail (the largest of a sample is not the largest of all).
TAIL_MARGIN = 1.5
#: Samples of the truth level up to which a source's tree is walked whole when it is opened
#: (``build_tree``: exact, and for a raster of up to about 2,049² pixels quicker than chunks,
#: which sample the levels they share more than once).
EAGER_SAMPLES = 1 << 22
#: Chunks kept in memory (each some 10 kB).
CHUNK_CACHE = 1 << 14


@dataclass(frozen=True)
class Tail:
    """What a grid of level L misses of the data below it, per tile: ``base + slope · d``, d
    the tile's own last step (the largest deviation of its parent level's grid from its own
    over it), at most ``worst``: an upper envelope of the samples' measured tails against
    their own last steps (rough ground hides more below it than smooth ground does)."""

    worst: float
    base: float = 0.0
    slope: float = 0.0

    def of(self, step: NDArray[np.floating]) -> F32:
        """The tail of tiles whose last step is ``step`` metres."""
        local = self.base + self.slope * np.asarray(step, np.float64)
        return np.minimum(local, self.worst).astype(np.float32)


_NO_TAIL = Tail(0.0)


def _envelope(step: NDArray[np.float64], tail: NDArray[np.float64]) -> Tail:
    """The line base + slope·step (both ≥ 0) above every sample (step, tail) whose mean over
    the samples is least (a two-variable linear programme: its optimum is on the samples'
    upper hull, so the slopes between pairs of samples, and zero, are its candidates)."""
    if tail.size == 0:
        return _NO_TAIL
    worst = float(tail.max())
    ds = step[:, None] - step[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        pair = (tail[:, None] - tail[None, :]) / ds
    slopes = np.concatenate([[0.0], pair[np.isfinite(pair) & (pair > 0)]])
    base = np.maximum((tail[None, :] - slopes[:, None] * step[None, :]).max(axis=1), 0.0)
    cost = base + slopes * step.mean()
    i = int(np.argmin(cost))
    return Tail(worst, float(base[i]), float(slopes[i]))


@dataclass(frozen=True, eq=False)
class _Chunk:
    """Per level k = 0..2 below the chunk's root: (2^k, 2^k) arrays, [y, x]."""

    exists: tuple[NDArray[np.bool_], ...]
    min_h: tuple[F32, ...]
    max_h: tuple[F32, ...]
    #: (len(grids), 2^k, 2^k) per level.
    error: tuple[F32, ...]
    #: (2^k·B, 2^k·B) per level, B = 2^(len(grids) - 1): the recorded 16-segment errors of the
    #: tiles whose grids have a level's tiles' finest grid's vertices, B×B blocks a tile
    #: (``LazyTree.grid_blocks``).
    blocks: tuple[F32, ...]


def _pool(a: NDArray[np.floating], f: int, op: str = "max") -> F32:
    """A square per-tile array reduced over f×f blocks (its tiles' ancestors f times larger)."""
    n = a.shape[0] // f
    out: F32 = getattr(a.reshape(n, f, n, f), op)(axis=(1, 3)).astype(np.float32)
    return out


def _step(
    hk: F32,
    vk: NDArray[np.bool_],
    rng: tuple[int, int, int, int],
    hf: F32,
    vf: NDArray[np.bool_],
    fine_rng: tuple[int, int, int, int],
    m: int,
) -> F32:
    """Per tile of the grid ``hf`` (tiles ``fine_rng``, m levels below ``rng``): its largest
    deviation from the coarser grid ``hk``, where both hold data (a step onto nodata is the
    edge's, not the terrain's detail)."""
    whole = vk.astype(np.float32)
    for _ in range(m):
        whole = _upsample(whole)
    ox, oy = fine_rng[0] - (rng[0] << m), fine_rng[1] - (rng[1] << m)
    whole = whole[oy * _BASE : oy * _BASE + hf.shape[0], ox * _BASE : ox * _BASE + hf.shape[1]]
    return deviation(hk, rng, hf, fine_rng, m, vf & (whole == 1.0))


class _Sidecar:
    """Chunks and tails kept between runs: one SQLite file per raster in lodscape's cache
    folder (``trees``; never beside the user's file), holding the source's whole identity
    (``source.identity``): a file that changed since finds its old statistics dropped."""

    def __init__(self, identity: str, name: str) -> None:
        import hashlib

        folder = user_cache() / "trees"
        self.path = folder / f"{hashlib.sha1(name.encode()).hexdigest()[:20]}.sqlite"
        self._conn: sqlite3.Connection | None = None
        self._todo: list[tuple[int, int, int, bytes]] = []
        try:
            folder.mkdir(parents=True, exist_ok=True)
            conn = sqlite3.connect(self.path, timeout=5.0, check_same_thread=False)
            conn.execute("PRAGMA journal_mode=WAL")
            with conn:
                conn.execute("CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value TEXT)")
                conn.execute(
                    "CREATE TABLE IF NOT EXISTS chunks (r INTEGER, x INTEGER, y INTEGER, "
                    "data BLOB, PRIMARY KEY (r, x, y)) WITHOUT ROWID"
                )
                row = conn.execute("SELECT value FROM meta WHERE name = 'identity'").fetchone()
                if row is None or row[0] != identity:
                    # another file (or this one changed): what was kept is not its statistics
                    conn.execute("DELETE FROM chunks")
                    conn.execute("DELETE FROM meta")
                    conn.execute("INSERT INTO meta VALUES ('identity', ?)", (identity,))
            self._conn = conn
        except (OSError, sqlite3.Error):
            self._conn = None  # a read-only or full cache: statistics are made each time

    def tails(self) -> dict[int, Tail] | None:
        if self._conn is None:
            return None
        try:
            row = self._conn.execute("SELECT value FROM meta WHERE name = 'tails'").fetchone()
        except sqlite3.Error:
            return None
        if row is None:
            return None
        return {int(k): Tail(*(float(a) for a in v)) for k, v in json.loads(row[0]).items()}

    def keep_tails(self, tails: dict[int, Tail]) -> None:
        if self._conn is None:
            return
        kept = {k: [t.worst, t.base, t.slope] for k, t in tails.items()}
        try:
            with self._conn:
                self._conn.execute(
                    "INSERT OR REPLACE INTO meta VALUES ('tails', ?)", (json.dumps(kept),)
                )
        except sqlite3.Error:
            self._conn = None

    def get(self, r: int, x: int, y: int, levels: int, grids: int) -> _Chunk | None:
        if self._conn is None:
            return None
        try:
            row = self._conn.execute(
                "SELECT data FROM chunks WHERE r = ? AND x = ? AND y = ?", (r, x, y)
            ).fetchone()
        except sqlite3.Error:
            return None
        return None if row is None else _decode(row[0], levels, grids)

    def put(self, r: int, x: int, y: int, chunk: _Chunk) -> None:
        if self._conn is None:
            return
        self._todo.append((r, x, y, _encode(chunk)))
        if len(self._todo) >= 64:
            self.flush()

    def flush(self) -> None:
        todo, self._todo = self._todo, []
        if self._conn is None or not todo:
            return
        try:
            with self._conn:
                self._conn.executemany("INSERT OR REPLACE INTO chunks VALUES (?, ?, ?, ?)", todo)
        except sqlite3.Error:
            self._conn = None

    def close(self) -> None:
        self.flush()
        if self._conn is not None:
            self._conn.close()
            self._conn = None


def _encode(c: _Chunk) -> bytes:
    parts = []
    for k in range(len(c.exists)):
        parts += [c.exists[k].astype(np.uint8).tobytes(), c.min_h[k].tobytes()]
        parts += [c.max_h[k].tobytes(), c.error[k].astype(np.float32).tobytes()]
        parts += [c.blocks[k].astype(np.float32).tobytes()]
    return b"".join(parts)


def _decode(data: bytes, levels: int, grids: int) -> _Chunk | None:
    ex, lo, hi, er, bl = [], [], [], [], []
    at = 0
    try:
        for k in range(levels):
            n = 1 << k
            ex.append(np.frombuffer(data, np.uint8, n * n, at).reshape(n, n).astype(bool))
            at += n * n
            lo.append(np.frombuffer(data, np.float32, n * n, at).reshape(n, n))
            at += 4 * n * n
            hi.append(np.frombuffer(data, np.float32, n * n, at).reshape(n, n))
            at += 4 * n * n
            er.append(np.frombuffer(data, np.float32, grids * n * n, at).reshape(grids, n, n))
            at += 4 * grids * n * n
            m = n << (grids - 1)
            bl.append(np.frombuffer(data, np.float32, m * m, at).reshape(m, m))
            at += 4 * m * m
    except ValueError:
        return None  # cut short: made again
    if at != len(data):
        return None
    return _Chunk(tuple(ex), tuple(lo), tuple(hi), tuple(er), tuple(bl))


def open_tree(source: SampleSource, *, tile_size: int = 256, grids: tuple[int, ...] = GRIDS) -> Any:
    """The tile tree of a source: walked whole where its truth level holds at most
    EAGER_SAMPLES samples, else made as the selection reaches it."""
    span = level_span(source.bounds_merc, source.resolution_merc, tile_size=tile_size, grids=grids)
    truth = span.texture_zmax + round(math.log2(tile_size / _BASE))
    _, _, nx, ny = level_range(source.bounds_merc, truth)
    if (nx * _BASE + 1) * (ny * _BASE + 1) <= EAGER_SAMPLES:
        return build_tree(source, tile_size=tile_size, grids=grids)
    return LazyTree(source, tile_size=tile_size, grids=grids)


class LazyTree:
    """The tile tree of a height source, its statistics made on demand (see the module)."""

    twist = None
    roughness = None
    #: The finest level's finest grid samples the truth (``pyramid.TileTree``'s).
    finest_is_truth = True

    def __init__(
        self,
        source: SampleSource,
        *,
        tile_size: int = 256,
        grids: tuple[int, ...] = GRIDS,
        workers: int | None = None,
        keep: bool = True,
    ) -> None:
        """``keep``: find and keep statistics in the sidecar (``_Sidecar``) where the source is
        local files."""
        span = level_span(
            source.bounds_merc,
            source.resolution_merc,
            tile_size=tile_size,
            grids=grids,
            max_samples=None,
        )
        self.source = source
        self.grids = grids
        self.tile_size = tile_size
        self.zmin = span.zmin
        self.texture_zmax: int | None = span.texture_zmax
        self.coarsened = 0  # nothing is held whole: never coarsened
        self._depth = len(grids) - 1
        self.truth = span.texture_zmax + round(math.log2(tile_size / _BASE))
        self._zmax = self.truth - self._depth
        self._stands_in = getattr(getattr(source, "fill", None), "kind", "none") != "none"
        self._ranges = {
            z: level_range(source.bounds_merc, z) for z in range(self.zmin, self.truth + 1)
        }
        self._lock = threading.Lock()
        self._chunks: OrderedDict[tuple[int, int, int], _Chunk] = OrderedDict()
        self._pending: set[tuple[int, int, int]] = set()
        #: Make children's statistics before a split (``ready``); False: ask for them and
        #: split once they have come (a scene's streamed frames).
        self.wait = True
        self._pool = ThreadPoolExecutor(
            max_workers=workers or min(8, os.cpu_count() or 1), thread_name_prefix="lodscape-tree"
        )
        #: Chunks made here, and found in the sidecar (for counters and tests).
        self.made = 0
        self.found = 0
        self._sidecar = self._open_sidecar() if keep else None
        tails = None if self._sidecar is None else self._sidecar.tails()
        if tails is None:
            tails = self._measure_tails()
            if self._sidecar is not None:
                self._sidecar.keep_tails(tails)
        self._tails = tails
        self._roots: tuple[I64, I64] | None = None
        self.height_range = self._height_range()

    # --- the tree protocol ------------------------------------------------------------------

    @property
    def zmax(self) -> int:
        return self._zmax

    @property
    def levels(self) -> tuple[_LazyLevel, ...]:
        return tuple(self.level(z) for z in range(self.zmin, self._zmax + 1))

    def level(self, z: int) -> _LazyLevel:
        return _LazyLevel(z, self)

    def roots(self) -> tuple[I64, I64]:
        # the data's own: the same tiles every time, worked out once (a frame asks twice)
        got = self._roots
        if got is None:
            x0, y0, nx, ny = self._ranges[self.zmin]
            st = self.level(self.zmin).stats(
                *[a.ravel() for a in np.meshgrid(np.arange(nx) + x0, np.arange(ny) + y0)]
            )
            yy, xx = np.divmod(np.flatnonzero(st.exists), nx)
            got = ((xx + x0).astype(np.int64), (yy + y0).astype(np.int64))
            for a in got:
                a.flags.writeable = False
            self._roots = got
        return got

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            if self._sidecar is not None:
                self._sidecar.close()
                self._sidecar = None

    def _open_sidecar(self) -> _Sidecar | None:
        ident = identity(self.source)  # type: ignore[arg-type]
        if ident is None:
            return None
        params = (
            f"tree v6|tile {self.tile_size}|grids {self.grids}|chunk {CHUNK_LEVELS}|"
            f"tail {TAIL_SAMPLES}×{TAIL_MARGIN}"
        )
        # one sidecar per raster (its name leaves out size and time: a changed file finds and
        # drops its old statistics rather than leaving them beside new ones)
        name = "\n".join(line.split("|")[0] for line in ident.splitlines())
        return _Sidecar(params + "\n" + ident, params + "\n" + name)

    # --- statistics -------------------------------------------------------------------------

    def tail(self, level: int) -> float:
        """The most metres a grid of ``level`` is taken to miss of the data below it (the
        measured tail; a tile's own is ``tails(level)`` of its last step, often less)."""
        return self.tails(level).worst

    def tails(self, level: int) -> Tail:
        """What a grid of ``level`` is taken to miss of the data below it, per tile."""
        return self._tails.get(level, _NO_TAIL)

    def grid_blocks(self, z: int, x: int, y: int) -> F32 | None:
        """Tile (z, x, y)'s finest grid's own error block by block, B×B (``_Chunk.blocks``),
        from its chunk where that is in memory (nothing made or read); else None."""
        r = self.zmin + CHUNK_LEVELS * ((z - self.zmin) // CHUNK_LEVELS)
        k = z - r
        with self._lock:
            c = self._chunks.get((r, x >> k, y >> k))
        if c is None:
            return None
        b = 1 << self._depth
        lx, ly = x - ((x >> k) << k), y - ((y >> k) << k)
        return c.blocks[k][ly * b : (ly + 1) * b, lx * b : (lx + 1) * b]

    def stats(self, z: int, x: I64, y: I64) -> TileStats:
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        r = self.zmin + CHUNK_LEVELS * ((z - self.zmin) // CHUNK_LEVELS)
        k = z - r
        x0, y0, nx, ny = self._ranges[z]
        inside = (x >= x0) & (x < x0 + nx) & (y >= y0) & (y < y0 + ny)
        n = x.size
        exists = np.zeros(n, bool)
        min_h = np.zeros(n, np.float32)
        max_h = np.zeros(n, np.float32)
        error = np.zeros((len(self.grids), n), np.float32)
        idx = np.flatnonzero(inside)
        if idx.size:
            cx, cy = x[idx] >> k, y[idx] >> k
            keys, inv = np.unique(np.stack([cx, cy], axis=1), axis=0, return_inverse=True)
            inv = inv.ravel()
            chunks = self._get(r, [(int(a), int(b)) for a, b in keys])
            lx, ly = x[idx] - (cx << k), y[idx] - (cy << k)
            ex = np.stack([c.exists[k] for c in chunks])
            lo = np.stack([c.min_h[k] for c in chunks])
            hi = np.stack([c.max_h[k] for c in chunks])
            er = np.stack([c.error[k] for c in chunks])
            exists[idx] = ex[inv, ly, lx]
            min_h[idx] = lo[inv, ly, lx]
            max_h[idx] = hi[inv, ly, lx]
            error[:, idx] = er[inv, :, ly, lx].T
        return TileStats(exists, min_h, max_h, error)

    def ready(self, z: int, x: I64, y: I64) -> NDArray[np.bool_]:
        """Which tiles (z, x, y) a selection may split now: their children's statistics are
        known. With ``wait`` (a picture made whole: ``render``) they are made first, in
        parallel; without (a frame of a flight), those not known are asked for on the workers
        and the tile is drawn whole meanwhile, as a tile whose children have not loaded."""
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        c = z + 1
        out = np.ones(x.size, bool)
        if (c - self.zmin) % CHUNK_LEVELS or c > self._zmax or not x.size:
            return out  # the children lie in their parents' chunk
        cx = (2 * x[:, None] + np.array([0, 1, 0, 1])).ravel()
        cy = (2 * y[:, None] + np.array([0, 0, 1, 1])).ravel()
        keys = [(int(a), int(b)) for a, b in np.unique(np.stack([cx, cy], axis=1), axis=0)]
        if self.wait:
            self._get(c, keys)
            return out
        with self._lock:
            missing = {k for k in keys if (c, *k) not in self._chunks}
        if missing:
            missing -= self._recall(c, sorted(missing)).keys()  # kept from an earlier run
        if not missing:
            return out
        with self._lock:
            for k in missing:
                if (c, *k) not in self._pending:
                    self._pending.add((c, *k))
                    self._pool.submit(self._learn, c, k)
        gone = np.array([(b << 32) | a for a, b in missing], np.int64)
        known = ~np.isin((cy << 32) | cx, gone)
        return np.asarray(known.reshape(-1, 4).all(axis=1), bool)

    def _recall(self, r: int, keys: list[tuple[int, int]]) -> dict[tuple[int, int], _Chunk]:
        """The chunks of ``keys`` found in the sidecar, now in memory too."""
        found: dict[tuple[int, int], _Chunk] = {}
        levels = min(CHUNK_LEVELS, self._zmax - r + 1)
        with self._lock:
            if self._sidecar is None:
                return found
            for key in keys:
                c = self._sidecar.get(r, *key, levels, len(self.grids))
                if c is not None:
                    self._chunks[(r, *key)] = c
                    found[key] = c
            self.found += len(found)
        return found

    def _learn(self, r: int, key: tuple[int, int]) -> None:
        try:
            chunk = self._chunk(r, *key)
        except Exception:  # a read that failed: asked for again by a later frame
            with self._lock:
                self._pending.discard((r, *key))
            return
        with self._lock:
            self._pending.discard((r, *key))
            self._store(r, key, chunk)
            if self._sidecar is not None and not self._pending:
                self._sidecar.flush()

    def _store(self, r: int, key: tuple[int, int], chunk: _Chunk) -> None:
        """Keep a chunk (the lock held)."""
        self._chunks[(r, *key)] = chunk
        self.made += 1
        if self._sidecar is not None:
            self._sidecar.put(r, *key, chunk)
        while len(self._chunks) > CHUNK_CACHE:
            self._chunks.popitem(last=False)

    def _get(self, r: int, keys: list[tuple[int, int]]) -> list[_Chunk]:
        out: dict[tuple[int, int], _Chunk] = {}
        with self._lock:
            for key in keys:
                c = self._chunks.get((r, *key))
                if c is not None:
                    self._chunks.move_to_end((r, *key))
                    out[key] = c
        todo = [key for key in keys if key not in out]
        if todo:
            out.update(self._recall(r, todo))
            todo = [key for key in keys if key not in out]
        if len(todo) == 1:
            out[todo[0]] = self._chunk(r, *todo[0])
        elif todo:
            for key, c in zip(
                todo, self._pool.map(lambda k: self._chunk(r, *k), todo), strict=True
            ):
                out[key] = c
        if todo:
            with self._lock:
                for key in todo:
                    self._store(r, key, out[key])
                if self._sidecar is not None:
                    self._sidecar.flush()  # one transaction a batch
        return [out[key] for key in keys]

    def _chunk(self, r: int, cx: int, cy: int) -> _Chunk:
        """Statistics of tile (r, cx, cy) and its descendants to r + 2, from its samples."""
        finest = min(self._finest(r), self.truth)
        grids = [
            _level_grid(self.source, r + k, (cx << k, cy << k, 1 << k, 1 << k))
            for k in range(finest - r + 1)
        ]
        # the finest sampled level: its tiles' range and existence from their own samples, what
        # they miss below from their own last step
        h, valid = grids[-1]
        n = 1 << (finest - r)
        rng_f = (cx << (finest - r), cy << (finest - r), n, n)
        tail = self.tails(finest)
        if tail.worst > 0.0:
            hp, vp = grids[-2]
            rng_p = (cx << (finest - r - 1), cy << (finest - r - 1), n // 2, n // 2)
            tail_f = tail.of(_step(hp, vp, rng_p, h, valid, rng_f, 1))
        else:
            tail_f = np.zeros((n, n), np.float32)
        blocks = _blocks(h)
        lo: F32 = blocks.min(axis=(2, 3)).astype(np.float32) - tail_f
        hi: F32 = blocks.max(axis=(2, 3)).astype(np.float32) + tail_f
        ex = np.asarray(_blocks(valid).any(axis=(2, 3)), bool)
        e16: F32 = np.where(ex, tail_f, np.float32(0.0)).astype(np.float32)
        per_level: list[tuple[NDArray[np.bool_], F32, F32, F32]] = [(ex, lo, hi, e16)]
        last = len(grids) - 1
        ref = _Reference(
            r + last,
            h,
            (cx << last, cy << last, 1 << last, 1 << last),
            ex,
            e16,
            valid if finest == self.truth else None,
        )
        for k in range(last - 1, -1, -1):
            hk, vk = grids[k]
            cex, clo, chi, ce16 = per_level[0]
            # measured against the finest sampled level, saturated by the children's
            rng = (cx << k, cy << k, 1 << k, 1 << k)
            e16 = np.maximum(
                _pool(np.where(cex, ce16, 0.0), 2), measured_error(hk, rng, ref, r + k)
            )
            b = _blocks(hk)
            lo = np.minimum(b.min(axis=(2, 3)).astype(np.float32), _pool(clo, 2, "min"))
            hi = np.maximum(b.max(axis=(2, 3)).astype(np.float32), _pool(chi, 2))
            ex = np.asarray(_blocks(vk).any(axis=(2, 3)), bool) | (
                _pool(cex.astype(np.float32), 2) > 0
            )
            per_level.insert(0, (ex, lo, hi, e16))
        exists, mins, maxs, errors, own_blocks = [], [], [], [], []
        for k in range(min(CHUNK_LEVELS, self._zmax - r + 1)):
            ex, lo, hi, _ = per_level[k]
            z = r + k
            x0, y0, nx, ny = self._ranges[z]
            n = 1 << k
            xs = (cx << k) + np.arange(n)
            ys = (cy << k) + np.arange(n)
            within = ((ys >= y0) & (ys < y0 + ny))[:, None] & ((xs >= x0) & (xs < x0 + nx))[None, :]
            ex = within & (ex | self._stands_in)
            errs = []
            for j in range(self._depth + 1):
                ej = per_level[k + j][3]
                errs.append(
                    _pool(ej, 1 << j) + sag(z, self.grids[j], ys)[:, None].astype(np.float32)
                )
            exists.append(ex)
            mins.append(lo)
            maxs.append(hi)
            errors.append(np.stack(errs).astype(np.float32))
            # the tiles whose 16-segment grids are this level's finest grid, block by block
            # (as ``errs``' last grid is their largest)
            fe16 = per_level[k + self._depth][3]
            fys = (cy << (k + self._depth)) + np.arange(fe16.shape[0])
            own = fe16 + sag(z + self._depth, self.grids[0], fys)[:, None].astype(np.float32)
            own_blocks.append(own.astype(np.float32))
        return _Chunk(tuple(exists), tuple(mins), tuple(maxs), tuple(errors), tuple(own_blocks))

    def _finest(self, r: int) -> int:
        """The finest level a chunk of root level ``r`` samples: one below its last level's
        finest grid's (five below its root), the truth at most."""
        return min(r + CHUNK_LEVELS + self._depth, self.truth)

    # --- opening ----------------------------------------------------------------------------

    def _measure_tails(self) -> dict[int, Tail]:
        """Per level L below which chunks do not see (a chunk's finest sampled level short of
        the truth), from tiles t of L spread over the data: their tail T_t = TAIL_MARGIN ·
        D_t(L, L') + the largest tail of their tiles of L' (L' the next such level or the
        truth, D the measured deviation), fitted against their own last step d_t
        (``_envelope``; module)."""
        short = {self._finest(r) for r in range(self.zmin, self._zmax + 1, CHUNK_LEVELS)}
        short = {level for level in short if level < self.truth}
        if not short:
            return {}
        # the step onto the truth at most two levels long, onto the level above it one: what
        # is read at the data's own resolution (those two levels' spacing) stays a 65² sample
        # a tile at most (a remote file's full-resolution reads are the dear ones)
        levels = sorted({*short, max(min(short), self.truth - 2)})
        below = dict(zip(levels, [*levels[1:], self.truth], strict=True))
        jobs = [(k, t) for k in levels for t in self._spread(k)]
        steps = list(
            self._pool.map(lambda job: self._increment(job[0], job[1], below[job[0]]), jobs)
        )
        tails: dict[int, Tail] = {}
        for k in reversed(levels):
            under = tails.get(below[k], _NO_TAIL)
            d, t = [], []
            for (level, _), (dev, own, fine) in zip(jobs, steps, strict=True):
                if level != k or own is None:
                    continue
                sub = float(under.of(fine).max()) if fine is not None else under.worst
                d.append(own)
                t.append(TAIL_MARGIN * dev + sub)
            tails[k] = _envelope(np.array(d, np.float64), np.array(t, np.float64))
        return tails

    def _spread(self, k: int) -> list[tuple[int, int]]:
        """Up to TAIL_SAMPLES tiles of level k: 4×4 neighbours around each of a few places spread
        evenly over its range (neighbours share the file's blocks: a remote file is fetched in
        a few places, not all over)."""
        x0, y0, nx, ny = self._ranges[k]
        side = max(1, math.isqrt(TAIL_SAMPLES // 16))
        out: set[tuple[int, int]] = set()
        for a in range(side):
            for b in range(side):
                cx = x0 + int((a + 0.5) * nx / side) - 2
                cy = y0 + int((b + 0.5) * ny / side) - 2
                for dx in range(4):
                    for dy in range(4):
                        x, y = cx + dx, cy + dy
                        if x0 <= x < x0 + nx and y0 <= y < y0 + ny:
                            out.add((x, y))
        return sorted(out)

    def _increment(
        self, k: int, t: tuple[int, int], fine: int
    ) -> tuple[float, float | None, NDArray[np.float32] | None]:
        """For tile t of level k: the largest deviation of its grid from level ``fine``'s over
        it (exact: the finer triangles nest in the coarser), its own last step (its parent
        level's grid against its own over it; None where it holds no data), and the last steps
        of its tiles of level ``fine`` (None where ``fine`` is the truth, which misses
        nothing)."""
        x, y = t
        m = fine - k
        hk, vk = _level_grid(self.source, k, (x, y, 1, 1))
        if not vk.any():
            return 0.0, None, None
        hp, vp = _level_grid(self.source, k - 1, (x >> 1, y >> 1, 1, 1))
        own = float(_step(hp, vp, (x >> 1, y >> 1, 1, 1), hk, vk, (x, y, 1, 1), 1).max())
        fine_rng = (x << m, y << m, 1 << m, 1 << m)
        hc, vc = _level_grid(self.source, fine, fine_rng)
        dev = float(_step(hk, vk, (x, y, 1, 1), hc, vc, fine_rng, m).max())
        if fine >= self.truth:
            return dev, own, None
        if m == 1:
            hq, vq, rq = hk, vk, (x, y, 1, 1)
        else:
            rq = (x << (m - 1), y << (m - 1), 1 << (m - 1), 1 << (m - 1))
            hq, vq = _level_grid(self.source, fine - 1, rq)
        return dev, own, _step(hq, vq, rq, hc, vc, fine_rng, 1)

    def _height_range(self) -> tuple[float, float]:
        # a raster's (a fill forwards it) from its coarse grid; a mosaic's from its roots
        known = getattr(self.source, "data_range", None)
        if known is not None:
            return float(known[0]), float(known[1])
        st = self.level(self.zmin).stats(*self.roots())
        if not st.exists.any():
            raise SourceError(f"{self.source.name}: no valid heights inside the data's footprint")
        return float(st.min_h[st.exists].min()), float(st.max_h[st.exists].max())


@dataclass(frozen=True, eq=False)
class _LazyLevel:
    z: int
    tree: LazyTree

    def stats(self, x: I64, y: I64) -> TileStats:
        return self.tree.stats(self.z, x, y)
