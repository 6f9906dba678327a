"""Terrain streamed from servers: quantized-mesh behind a Cesium ``layer.json`` (``lodscape
serve`` among them; Web Mercator or geographic tiling) and Terrarium / Terrain-RGB PNG tiles
from an XYZ template. Heights come through the imagery's HTTP client (``HttpSource``: its
timeouts, retries, deadline and SQLite cache), each server tile fetched once and its decoded
form kept in a byte-bounded LRU.

Nothing is known of a server's terrain before its tiles come, so the tile tree learns it
(``RemoteTree``): a tile's height range is its own once its mesh was made, else its nearest
known ancestor's, else ``UNKNOWN_RANGE``; a tile whose own range is not known yet is not split
(as Cesium refines only loaded tiles), so the tree opens a level per round of loads. Geometric
errors are Cesium's estimate for a 65-sample tile of the level (``level_error``), not measured.
Where a server has no tile (404) the terrain has a hole: nothing is made up.
"""

from __future__ import annotations

import json
import math
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urljoin, urlsplit

import numpy as np
from numpy.typing import NDArray

from lodscape._lru import ByteLRU
from lodscape.errors import SourceError
from lodscape.geo.frames import WGS84_A
from lodscape.geo.keys import grid_of, is_texture, tile_of
from lodscape.geo.tiles import ORIGIN, Bbox, lonlat_to_merc, merc_to_lonlat, tile_size
from lodscape.imagery.layers import KINDS, warn_stderr
from lodscape.imagery.sources import (
    HttpSource,
    ImageryError,
    TileCache,
    TileMissing,
    open_image,
)
from lodscape.store.provider import RasterProvider
from lodscape.store.quantized_mesh import QUANTIZED_MAX, QuantizedMeshError, decode
from lodscape.terrain.mesh import GRIDS, grid_coordinates
from lodscape.terrain.pyramid import TileStats

