"""The tile tree of a height source: which tiles exist, their height range and geometric error.

One bottom-up pass, a whole level per numpy call. Level z is sampled on a grid of 16 segments per
tile; the deepest level sampled is the data's own resolution (its 16-segment grid is as fine as the
256-texel texture of the finest tile level), taken as the truth with zero error. A coarser tile's
error is *measured*, not summed: the triangles of every finer level nest in its own (each cell
split along the same diagonal), so its surface and a finer level's differ most at one of the
finer level's vertices, and the largest difference over them is the exact deviation. A tile of
the ``REFERENCE_LEVELS`` levels above the truth is measured against the truth itself; one
higher up against the level ``REFERENCE_LEVELS`` above the truth, plus that level's own error
there (one triangle inequality, where summing level by level adds one per level: ×1.4-2.3 the
measured error on the coarse levels of an fBm DEM). Errors are saturated: a tile's is at least
its children's. A tile drawn with 16·2^k segments uses exactly the vertices of its level z+k
descendants, so its error is their largest 16-segment error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from lodscape.errors import SourceError
from lodscape.geo.frames import WGS84_A
from lodscape.geo.tiles import MAX_ZOOM, ORIGIN, Bbox, merc_to_lonlat, tiles_array
from lodscape.terrain.mesh import GRIDS

__all__ = [
    "DeeperTree",
    "Level",
    "RefinedTree",
    "SampleSource",
    "TileStats",
    "TileTree",
    "build_tree",
    "level_range",
]

_BASE = GRIDS[0]
#: Samples of the deepest level above which on-the-fly rendering coarsens the data (a build keeps
#: full detail); 2^26 float32 heights are 256 MiB.
MAX_SAMPLES = 1 << 26
#: Points sampled per call while building (about 40 bytes each in temporaries).
_STRIP_POINTS = 1 << 22
#: Tiles a side of the truth level's blocks: 32 (263,000 samples held at a time) builds a
#: 16385² DEM's tree as fast as 64 with 160 MB less at the peak.
BLOCK_TILES = 32
#: Levels above the truth measured against the truth itself (the module's docstring); a block
#: holds them all, so blocks are at least 2^REFERENCE_LEVELS tiles a side.
REFERENCE_LEVELS = 5


class SampleSource(Protocol):
    name: str
    bounds_merc: Bbox
    resolution_merc: float

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...

    def sample_grid(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...


@dataclass(frozen=True, eq=False)
class TileStats:
    """What the selection needs of N tiles of one level (zero where a tile does not exist)."""

    exists: NDArray[np.bool_]
    min_h: NDArray[np.floating]
    max_h: NDArray[np.floating]
    #: (len(grids), N) metres of geometric error of each grid.
    error: NDArray[np.floating]
    #: Tiles with no children (a tileset refined only where its finest level missed its
    #: budget); None: every tile above the finest level has them.
    leaf: NDArray[np.bool_] | None = None

    def take(self, m: NDArray[np.bool_]) -> TileStats:
        leaf = None if self.leaf is None else self.leaf[m]
        return TileStats(self.exists[m], self.min_h[m], self.max_h[m], self.error[:, m], leaf)


@dataclass(frozen=True, eq=False)
class Level:
    """Per-tile statistics of one level over the tile range x0.., y0.. (arrays indexed [y, x])."""

    z: int
    x0: int
    y0: int
    exists: NDArray[np.bool_]
    min_h: NDArray[np.float32]
    max_h: NDArray[np.float32]
    #: (len(grids), ny, nx): metres of vertical error of the tile meshed with grids[k] segments.
    error: NDArray[np.float32]
    #: (ny, nx) tiles without children (see ``TileStats.leaf``); None: none.
    leaf: NDArray[np.bool_] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        ny, nx = self.exists.shape
        return ny, nx

    def index(
        self, x: NDArray[np.int64], y: NDArray[np.int64]
    ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
        """(tile exists, flat index into the level's arrays; 0 where it does not)."""
        ny, nx = self.shape
        cx, cy = x - self.x0, y - self.y0
        inside = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
        flat = np.where(inside, cy * nx + cx, 0)
        return inside & self.exists.ravel()[flat], flat

    def stats(self, x: NDArray[np.int64], y: NDArray[np.int64]) -> TileStats:
        """The selection's view of tiles (x, y) of this level."""
        ok, flat = self.index(x, y)
        _ny, nx = self.shape
        return TileStats(
            ok,
            self.min_h.ravel()[flat],
            self.max_h.ravel()[flat],
            self.error[:, flat // nx, flat % nx],
            None if self.leaf is None else self.leaf.ravel()[flat],
        )


@dataclass(frozen=True, eq=False)
class TileTree:
    """The quadtree a selection walks: levels zmin..zmax, each with per-tile statistics.

    Textures exist down to ``texture_zmax``, where a texel is as fine as the data; the levels below
    it carry geometry only (their meshes reach the data's own resolution with coarse grids).
    """

    levels: tuple[Level, ...]
    grids: tuple[int, ...]
    tile_size: int
    height_range: tuple[float, float]
    #: Levels the data's resolution was coarsened by to fit MAX_SAMPLES (0: full detail).
    coarsened: int = 0
    #: The finest level that has its own texture (None: every level).
    texture_zmax: int | None = None
    #: Per tile of the finest level: the largest twist |a + d - b - c| of the data's lattice
    #: cells under it (bounds how far another diagonal moves the surface); None if unknown.
    twist: NDArray[np.float32] | None = None
    #: RMS height difference between neighbouring points of the data's lattice, metres.
    roughness: float | None = None
    #: The finest level's finest grid samples the truth its errors are measured against: the
    #: grid twice as fine one level up is the truth's (``terrain.tin_tiles.ErrorLadder``).
    finest_is_truth: ClassVar[bool] = True

    @property
    def zmin(self) -> int:
        return self.levels[0].z

    @property
    def zmax(self) -> int:
        return self.levels[-1].z

    def level(self, z: int) -> Level:
        return self.levels[z - self.zmin]

    def roots(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        lv = self.levels[0]
        y, x = np.nonzero(lv.exists)
        return (x + lv.x0).astype(np.int64), (y + lv.y0).astype(np.int64)


def level_range(bounds: Bbox, z: int) -> tuple[int, int, int, int]:
    """(x0, y0, nx, ny): the tiles of level z that the box touches."""
    x0, y0 = tiles_array(bounds.left, bounds.top, z)
    # a box edge exactly on a tile edge does not pull in the next tile
    eps = 1e-6 * (2.0 * ORIGIN / (1 << z))
    x1, y1 = tiles_array(bounds.right - eps, bounds.bottom + eps, z)
    return int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1)


def _level_grid(
    source: SampleSource, z: int, rng: tuple[int, int, int, int]
) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    x0, y0, nx, ny = rng
    step = 2.0 * ORIGIN / float(1 << z) / _BASE
    # the same exact-power-of-two vertex coordinates as terrain.mesh.grid_coordinates
    xs = -ORIGIN + (x0 * _BASE + np.arange(nx * _BASE + 1)).astype(np.float64) * step
    ys = ORIGIN - (y0 * _BASE + np.arange(ny * _BASE + 1)).astype(np.float64) * step
    h = np.empty((ys.size, xs.size), dtype=np.float32)
    valid = np.empty((ys.size, xs.size), dtype=bool)
    # strips of rows bound the float64 temporaries of sampling, whatever the data's size
    rows = max(1, _STRIP_POINTS // xs.size)
    for r in range(0, ys.size, rows):
        h[r : r + rows], valid[r : r + rows] = source.sample_grid(xs, ys[r : r + rows], step)
    return h, valid


def _blocks(a: NDArray[np.generic]) -> NDArray[np.generic]:
    """(ny, nx, 17, 17) views of each tile's vertices (edges shared with the neighbours)."""
    return sliding_window_view(a, (_BASE + 1, _BASE + 1))[::_BASE, ::_BASE]


def _upsample(h: NDArray[np.float32]) -> NDArray[np.float32]:
    """The parent's triangulated surface evaluated on the child grid (twice as fine)."""
    m, n = h.shape
    out = np.empty((2 * m - 1, 2 * n - 1), dtype=np.float32)
    out[::2, ::2] = h
    out[::2, 1::2] = (h[:, :-1] + h[:, 1:]) / 2
    out[1::2, ::2] = (h[:-1, :] + h[1:, :]) / 2
    # cell centres lie on the north-west to south-east diagonal
    out[1::2, 1::2] = (h[:-1, :-1] + h[1:, 1:]) / 2
    return out


def _pool(
    child: NDArray[np.floating],
    off: tuple[int, int],
    shape: tuple[int, int],
    fill: float,
    op: str,
    factor: int = 2,
) -> NDArray[np.float32]:
    """Reduce a finer level's per-tile array onto its ancestors (``factor``² blocks: 2, the
    level below), missing = fill."""
    ny, nx = shape
    f = factor
    full = np.full((f * ny, f * nx), fill, dtype=np.float32)
    oy, ox = off
    full[oy : oy + child.shape[0], ox : ox + child.shape[1]] = child
    blocks = full.reshape(ny, f, nx, f)
    return getattr(blocks, op)(axis=(1, 3)).astype(np.float32)  # type: ignore[no-any-return]


@dataclass(frozen=True, eq=False)
class _Reference:
    """A finer level's grid over a range of its tiles, which coarser tiles are measured
    against, with its tiles' existence and 16-segment errors."""

    z: int
    heights: NDArray[np.float32]
    rng: tuple[int, int, int, int]
    exists: NDArray[np.bool_]
    error: NDArray[np.float32]
    #: Where the grid's points hold data (the truth's: what the picture shows of it); None:
    #: every point of a tile that exists (a coarser reference's vertices off the data still
    #: shape its surface over the data next to them).
    valid: NDArray[np.bool_] | None = None


def deviation(
    h: NDArray[np.float32],
    rng: tuple[int, int, int, int],
    fine: NDArray[np.float32],
    fine_rng: tuple[int, int, int, int],
    levels: int,
    valid: NDArray[np.bool_] | None = None,
) -> NDArray[np.float32]:
    """Per tile of the finer grid ``fine`` (tiles ``fine_rng``, ``levels`` below): the largest
    difference between its surface and the coarser grid ``h``'s (tiles ``rng``), exact (every
    finer vertex is compared, or those ``valid`` marks; the coarser triangles hold the finer
    ones)."""
    up = h
    for _ in range(levels):
        up = _upsample(up)
    ox, oy = fine_rng[0] - (rng[0] << levels), fine_rng[1] - (rng[1] << levels)
    sub = up[oy * _BASE : oy * _BASE + fine.shape[0], ox * _BASE : ox * _BASE + fine.shape[1]]
    diff = np.abs(sub - fine)
    if valid is not None:
        diff = np.where(valid, diff, np.float32(0.0))
    out: NDArray[np.float32] = _blocks(diff).max(axis=(2, 3)).astype(np.float32)
    return out


def measured_error(
    h: NDArray[np.float32],
    rng: tuple[int, int, int, int],
    ref: _Reference,
    z: int,
) -> NDArray[np.float32]:
    """Per tile of level z over ``rng`` (grid ``h``): its largest difference from the
    reference level's surface plus the reference's own error there, over the reference's
    tiles that exist."""
    k = ref.z - z
    dev = deviation(h, rng, ref.heights, ref.rng, k, ref.valid)
    total = np.where(ref.exists, dev + ref.error, np.float32(0.0))
    off = (ref.rng[1] - (rng[1] << k), ref.rng[0] - (rng[0] << k))
    return _pool(total, off, (rng[3], rng[2]), 0.0, "max", 1 << k)


@dataclass(frozen=True)
class LevelSpan:
    """Which levels a tile tree over some data has."""

    #: The roots: the finest level at which the data spans at most 2×2 tiles.
    zmin: int
    #: The finest texture level: its texels as fine as the data.
    texture_zmax: int
    #: The finest level: its finest grid samples every texel of ``texture_zmax``.
    zmax: int
    #: Levels the data's resolution was coarsened by to fit ``max_samples`` (0: full detail).
    coarsened: int = 0


def level_span(
    bounds: Bbox,
    resolution: float,
    *,
    tile_size: int = 256,
    grids: tuple[int, ...] = GRIDS,
    max_samples: int | None = MAX_SAMPLES,
) -> LevelSpan:
    """The levels of the tree over data of ``bounds`` and ``resolution`` (EPSG:3857 metres)."""
    if grids[0] != _BASE or any(g != _BASE << k for k, g in enumerate(grids)):
        raise ValueError(f"Expected grids {_BASE}·2^k, got {grids}")
    texel_levels = round(math.log2(tile_size / _BASE)) if tile_size >= _BASE else -1
    if texel_levels < 0 or _BASE << texel_levels != tile_size:
        raise ValueError(f"Expected a tile size of {_BASE}·2^k texels, got {tile_size}")
    depth = len(grids) - 1
    if depth > texel_levels:
        raise ValueError(f"Expected grids no finer than the {tile_size} texels of a tile")
    zmax = math.ceil(math.log2(2.0 * ORIGIN / (tile_size * resolution)))
    zmax = min(max(zmax, 0), MAX_ZOOM - texel_levels)
    coarsened = 0
    while max_samples is not None and zmax > 0:
        _, _, nx, ny = level_range(bounds, zmax + texel_levels)
        if (nx * _BASE + 1) * (ny * _BASE + 1) <= max_samples:
            break
        zmax -= 1
        coarsened += 1
    zmin = zmax
    while zmin > 0 and max(level_range(bounds, zmin)[2:]) > 2:
        zmin -= 1
    return LevelSpan(zmin, zmax, zmax + texel_levels - depth, coarsened)


def build_tree(
    source: SampleSource,
    *,
    tile_size: int = 256,
    grids: tuple[int, ...] = GRIDS,
    block_tiles: int = BLOCK_TILES,
    reference_levels: int = REFERENCE_LEVELS,
) -> TileTree:
    """Walk the source once, bottom-up, and return its tile tree.

    The finest levels are walked in aligned blocks of ``block_tiles``² tiles of the truth
    level (every parent's children lie in its block), each block from the truth up to the
    level where it is one tile; the levels above, a few tiles each, are walked whole. So the
    samples held at once are bounded by the block, not by the data's size.

    Tiles of the ``reference_levels`` levels above the truth are measured against it, those
    higher up against the level ``reference_levels`` above it (the module's docstring); blocks
    hold those levels, so they are at least 2^reference_levels tiles a side unless one block
    holds the whole tree."""
    span = level_span(source.bounds_merc, source.resolution_merc, tile_size=tile_size, grids=grids)
    bounds = source.bounds_merc
    zmin, zmax, coarsened = span.zmin, span.texture_zmax, span.coarsened
    texel_levels = round(math.log2(tile_size / _BASE))
    depth = len(grids) - 1
    if block_tiles < 1 or block_tiles & (block_tiles - 1):
        raise ValueError(f"Expected a power of two of block tiles, got {block_tiles}")
    # a fill that stands in where there is no data (a level, the ellipsoid, the nearest height)
    # makes every tile over the data's box one to draw; without, a tile exists where data does
    stands_in = getattr(getattr(source, "fill", None), "kind", "none") != "none"
    # the truth: the level whose 16-segment grid samples the finest texture level's texels;
    # meshes reach it through levels below zmax that carry geometry only
    truth = zmax + texel_levels
    zgeo = truth - depth
    # the level the levels above it are measured against (the truth below it)
    second = truth - reference_levels
    # the block levels: truth .. top, each block one tile at ``top``
    top = max(truth - round(math.log2(block_tiles)), zmin)
    if top > max(second, zmin):
        raise ValueError(
            f"Expected a power of two of at least {1 << reference_levels} block tiles "
            f"(the levels measured against the truth), got {block_tiles}"
        )
    ranges = {z: level_range(bounds, z) for z in range(zmin, truth + 1)}
    acc = {z: _LevelAcc(ranges[z]) for z in range(top, truth + 1)}
    twist_z = max(zgeo, top)
    twist = np.zeros(ranges[twist_z][3:1:-1], np.float32)
    lo, hi, sq, count = math.inf, -math.inf, 0.0, 0
    tx0, ty0, tnx, tny = ranges[truth]
    b = 1 << (truth - top)
    for by in range(ty0 // b, (ty0 + tny - 1) // b + 1):
        for bx in range(tx0 // b, (tx0 + tnx - 1) // b + 1):
            child: tuple[tuple[int, int, int, int], Level] | None = None
            block_twist = np.zeros((0, 0), np.float32)
            refs: dict[int, _Reference] = {}
            for z in range(truth, top - 1, -1):
                k = truth - z
                rng = _clip(ranges[z], (bx * b) >> k, (by * b) >> k, max(b >> k, 1))
                if rng is None:
                    break
                h, valid = _level_grid(source, z, rng)
                if child is None:
                    if valid.any():
                        hv = h[valid]
                        lo, hi = min(lo, float(hv.min())), max(hi, float(hv.max()))
                    east = rng[0] + rng[2] == tx0 + tnx
                    south = rng[1] + rng[3] == ty0 + tny
                    block_twist, s2, n2 = _twist(h, valid, rng[3], rng[2], east, south)
                    sq, count = sq + s2, count + n2
                ref = refs.get(truth if z >= second else second)
                lv, e16, twisted = _step(
                    z, h, valid, rng, child, stands_in, block_twist, z >= zgeo, ref
                )
                block_twist = twisted
                acc[z].put(lv, e16)
                if z in (truth, second):
                    refs[z] = _Reference(z, h, rng, lv.exists, e16, valid if z == truth else None)
                if z == twist_z:
                    ox, oy = rng[0] - ranges[z][0], rng[1] - ranges[z][1]
                    twist[oy : oy + rng[3], ox : ox + rng[2]] = block_twist
                child = (rng, lv)
    if lo > hi:
        raise SourceError(f"{source.name}: no valid heights inside the data's footprint")
    height_range = (lo, hi)
    roughness = math.sqrt(sq / count) if count else 0.0
    levels: dict[int, tuple[Level, NDArray[np.float32], tuple[int, int, int, int]]] = {
        z: (a.level(z), a.e16, ranges[z]) for z, a in acc.items()
    }
    # the levels above the blocks: whole, their child the top block level, all measured
    # against ``second`` (at or below ``top``), sampled whole
    if top > zmin:
        child = (ranges[top], levels[top][0])
        second_grid = _level_grid(source, second, ranges[second])[0]
        whole = _Reference(
            second, second_grid, ranges[second], levels[second][0].exists, levels[second][1]
        )
        for z in range(top - 1, zmin - 1, -1):
            rng = ranges[z]
            h, valid = _level_grid(source, z, rng)
            lv, e16, twisted = _step(z, h, valid, rng, child, stands_in, twist, z >= zgeo, whole)
            if z >= zgeo:
                twist = twisted
            levels[z] = (lv, e16, rng)
            child = (rng, lv)

    out = []
    for z in range(zmin, zgeo + 1):
        lv, _, rng = levels[z]
        x0, y0, nx, ny = rng
        errs = []
        for k in range(depth + 1):
            _, ek, (kx0, ky0, _, _) = levels[z + k]
            f = 1 << k
            full = np.zeros((ny * f, nx * f), dtype=np.float32)
            oy, ox = ky0 - y0 * f, kx0 - x0 * f
            full[oy : oy + ek.shape[0], ox : ox + ek.shape[1]] = ek
            err = full.reshape(ny, f, nx, f).max(axis=(1, 3))
            errs.append(err + _sag(z, grids[k], y0, ny))
        out.append(Level(z, x0, y0, lv.exists, lv.min_h, lv.max_h, np.stack(errs)))
    return TileTree(tuple(out), grids, tile_size, height_range, coarsened, zmax, twist, roughness)


class _LevelAcc:
    """A level's per-tile statistics, filled block by block."""

    def __init__(self, rng: tuple[int, int, int, int]) -> None:
        self.rng = rng
        _, _, nx, ny = rng
        self.exists = np.zeros((ny, nx), bool)
        self.min_h = np.zeros((ny, nx), np.float32)
        self.max_h = np.zeros((ny, nx), np.float32)
        self.e16 = np.zeros((ny, nx), np.float32)

    def put(self, lv: Level, e16: NDArray[np.float32]) -> None:
        ox, oy = lv.x0 - self.rng[0], lv.y0 - self.rng[1]
        ny, nx = lv.shape
        sl = (slice(oy, oy + ny), slice(ox, ox + nx))
        self.exists[sl], self.min_h[sl], self.max_h[sl] = lv.exists, lv.min_h, lv.max_h
        self.e16[sl] = e16

    def level(self, z: int) -> Level:
        x0, y0, _, _ = self.rng
        return Level(z, x0, y0, self.exists, self.min_h, self.max_h, self.e16[None])


def _clip(
    rng: tuple[int, int, int, int], x0: int, y0: int, n: int
) -> tuple[int, int, int, int] | None:
    """The tiles of ``rng`` within the n×n tiles from (x0, y0); None if none."""
    ax0, ay0 = max(rng[0], x0), max(rng[1], y0)
    ax1, ay1 = min(rng[0] + rng[2], x0 + n), min(rng[1] + rng[3], y0 + n)
    if ax1 <= ax0 or ay1 <= ay0:
        return None
    return ax0, ay0, ax1 - ax0, ay1 - ay0


def _step(
    z: int,
    h: NDArray[np.float32],
    valid: NDArray[np.bool_],
    rng: tuple[int, int, int, int],
    child: tuple[tuple[int, int, int, int], Level] | None,
    stands_in: bool,
    twist: NDArray[np.float32],
    pool_twist: bool,
    ref: _Reference | None = None,
) -> tuple[Level, NDArray[np.float32], NDArray[np.float32]]:
    """One level's statistics over ``rng`` from its sampled grid and its child level's (the
    level below, over the children of ``rng``): (level, 16-segment errors measured against
    ``ref`` and saturated by the children's, the twist pooled onto it when ``pool_twist``)."""
    x0, y0, nx, ny = rng
    mn = _blocks(h).min(axis=(2, 3)).astype(np.float32)
    mx = _blocks(h).max(axis=(2, 3)).astype(np.float32)
    if stands_in:
        exists = np.ones((ny, nx), dtype=bool)
    else:
        exists = np.asarray(_blocks(valid).any(axis=(2, 3)), dtype=bool)
    e16 = np.zeros((ny, nx), dtype=np.float32)
    if child is not None:
        crng, clv = child
        cx0, cy0 = crng[0], crng[1]
        ox, oy = cx0 - 2 * x0, cy0 - 2 * y0
        # saturated: no tile's error under its children's
        e16 = _pool(np.where(clv.exists, clv.error[0], 0.0), (oy, ox), (ny, nx), 0.0, "max")
        if ref is not None:
            e16 = np.maximum(e16, measured_error(h, rng, ref, z))
        mn = np.minimum(mn, _pool(clv.min_h, (oy, ox), (ny, nx), np.inf, "min"))
        mx = np.maximum(mx, _pool(clv.max_h, (oy, ox), (ny, nx), -np.inf, "max"))
        exists |= _pool(clv.exists.astype(np.float32), (oy, ox), (ny, nx), 0.0, "max") > 0
        if pool_twist:
            twist = _pool(twist, (oy, ox), (ny, nx), 0.0, "max")
    return Level(z, x0, y0, exists, mn, mx, e16[None]), e16, twist


def _twist(
    h: NDArray[np.float32],
    valid: NDArray[np.bool_],
    ny: int,
    nx: int,
    east: bool = True,
    south: bool = True,
) -> tuple[NDArray[np.float32], float, int]:
    """Per tile (16-segment blocks) the largest cell twist; and the sum of squared one-step
    differences with their count (the data's RMS roughness, summed over blocks: a block that
    is not the ``east``-most or ``south``-most leaves its last column or row, which the next
    block shares, to that block)."""
    hh = h.astype(np.float64)
    ok = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    t = np.where(ok, np.abs(hh[:-1, :-1] + hh[1:, 1:] - hh[:-1, 1:] - hh[1:, :-1]), 0.0)
    per_tile = t.reshape(ny, _BASE, nx, _BASE).max(axis=(1, 3)).astype(np.float32)
    rows = slice(None) if south else slice(None, -1)
    cols = slice(None) if east else slice(None, -1)
    hx, vx = hh[rows], valid[rows]
    hy, vy = hh[:, cols], valid[:, cols]
    dx = (hx[:, 1:] - hx[:, :-1])[vx[:, 1:] & vx[:, :-1]]
    dy = (hy[1:, :] - hy[:-1, :])[vy[1:, :] & vy[:-1, :]]
    return per_tile, float((dx * dx).sum()) + float((dy * dy).sum()), int(dx.size + dy.size)


def _sag(z: int, segments: int, y0: int, ny: int) -> NDArray[np.float32]:
    """``sag`` of tile rows y0 .. y0 + ny, as a column."""
    return sag(z, segments, np.arange(ny) + y0).astype(np.float32)[:, None]


def sag(z: int, segments: int, y: NDArray[np.int64]) -> NDArray[np.float64]:
    """How far straight mesh edges sag below the curved Earth, spacing²/(8R), for tiles of rows
    ``y`` of level z drawn with ``segments`` segments."""
    step = 2.0 * ORIGIN / float(1 << z) / segments
    ym = ORIGIN - (np.asarray(y, np.float64) + 0.5) * (2.0 * ORIGIN / float(1 << z))
    _, lat = merc_to_lonlat(0.0, ym)
    ground = step * np.cos(np.radians(lat)) * math.sqrt(2.0)
    out: NDArray[np.float64] = ground**2 / (8.0 * WGS84_A)
    return out


@dataclass(frozen=True, eq=False)
class _RefinedLevel:
    """A level below a tree's finest: each tile's bounds are its ancestor's at the finest level;
    its meshes sample the finest stored surface, so their error against it is the straight
    edges' sag alone (what the data says below its finest level is not known, and not
    invented)."""

    z: int
    base: Any

    def stats(self, x: NDArray[np.int64], y: NDArray[np.int64]) -> TileStats:
        """A stored tile's own statistics where level z has it; elsewhere those of its nearest
        stored ancestor (a build refines its finest levels only where they missed their
        budget, so that ancestor can be above the finest level), with the sag's error."""
        base = self.base
        errs = np.stack([sag(self.z, g, y).astype(np.float32) for g in base.grids])
        exists = np.zeros(x.shape, dtype=bool)
        min_h = np.zeros(x.shape, dtype=np.float32)
        max_h = np.zeros(x.shape, dtype=np.float32)
        for zb in range(min(self.z, base.zmax), base.zmin - 1, -1):
            todo = ~exists
            if not todo.any():
                break
            k = self.z - zb
            st = base.level(zb).stats(x[todo] >> k, y[todo] >> k)
            got = np.flatnonzero(todo)[st.exists]
            exists[got] = True
            min_h[got] = st.min_h[st.exists]
            max_h[got] = st.max_h[st.exists]
            if zb == self.z:
                errs[:, got] = st.error[:, st.exists]
        return TileStats(exists, min_h, max_h, errs)


class DeeperTree:
    """What a tile tree carried on below another's (``base``) finest level shares: the base's
    grids, tile size, roots and heights, and its levels made once each by ``_make_level``.
    Subclasses give ``zmax``, ``texture_zmax`` and ``_make_level``."""

    base: Any
    _levels: dict[int, Any]
    zmax: int

    @property
    def grids(self) -> tuple[int, ...]:
        return tuple(self.base.grids)

    @property
    def tile_size(self) -> int:
        return int(self.base.tile_size)

    @property
    def zmin(self) -> int:
        return int(self.base.zmin)

    @property
    def height_range(self) -> tuple[float, float]:
        lo, hi = self.base.height_range
        return (float(lo), float(hi))

    @property
    def coarsened(self) -> int:
        return int(self.base.coarsened)

    @property
    def levels(self) -> tuple[Any, ...]:
        return tuple(self.level(z) for z in range(self.zmin, self.zmax + 1))

    def level(self, z: int) -> Any:
        lv = self._levels.get(z)
        if lv is None:
            lv = self._levels[z] = self._make_level(z)
        return lv

    def _make_level(self, z: int) -> Any:
        raise NotImplementedError

    def roots(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        r: tuple[NDArray[np.int64], NDArray[np.int64]] = self.base.roots()
        return r


@dataclass(frozen=True, eq=False)
class RefinedTree(DeeperTree):
    """A tile tree carried on below its finest level down to ``zmax`` (for imagery finer than
    the terrain), the levels below being its finest surface refined."""

    base: Any
    zmax: int
    _levels: dict[int, Any] = field(default_factory=dict, repr=False)

    @property
    def texture_zmax(self) -> int | None:
        z = self.base.texture_zmax
        return None if z is None else int(z)

    @property
    def twist(self) -> Any:
        return self.base.twist

    @property
    def roughness(self) -> Any:
        return self.base.roughness

    def _make_level(self, z: int) -> Any:
        leaves = [
            zb
            for zb in range(self.base.zmin, min(z, self.base.zmax) + 1)
            if getattr(self.base.level(zb), "leaf", None) is not None
        ]
        if z <= self.base.zmax and not leaves:
            return self.base.level(z)
        # below the finest level, or at and below stored tiles without children: the finest
        # stored surface, cut finer
        return _RefinedLevel(z, self.base)

    def stored(self, z: int, x: int, y: int) -> bool:
        """Whether tile z/x/y is the base's own (not cut from an ancestor's surface)."""
        if z > self.base.zmax:
            return False
        st = self.base.level(z).stats(np.array([x], np.int64), np.array([y], np.int64))
        return bool(st.exists[0])