__all__ = [
    "UNKNOWN_RANGE",
    "RemoteHeights",
    "RemoteProvider",
    "RemoteTree",
    "ServerTiles",
    "level_error",
    "open_server",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Heights (metres) a tile is assumed to span before anything of it or its ancestors has come:
#: the deepest sea floor to the highest summit, so nothing is culled that could be seen.
UNKNOWN_RANGE = (-11000.0, 8900.0)
#: Cesium's level-0 error estimate for a 65-sample heightmap over the Web Mercator square
#: (``getEstimatedLevelZeroGeometricErrorForAHeightmap``: a · 2π · 0.25 / 65 per root tile).
_LEVEL0_ERROR = WGS84_A * 2.0 * math.pi * 0.25 / 65.0
#: Decoded server tiles kept, bytes.
_DECODED_BYTES = 256 << 20


def level_error(z: int | I64, segments: int) -> F64:
    """Metres of geometric error of a level-z tile meshed with ``segments`` cells a side:
    Cesium's estimate (64 cells), scaled by the cells' size."""
    return np.asarray(_LEVEL0_ERROR / np.exp2(z) * (64.0 / segments), np.float64)


# --- what a server holds -------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Mesh:
    """A decoded quantized-mesh tile: u, v in 0..1 over the tile, heights, triangles."""

    u: F64
    v: F64
    h: F64
    tri: NDArray[np.int64]
    nbytes: int


@dataclass(frozen=True, eq=False)
class _Raster:
    """A decoded PNG height tile: heights at pixel centres, NaN where it says none."""

    h: NDArray[np.float32]
    nbytes: int


class ServerTiles:
    """One server's height tiles: fetched through ``HttpSource``, decoded once, kept in an LRU.

    ``kind``: "quantized-mesh", "terrarium" or "terrain-rgb"; ``geographic``: the tiling is
    EPSG:4326 (two root tiles), else Web Mercator; ``tms``: rows count from the south."""

    def __init__(
        self,
        name: str,
        template: str,
        kind: str,
        *,
        geographic: bool = False,
        tms: bool = False,
        minzoom: int = 0,
        maxzoom: int = 15,
        bounds: tuple[float, float, float, float] = (-180.0, -90.0, 180.0, 90.0),
        available: list[list[tuple[int, int, int, int]]] | None = None,
        cache: TileCache | None = None,
        timeout: float = 10.0,
        warn: Callable[[str], None] = warn_stderr,
    ) -> None:
        self.name = name
        self._warn = warn
        self.kind = kind
        self.geographic = geographic
        self.tms = tms
        self.minzoom, self.maxzoom = minzoom, maxzoom
        self.bounds = bounds
        #: Per level, rectangles (x0, y0, x1, y1) of the tiles the server has (its own rows).
        self.available = available
        checker = _check_mesh if kind == "quantized-mesh" else None
        self.http = HttpSource(
            template,
            subdomains="abc",
            timeout=timeout,
            deadline=timeout,
            cache=cache,
            max_zoom=maxzoom,
            check=checker,
            accept=_QM_ACCEPT if kind == "quantized-mesh" else None,
        )
        self._decoded: ByteLRU[tuple[int, int, int], _Mesh | _Raster | None] = ByteLRU()
        self._lock = threading.Lock()
        self._inflight: dict[tuple[int, int, int], Future[Any]] = {}
        #: Tiles the server answered 404 for (drawn as holes; the first said on stderr).
        self.missing = 0
        #: Failed tiles by kind (``imagery.layers.KINDS``), and each kind's first failure as a
        #: line to say (``notices``): a flight retries them, drawing a coarser tile (or the
        #: ellipsoid) meanwhile; a one-shot render fails with the error itself.
        self.failures: Counter[str] = Counter()
        self._notices: dict[str, str] = {}
        #: A PNG server's tile size (pixels a side, without a border), from its first tile.
        self.pixels: int | None = None

    @property
    def cells(self) -> int:
        """Cells a side a tile's data resolves (a PNG's pixels, 256 until a tile says; a mesh
        taken as 64)."""
        return 64 if self.kind == "quantized-mesh" else (self.pixels or 256)

    def has(self, z: int, x: I64, y: I64) -> NDArray[np.bool_]:
        """Which tiles (x, y; rows from the north) of level z the server says it has."""
        nx = 1 << (z + 1) if self.geographic else 1 << z
        ny = 1 << z
        ok = (z >= self.minzoom) & (z <= self.maxzoom) & (x >= 0) & (x < nx) & (y >= 0) & (y < ny)
        if not self.available:
            return ok
        # levels past the listed ones (servers that list the first levels in layer.json and
        # the rest in tiles' metadata): the listed ancestor says, and a 404 is a hole
        up = max(z - (len(self.available) - 1), 0)
        lz, lx, ly = z - up, x >> up, y >> up
        row = (1 << lz) - 1 - ly if self.tms else ly
        hit = np.zeros_like(ok)
        for x0, y0, x1, y1 in self.available[lz]:
            hit |= (lx >= x0) & (lx <= x1) & (row >= y0) & (row <= y1)
        return ok & hit

    def tile(self, z: int, x: int, y: int) -> _Mesh | _Raster | None:
        """Tile z/x/y (rows from the north) decoded; None where the server has none (404, or
        outside what it says it has). Fetch failures raise ``ImageryError`` in one line."""
        key = (z, x, y)
        with self._lock:
            if key in self._decoded:
                return self._decoded.get(key)
            running = self._inflight.get(key)
            mine = running is None
            if mine:
                running = Future()
                self._inflight[key] = running
        assert running is not None
        if not mine:
            got: _Mesh | _Raster | None = running.result()
            return got
        try:
            made = self._make(z, x, y)
        except BaseException as exc:
            with self._lock:
                self._inflight.pop(key, None)
            running.set_exception(exc)
            raise
        with self._lock:
            self._decoded.put(key, made, 64 if made is None else made.nbytes)
            self._decoded.shrink(_DECODED_BYTES)
            self._inflight.pop(key, None)
        running.set_result(made)
        return made

    def cached(self, z: int, x: int, y: int) -> _Mesh | _Raster | bool | None:
        """The decoded tile if it is here (None: known missing), False if it has not come."""
        with self._lock:
            if (z, x, y) in self._decoded:
                return self._decoded.get((z, x, y))
        return False

    def _make(self, z: int, x: int, y: int) -> _Mesh | _Raster | None:
        if not bool(self.has(z, np.array([x]), np.array([y]))[0]):
            return None
        row = (1 << z) - 1 - y if self.tms else y
        try:
            data = self.http.fetch(z, x, row)
            if self.kind == "quantized-mesh":
                return _decode_mesh(data)
            raster = _decode_png(data, self.kind, self.http.url(z, x, row))
            side = raster.h.shape[0]
            with self._lock:
                if self.pixels is None:
                    self.pixels = side
                seen = self.pixels
            if side != seen:
                raise ImageryError(
                    f"{self.http.url(z, x, row)}: {side} pixels a side where this server's "
                    f"first tile had {seen}",
                    "not-terrain",
                )
            return raster
        except TileMissing as exc:
            with self._lock:
                self.missing += 1
                first = self.missing == 1
            if first:
                self._warn(
                    f"terrain: {exc}; where {self.name} has no tile, its deepest ancestor the "
                    "server has is drawn (a hole where it has none)"
                )
            return None
        except ImageryError as exc:
            self._failed(exc.kind, str(exc))
            raise
        except QuantizedMeshError as exc:
            self._failed("not-terrain", str(exc))
            raise ImageryError(f"{self.http.url(z, x, row)}: {exc}", "not-terrain") from None

    def _failed(self, kind: str, message: str) -> None:
        what = KINDS.get(kind, _NOT_TERRAIN if kind == "not-terrain" else kind)
        with self._lock:
            self.failures[kind] += 1
            self._notices.setdefault(
                kind,
                f"terrain server {self.name}: {what}: {message}; a coarser tile (or the "
                "ellipsoid) is drawn there and the tile asked for again (counted in --stats)",
            )

    def notices(self) -> dict[str, str]:
        """Each failure kind's first failure, as a line to say once."""
        with self._lock:
            return dict(self._notices)

    @property
    def failed(self) -> int:
        return sum(self.failures.values())

    def close(self) -> None:
        self.http.close()


_NOT_TERRAIN = "answers that are not terrain tiles"
_QM_ACCEPT = "application/vnd.quantized-mesh,application/octet-stream;q=0.9,*/*;q=0.01"


def _check_mesh(data: bytes, what: str) -> bytes:
    try:
        decode(data)
    except QuantizedMeshError as exc:
        raise ImageryError(f"{what}: not a quantized-mesh tile ({exc})", "not-terrain") from None
    return data


def _decode_mesh(data: bytes) -> _Mesh:
    qm = decode(data)
    s = 1.0 / QUANTIZED_MAX
    u = qm.u.astype(np.float64) * s
    v = 1.0 - qm.v.astype(np.float64) * s  # rows from the north, as everything here
    h = qm.min_height + (qm.max_height - qm.min_height) * (qm.h.astype(np.float64) * s)
    tri = qm.triangles.astype(np.int64)
    return _Mesh(u, v, h, tri, u.nbytes * 3 + tri.nbytes)


def _decode_png(data: bytes, kind: str, url: str) -> _Raster:
    try:
        with open_image(data, url) as im:  # a bomb refused from its header
            rgba = np.asarray(im.convert("RGBA"), np.float64)
    except (OSError, ValueError) as exc:
        raise ImageryError(
            f"{url}: not an image ({type(exc).__name__}: {exc})", "not-image"
        ) from None
    side = rgba.shape[0]
    # 256 or 512 pixels (rio-rgbify, MapTiler and Mapbox's @2x write 512), or either with a
    # one-pixel border of the neighbours' (2^k + 2)
    if side == rgba.shape[1] and side >= 4 and (side - 2) & (side - 3) == 0 and side & (side - 1):
        rgba = rgba[1:-1, 1:-1]
    elif rgba.shape[0] != rgba.shape[1] or side < 2 or side & (side - 1):
        raise ImageryError(
            f"{url}: a height tile must be square with 2^k pixels a side (256, 512), or 2^k + 2 "
            f"with a one-pixel border; got {rgba.shape[1]}×{rgba.shape[0]}",
            "not-terrain",
        )
    r, g, b, a = (rgba[..., i] for i in range(4))
    if kind == "terrarium":
        h = r * 256.0 + g + b / 256.0 - 32768.0
    else:  # Mapbox Terrain-RGB
        h = -10000.0 + (r * 65536.0 + g * 256.0 + b) * 0.1
    h32 = np.where(a > 0, h, np.nan).astype(np.float32)  # alpha 0: no data there
    return _Raster(h32, h32.nbytes)


# --- heights anywhere ------------------------------------------------------------------------


class RemoteHeights:
    """A server's terrain as a height source: points sampled from the tiles of the level that
    resolves the asked spacing (bilinear between PNG pixel centres, across tile edges; linear
    on a mesh's own triangles)."""

    crs_wkt = ""

    def __init__(self, tiles: ServerTiles) -> None:
        self.tiles = tiles
        self.name = tiles.name
        w, s, e, n = tiles.bounds
        (x0, x1), (y0, y1) = lonlat_to_merc(
            [max(w, -180.0), min(e, 180.0)], [max(s, -85.05), min(n, 85.05)]
        )
        self.bounds_merc = Bbox(float(x0), float(y0), float(x1), float(y1))

    @property
    def resolution_merc(self) -> float:
        """The finest level's cell (a PNG server's: known once a tile has come)."""
        t = self.tiles
        world = 2.0 * ORIGIN / (1 << t.maxzoom)
        return world / t.cells / (2.0 if t.geographic else 1.0)

    def level_for(self, spacing: float) -> int:
        """The server level whose data resolves ``spacing`` (Web Mercator metres)."""
        t = self.tiles
        per_cell = 2.0 * ORIGIN / t.cells
        z = math.ceil(math.log2(per_cell / max(spacing, 1e-9)) - 1e-9)
        if t.geographic:
            z -= 1  # a geographic tile of level z spans 180°/2^z: Web Mercator's level z + 1
        return int(min(max(z, t.minzoom), t.maxzoom))

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        h, ok = self._at(xb.ravel(), yb.ravel(), self.level_for(spacing), cached=False)
        return h.reshape(xb.shape).astype(np.float32), ok.reshape(xb.shape)

    def sample_cached(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """Heights from the tiles already here only (the finest that has each point): what a
        frame may ask without waiting on the network."""
        x = np.asarray(xm, np.float64).ravel()
        y = np.asarray(ym, np.float64).ravel()
        h = np.full(x.shape, np.nan)
        ok = np.zeros(x.shape, bool)
        t = self.tiles
        for z in range(t.maxzoom, t.minzoom - 1, -1):
            todo = ~ok
            if not todo.any():
                break
            hz, okz = self._at(x[todo], y[todo], z, cached=True, deepest=False)
            idx = np.flatnonzero(todo)
            h[idx[okz]], ok[idx[okz]] = hz[okz], True
        return h, ok

    def sample_grid(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        xx, yy = np.meshgrid(xs, ys)
        return self.sample(xx, yy, spacing)

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        rows, cols = shape
        xs = np.linspace(bounds.left, bounds.right, cols)
        ys = np.linspace(bounds.top, bounds.bottom, rows)
        return self.sample_grid(xs, ys, (bounds.right - bounds.left) / max(cols - 1, 1))

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        b = self.bounds_merc
        x, y = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        return (x >= b.left) & (x <= b.right) & (y >= b.bottom) & (y <= b.top)

    def pixels_in(self, box: Bbox) -> Iterator[tuple[F64, F64, F64]]:
        raise SourceError(f"{self.name}: a server's terrain has no pixels to build a tileset from")

    def close(self) -> None:
        self.tiles.close()

    # -- sampling one level

    def _at(
        self, x: F64, y: F64, z: int, *, cached: bool, deepest: bool = True
    ) -> tuple[F64, NDArray[np.bool_]]:
        """Heights at level z, or where the server has no tile there (its pyramid shallower:
        over the sea, say; ``available`` or a 404 says) at the deepest level above that has
        one, as CesiumJS draws the deepest available ancestor (``deepest``; else level z
        only)."""
        h = np.full(x.shape, np.nan)
        ok = np.zeros(x.shape, bool)
        todo = np.arange(x.size)
        for level in range(z, self.tiles.minzoom - 1, -1):
            if self.tiles.kind == "quantized-mesh":
                hz, okz, tiled = self._on_meshes(x[todo], y[todo], level, cached)
            else:
                hz, okz, tiled = self._on_pixels(x[todo], y[todo], level, cached)
            h[todo[okz]], ok[todo[okz]] = hz[okz], True
            todo = todo[~tiled]
            if not todo.size or not deepest:
                break
        return h, ok

    def _get(self, z: int, tx: int, ty: int, cached: bool) -> Any:
        if cached:
            got = self.tiles.cached(z, tx, ty)
            return None if got is False else got
        return self.tiles.tile(z, tx, ty)

    def _on_pixels(
        self, x: F64, y: F64, z: int, cached: bool
    ) -> tuple[F64, NDArray[np.bool_], NDArray[np.bool_]]:
        """(heights, which have one, which points' own tile the server has) at level z."""
        tiles = 1 << z
        if self.tiles.pixels is None and not cached:
            # the server's tile size from the first tile these points fall in that it has
            tx = np.clip(np.floor((x + ORIGIN) / (2.0 * ORIGIN) * tiles), 0, tiles - 1)
            ty = np.clip(np.floor((ORIGIN - y) / (2.0 * ORIGIN) * tiles), 0, tiles - 1)
            for tid in np.unique(ty.astype(np.int64) * tiles + tx.astype(np.int64)):
                if self._get(z, int(tid % tiles), int(tid // tiles), cached) is not None:
                    break
        side = self.tiles.pixels or 256
        n = side * tiles
        gx = (x + ORIGIN) / (2.0 * ORIGIN) * n - 0.5
        gy = (ORIGIN - y) / (2.0 * ORIGIN) * n - 0.5
        x0, y0 = np.floor(gx).astype(np.int64), np.floor(gy).astype(np.int64)
        fx, fy = gx - x0, gy - y0
        px = np.stack([x0, x0 + 1, x0, x0 + 1]).clip(0, n - 1)
        py = np.stack([y0, y0, y0 + 1, y0 + 1]).clip(0, n - 1)
        vals = np.full(px.shape, np.nan)
        tile_ids = (py // side) * tiles + (px // side)
        own = np.clip(np.floor(gy + 0.5).astype(np.int64), 0, n - 1) // side * tiles
        own += np.clip(np.floor(gx + 0.5).astype(np.int64), 0, n - 1) // side
        had: set[int] = set()
        for tid in np.unique(np.concatenate([tile_ids.ravel(), own])):
            got = self._get(z, int(tid % tiles), int(tid // tiles), cached)
            if got is None:
                continue
            had.add(int(tid))
            m = tile_ids == tid
            vals[m] = got.h[py[m] % side, px[m] % side]
        w = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
        ok = np.isfinite(vals).all(axis=0)
        h = np.where(ok, (np.nan_to_num(vals) * w).sum(axis=0), np.nan)
        tiled = np.isin(own, np.fromiter(had, np.int64, len(had)))
        return h, ok, tiled

    def _on_meshes(
        self, x: F64, y: F64, z: int, cached: bool
    ) -> tuple[F64, NDArray[np.bool_], NDArray[np.bool_]]:
        """(heights, which have one, which points' tile the server has) at level z."""
        t = self.tiles
        if t.geographic:
            lon, lat = merc_to_lonlat(x, y)
            span = 180.0 / (1 << z)
            fx, fy = (lon + 180.0) / span, (90.0 - lat) / span
            nx, ny = 2 << z, 1 << z
        else:
            nx = ny = 1 << z
            fx = (x + ORIGIN) / (2.0 * ORIGIN) * nx
            fy = (ORIGIN - y) / (2.0 * ORIGIN) * ny
        tx = np.clip(np.floor(fx).astype(np.int64), 0, nx - 1)
        ty = np.clip(np.floor(fy).astype(np.int64), 0, ny - 1)
        u, v = fx - tx, fy - ty
        h = np.full(x.shape, np.nan)
        tiled = np.zeros(x.shape, bool)
        ids = ty * nx + tx
        for tid in np.unique(ids):
            got = self._get(z, int(tid % nx), int(tid // nx), cached)
            if got is None:
                continue
            m = ids == tid
            h[m] = interpolate_mesh(got, u[m], v[m])
            tiled |= m
        return h, np.isfinite(h), tiled


def interpolate_mesh(mesh: _Mesh, u: F64, v: F64, cells: int = 32) -> F64:
    """Heights of points (u, v in 0..1, rows from the north) on a mesh's own triangles (NaN
    where none holds them): points bucketed on a grid, each triangle tested against the points
    of the buckets its box covers."""
    out = np.full(u.shape, np.nan)
    if not u.size or not mesh.tri.size:
        return out
    bx = np.clip((u * cells).astype(np.int64), 0, cells - 1)
    by = np.clip((v * cells).astype(np.int64), 0, cells - 1)
    bucket = by * cells + bx
    order = np.argsort(bucket, kind="stable")
    starts = np.searchsorted(bucket[order], np.arange(cells * cells + 1))
    tri = mesh.tri
    tu, tv = mesh.u[tri], mesh.v[tri]
    eps = 1e-9
    c0 = np.clip((tu.min(1) * cells - eps).astype(np.int64), 0, cells - 1)
    c1 = np.clip((tu.max(1) * cells + eps).astype(np.int64), 0, cells - 1)
    r0 = np.clip((tv.min(1) * cells - eps).astype(np.int64), 0, cells - 1)
    r1 = np.clip((tv.max(1) * cells + eps).astype(np.int64), 0, cells - 1)
    # each triangle's buckets: the cells of its box, row by row
    nb = (c1 - c0 + 1) * (r1 - r0 + 1)
    t_of = np.repeat(np.arange(len(tri)), nb)
    k = np.arange(int(nb.sum())) - np.repeat(np.cumsum(nb) - nb, nb)
    width = (c1 - c0 + 1)[t_of]
    cell = (r0[t_of] + k // width) * cells + c0[t_of] + k % width
    # each (triangle, bucket): the bucket's points
    counts = starts[cell + 1] - starts[cell]
    t_of = np.repeat(t_of, counts)
    j = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    p = order[np.repeat(starts[cell], counts) + j]
    a, b, c = tri[t_of, 0], tri[t_of, 1], tri[t_of, 2]
    ax, ay = mesh.u[a], mesh.v[a]
    v0x, v0y = mesh.u[b] - ax, mesh.v[b] - ay
    v1x, v1y = mesh.u[c] - ax, mesh.v[c] - ay
    px, py = u[p] - ax, v[p] - ay
    den = v0x * v1y - v1x * v0y
    good = np.abs(den) > 1e-18
    den = np.where(good, den, 1.0)
    wb = (px * v1y - v1x * py) / den
    wc = (v0x * py - px * v0y) / den
    wa = 1.0 - wb - wc
    tol = -1e-7
    inside = good & (wa >= tol) & (wb >= tol) & (wc >= tol)
    hv = wa * mesh.h[a] + wb * mesh.h[b] + wc * mesh.h[c]
    out[p[inside]] = hv[inside]
    return out


# --- the tree a selection walks --------------------------------------------------------------


@dataclass(eq=False)
class RemoteTree:
    """The tile tree of a server's terrain, learnt as its tiles are meshed (see the module)."""

    zmax: int
    #: What the server's data reaches (the levels below it interpolate its finest surface).
    data_zmax: int
    exists_at: Any
    grids: tuple[int, ...] = GRIDS
    tile_size: int = 256
    zmin: int = 0
    coarsened: int = 0
    #: The colour scale of the terrain's own tint (not known from a server: stated).
    height_range: tuple[float, float] = (-100.0, 4000.0)
    twist: Any = None
    roughness: Any = None
    #: Counts what was learnt: a selection made before it changed may be stale.
    epoch: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _known: dict[int, tuple[float, float]] = field(default_factory=dict, repr=False)
    _index: tuple[NDArray[np.uint64], F64, F64] | None = field(default=None, repr=False)

    @property
    def texture_zmax(self) -> int | None:
        return self.data_zmax

    @property
    def levels(self) -> tuple[Any, ...]:
        return tuple(self.level(z) for z in range(self.zmin, self.zmax + 1))

    def deepen(self, zmax: int) -> None:
        """Carry the tree on below the data to ``zmax`` (imagery finer than the terrain)."""
        self.zmax = max(self.zmax, int(zmax))

    def level(self, z: int) -> _RemoteLevel:
        return _RemoteLevel(z, self)

    def roots(self) -> tuple[I64, I64]:
        return np.zeros(1, np.int64), np.zeros(1, np.int64)

    def learn(self, z: int, x: int, y: int, lo: float, hi: float) -> None:
        """A tile's heights are known (its mesh was made): its range, and a new epoch."""
        with self._lock:
            key = _key(z, x, y)
            if self._known.get(key) == (lo, hi):
                return
            self._known[key] = (lo, hi)
            self._index = None
            self.epoch += 1

    def ranges(self, z: int, x: I64, y: I64) -> tuple[F64, F64, NDArray[np.bool_]]:
        """Per tile: the height range it is taken to span (its own, else its nearest known
        ancestor's widened by that ancestor's error, else ``UNKNOWN_RANGE``) and whether it is
        its own."""
        with self._lock:
            if self._index is None:
                keys = np.array(sorted(self._known), np.uint64)
                lo = np.array([self._known[int(k)][0] for k in keys], np.float64)
                hi = np.array([self._known[int(k)][1] for k in keys], np.float64)
                self._index = (keys, lo, hi)
            keys, lo_k, hi_k = self._index
        lo = np.full(x.shape, UNKNOWN_RANGE[0])
        hi = np.full(x.shape, UNKNOWN_RANGE[1])
        own = np.zeros(x.shape, bool)
        if not keys.size:
            return lo, hi, own
        todo = np.ones(x.shape, bool)
        for up in range(0, z + 1):
            if not todo.any():
                break
            idx = np.flatnonzero(todo)
            k = _key_array(z - up, x[idx] >> up, y[idx] >> up)
            pos = np.minimum(np.searchsorted(keys, k), keys.size - 1)
            hit = keys[pos] == k
            if not hit.any():
                continue
            found = idx[hit]
            pad = 0.0 if up == 0 else float(level_error(z - up, self.grids[-1]))
            lo[found], hi[found] = lo_k[pos[hit]] - pad, hi_k[pos[hit]] + pad
            own[found] = up == 0
            todo[found] = False
        return lo, hi, own


@dataclass(frozen=True, eq=False)
class _RemoteLevel:
    z: int
    tree: RemoteTree

    def stats(self, x: I64, y: I64) -> TileStats:
        t = self.tree
        x = np.asarray(x, np.int64)
        y = np.asarray(y, np.int64)
        n = 1 << self.z
        inside = (x >= 0) & (x < n) & (y >= 0) & (y < n)
        exists = inside & t.exists_at(
            min(self.z, t.data_zmax),
            x >> max(self.z - t.data_zmax, 0),
            y >> max(self.z - t.data_zmax, 0),
        )
        lo, hi, own = t.ranges(self.z, x, y)
        err = np.stack([np.broadcast_to(level_error(self.z, g), x.shape) for g in t.grids])
        # a tile whose own heights have not come is not split yet (Cesium refines loaded tiles)
        leaf = ~own | (self.z >= t.zmax)
        return TileStats(exists, lo, hi, err, leaf)


def _key(z: int, x: int, y: int) -> int:
    return (z << 58) | (y << 29) | x


def _key_array(z: int, x: I64, y: I64) -> NDArray[np.uint64]:
    return (
        (np.uint64(z) << np.uint64(58))
        | (y.astype(np.uint64) << np.uint64(29))
        | x.astype(np.uint64)
    )


# --- opening --------------------------------------------------------------------------------


def is_server_spec(text: str) -> bool:
    """Whether a SOURCE names terrain on a server (without asking it: a ``layer.json`` URL or
    ``terrarium:``/``terrain-rgb:``; ``server_layer`` asks a URL that says neither)."""
    low = text.lower()
    return low.startswith(("terrarium:", "terrain-rgb:")) or (
        low.startswith(("http://", "https://")) and "layer.json" in low
    )


#: Endings of URLs that name a raster for GDAL, never a terrain layer: not asked.
_RASTER_ENDINGS = (".tif", ".tiff", ".vrt", ".img", ".jp2", ".nc", ".hgt", ".dem", ".asc", ".zip")


def server_layer(url: str, timeout: float = 10.0) -> str | None:
    """The ``layer.json`` URL of a quantized-mesh terrain server that ``url`` names, whatever
    its path: the URL itself where it answers JSON whose ``format`` is quantized-mesh, or its
    ``layer.json`` where it is the layer's folder (as CesiumJS takes it); None where it is
    neither (a raster for GDAL, or nothing answers)."""
    import httpx

    from lodscape.imagery.sources import USER_AGENT

    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or parts.path.lower().endswith(_RASTER_ENDINGS):
        return None
    candidates = [url]
    if "." not in parts.path.rstrip("/").rsplit("/", 1)[-1]:  # a folder's name, not a file's
        candidates.append(parts._replace(path=parts.path.rstrip("/") + "/layer.json").geturl())
    for candidate in candidates:
        try:
            with httpx.stream(
                "GET",
                candidate,
                timeout=timeout,
                headers={"User-Agent": USER_AGENT},
                follow_redirects=True,
            ) as r:
                if r.status_code != 200:
                    continue
                head = b""
                for chunk in r.iter_bytes():
                    head += chunk
                    # a raster's bytes (or a page) end the reading at once
                    if head.lstrip()[:1] not in (b"", b"{") or len(head) > 1 << 20:
                        break
        except httpx.HTTPError:
            continue
        if head.lstrip()[:1] != b"{":
            continue
        try:
            layer = json.loads(head)
        except ValueError:
            continue
        if isinstance(layer, dict) and str(layer.get("format", "")).startswith("quantized-mesh"):
            return candidate
    return None


def open_server(
    spec: str, *, cache_dir: Any = None, timeout: float = 10.0
) -> tuple[RemoteHeights, RemoteTree]:
    """The heights and tree of ``spec``: a ``layer.json`` URL, or ``terrarium:[MAXZOOM:]URL`` /
    ``terrain-rgb:[MAXZOOM:]URL`` with {z}, {x}, {y} (default maxzoom 15)."""
    from pathlib import Path

    cache = None if cache_dir is None else TileCache(Path(cache_dir) / "terrain-cache.sqlite")
    try:
        if spec.lower().startswith(("terrarium:", "terrain-rgb:")):
            kind, _, rest = spec.partition(":")
            kind = kind.lower()
            maxzoom = 15
            head, sep, tail = rest.partition(":")
            if sep and head.isdigit():
                maxzoom, rest = int(head), tail
            if not rest.lower().startswith(("http://", "https://")):
                raise SourceError(
                    f"{spec}: expected {kind}:[MAXZOOM:]http(s)://…/{{z}}/{{x}}/{{y}}.png"
                )
            if not 0 <= maxzoom <= 22:
                raise SourceError(f"{spec}: maxzoom must be 0..22, got {maxzoom}")
            tiles = ServerTiles(spec, rest, kind, maxzoom=maxzoom, cache=cache, timeout=timeout)
        else:
            tiles = _from_layer(spec, cache, timeout)
    except ImageryError as exc:
        if cache is not None:
            cache.close()
        raise SourceError(str(exc)) from None
    except BaseException:
        if cache is not None:
            cache.close()
        raise
    heights = RemoteHeights(tiles)
    zmax = tiles.maxzoom + (1 if tiles.geographic else 0)
    if tiles.kind != "quantized-mesh":
        zmax = tiles.maxzoom
    # Web Mercator tiles below the finest a PNG server's 256 pixels or a mesh's 64 cells map to
    exists = _exists_fn(tiles)
    tree = RemoteTree(zmax=zmax, data_zmax=zmax, exists_at=exists)
    return heights, tree


def _exists_fn(tiles: ServerTiles) -> Any:
    """Which Web Mercator tiles of a level to draw: those over the server's bounds (and, for a
    Web Mercator quantized-mesh layer, the tiles its ``available`` lists)."""
    w, s, e, n = tiles.bounds
    (bx0, bx1), (by0, by1) = lonlat_to_merc([w, e], [max(s, -85.06), min(n, 85.06)])

    def exists(z: int, x: I64, y: I64) -> NDArray[np.bool_]:
        size = 2.0 * ORIGIN / (1 << z)
        left = -ORIGIN + x * size
        top = ORIGIN - y * size
        over = (left < bx1) & (left + size > bx0) & (top > by0) & (top - size < by1)
        if tiles.kind == "quantized-mesh" and not tiles.geographic and tiles.available is not None:
            over &= tiles.has(z, x, y)
        out: NDArray[np.bool_] = over
        return out

    return exists


#: The deepest level a server's layer.json may claim (level 22: a few centimetres).
_MAX_SERVER_ZOOM = 22


def _from_layer(url: str, cache: TileCache | None, timeout: float) -> ServerTiles:
    import httpx

    from lodscape.imagery.sources import USER_AGENT

    try:
        r = httpx.get(
            url, timeout=timeout, headers={"User-Agent": USER_AGENT}, follow_redirects=True
        )
    except httpx.HTTPError as exc:
        raise SourceError(f"{url}: cannot fetch the layer ({exc})") from None
    if r.status_code != 200:
        raise SourceError(f"{url}: HTTP {r.status_code} for the layer")
    try:
        layer = json.loads(r.content)
        if not isinstance(layer, dict):
            raise ValueError("not a JSON object")
        fmt = str(layer.get("format", "quantized-mesh-1.0"))
        if not fmt.startswith("quantized-mesh"):
            raise ValueError(f"format {fmt!r} is not quantized-mesh")
        templates = layer.get("tiles")
        if not isinstance(templates, list) or not templates or not isinstance(templates[0], str):
            raise ValueError("no tiles template")
        version = str(layer.get("version", "1.0.0"))
        template = urljoin(url, templates[0].replace("{version}", version))
        query = urlsplit(url).query
        if query and not urlsplit(template).query:
            template += "?" + query  # an access token on the layer goes with its tiles
        projection = str(layer.get("projection", "EPSG:4326")).upper()
        if projection not in ("EPSG:4326", "EPSG:3857"):
            raise ValueError(f"projection {projection} (EPSG:4326 or EPSG:3857)")
        scheme = str(layer.get("scheme", "tms")).lower()
        if scheme not in ("tms", "slippymap", "xyz"):
            raise ValueError(f"scheme {scheme!r}")
        minzoom = int(layer.get("minzoom", 0))
        avail_raw = layer.get("available")
        available = None
        if isinstance(avail_raw, list):
            available = [
                [(int(r["startX"]), int(r["startY"]), int(r["endX"]), int(r["endY"])) for r in lv]
                for lv in avail_raw
            ]
        maxzoom = int(layer.get("maxzoom", len(available) - 1 if available else 15))
        if not 0 <= minzoom <= maxzoom <= _MAX_SERVER_ZOOM:
            raise ValueError(
                f"minzoom {minzoom} and maxzoom {maxzoom} must be 0 <= minzoom <= maxzoom <= "
                f"{_MAX_SERVER_ZOOM}"
            )
        bounds = tuple(float(b) for b in layer.get("bounds", (-180.0, -90.0, 180.0, 90.0)))
        if len(bounds) != 4 or not all(math.isfinite(b) for b in bounds):
            raise ValueError("bounds must be four numbers")
        w, s, e, n = bounds
        if not (-180.0 <= w < e <= 180.0 and -90.0 <= s < n <= 90.0):
            raise ValueError(
                f"bounds {list(bounds)} are not west < east in -180..180 and south < north in "
                "-90..90"
            )
    except (ValueError, KeyError, TypeError) as exc:
        raise SourceError(f"{url}: not a quantized-mesh layer.json ({exc})") from None
    return ServerTiles(
        url,
        template,
        "quantized-mesh",
        geographic=projection == "EPSG:4326",
        tms=scheme == "tms",
        minzoom=minzoom,
        maxzoom=maxzoom,
        bounds=bounds,  # type: ignore[arg-type]
        available=available,
        cache=cache,
        timeout=timeout,
    )


class RemoteProvider(RasterProvider):
    """A server's terrain as a Scene's provider: ``RasterProvider``'s grids over
    ``RemoteHeights``, each mesh made teaching the tree its tile's height range. Every key
    touches the network (``network``): the streamer runs them on its network threads."""

    network = True

    def __init__(self, heights: RemoteHeights, tree: RemoteTree) -> None:
        super().__init__(heights, tree, sea_level=None)  # type: ignore[arg-type]
        self.heights = heights
        self.remote_tree = tree

    def notices(self) -> dict[str, str]:
        """The terrain server's failures, a line per kind (``ServerTiles.notices``)."""
        return self.heights.tiles.notices()

    def server_figures(self) -> dict[str, int]:
        """The terrain server's failed tiles and its HTTP requests and retries so far."""
        tiles = self.heights.tiles
        return {
            "terrain_failed": tiles.failed,
            "http_requests": tiles.http.requests,
            "http_retries": tiles.http.retried,
        }

    def ground_height(self, lon: float, lat: float) -> float | None:
        """The height under a point from the tiles already here; None before any has come
        (a frame never waits on the network for it)."""
        xm, ym = lonlat_to_merc([lon], [lat])
        h, ok = self.heights.sample_cached(xm, ym)
        return float(h[0]) if bool(ok[0]) else None

    def heights_at(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        xm, ym = lonlat_to_merc(lon, lat)
        h, ok = self.heights.sample_cached(xm, ym)
        return np.where(ok, h, np.nan).reshape(np.shape(lon))

    def fetch(self, key: int) -> bytes:
        t = tile_of(key)
        if is_texture(key):
            return super().fetch(key)
        segments = self.tree.grids[grid_of(key)]
        xs, ys = grid_coordinates(t.z, t.x, t.y, segments)
        xx, yy = np.meshgrid(xs, ys)
        h, ok = self.heights.sample(xx, yy, float(tile_size(t.z)) / segments)
        if ok.any():
            lo, hi = float(h[ok].min()), float(h[ok].max())
            # under the holes (cut by the texture's alpha) the mesh lies at the lowest height
            h = np.where(ok, h, lo)
        else:
            lo = hi = 0.0
            h = np.zeros_like(h)
        self.remote_tree.learn(t.z, t.x, t.y, lo, hi)
        return h.astype(np.float32).tobytes()
