"""Tile meshes by error (Cesium's and Martini's way): an RTIN of the tile's finest grid, cut at an
error bound picked per frame, instead of one of a few regular grids.

A regular grid spends its triangles evenly: where a tile is rough in one corner and smooth in
the rest, the grid that follows the corner is far too fine elsewhere, and a tile split for its
texture (paper 000's pixel band) keeps at least the coarsest grid's 512 triangles however small
its error is on screen. An RTIN (``terrain.rtin``) splits only where its error bound needs it.

The selection needs each candidate mesh's error before any mesh is made, so a tile's candidates
are a fixed ladder of bounds, ``LADDER[j]`` times its coarsest grid's recorded error (the tile's
roughness at its own scale), the last one 0 (the whole grid). Slot j's error is its bound plus
the finest grid's own recorded error against the data (one triangle inequality), except on the
level above the finest, whose tiles are meshed from a grid twice as fine: the data's own (the
truth the tree measures against), so a slot's error is its bound alone. The sum is spent block
by block where the tree knows the finest grid's own error per block (its descendants' errors:
``ErrorLadder.cut``): a triangle over well-sampled blocks takes the allowance the roughest block
does not use, within the same sum. ``ErrorLadder`` wraps a
tile tree so that its statistics give those errors per slot, and the selection picks the
coarsest slot within ``max_sse`` as it picked the coarsest grid. A mesh key names the tile and
the slot (``geo.keys``' grid index).

Heights are meshed as the height above the tile's tangent plane at its centre, so the RTIN's
error includes the ellipsoid's curvature under its flat triangles (a tile-wide triangle sags
far below the surface it spans). Measured along the centre's vertical, not each point's, and
with the grid's Web Mercator spacing taken as even in the plane, which is exact to 0.4 % of the
bound on a 626 km tile (level 6) and closer on smaller ones (tests/test_tin_tiles.py).

The RTIN is ``terrain.rtin_numpy``'s, the same meshes as ``terrain.rtin``'s without numba, whose
import and kernels would cost a first picture 0.8 s.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import geodetic_to_ecef, up_vector
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.terrain import rtin_numpy
from lodscape.terrain.mesh import TileMesh, grid_coordinates, tin_mesh
from lodscape.terrain.pyramid import TileStats

__all__ = [
    "LADDER",
    "SPLIT_RUNG",
    "TRUTH_SPLIT_RUNG",
    "ErrorLadder",
    "SplitBeforeFinest",
    "TinTile",
    "cache_order",
    "ladder_errors",
    "ladder_threshold",
    "tin_tile_mesh",
]


#: The bounds a tile may be meshed at, as multiples of its coarsest grid's recorded error,
#: coarsest first (twenty-four: ``geo.keys.MAX_GRIDS``); the last is the whole finest grid. A
#: tile is drawn at the coarsest bound within what the frame allows, so the rungs' spacing is
#: what the bound gives away: a fourth root of two (1.19) from 2 down to 0.044; eight rungs 1.4
#: to 2 apart drew up to a fifth more triangles for the same 2 px, with a lower 99.9th
#: percentile of the measured error (BENCHMARKS, eighth pass).
LADDER: tuple[float, ...] = (*(2.0 ** (1 - k / 4) for k in range(23)), 0.0)
#: The finest rung a tile that can split is drawn at (2^-1.5 = 0.354 of its coarsest grid's
#: error); where it needs less it splits, and the rungs below (and the whole grid) are for the
#: tiles that cannot: the finest level's, a tileset's leaves. Four children, each cut by its
#: own error and its own distance, draw fewer triangles than their parent cut finer: on the
#: spine's views (``bench_spine.py``) 34-46 % fewer than sixteen rungs splitting below 0.125
#: (on 1.6-1.8 times the tiles), the measured error's 99.9th percentile up from 1.06-1.46 px
#: to 1.15-1.57 (BENCHMARKS, ninth pass).
SPLIT_RUNG = 10
#: The split rung of the level meshed from the truth (``ErrorLadder.from_truth``): 2^-0.5 =
#: 0.707 of its coarsest grid's error, about where that level split while its finest grid's
#: own error was part of its charge (SPLIT_RUNG plus that error); at SPLIT_RUNG such a tile is
#: cut finer on its finer grid where four children would draw fewer triangles.
TRUTH_SPLIT_RUNG = 6
_LADDER = np.asarray(LADDER, np.float64)[:, None]


def ladder_errors(error: NDArray[np.floating]) -> NDArray[np.float32]:
    """(len(LADDER), N) errors of a tile's ladder meshes from its (grids, N) grid errors: each
    slot's bound over the finest grid, plus that grid's own error."""
    e = np.asarray(error, np.float64)
    out: NDArray[np.float32] = (_LADDER * e[0] + e[-1]).astype(np.float32)
    return out


def ladder_threshold(error: NDArray[np.floating], slot: int) -> float:
    """The RTIN bound (metres) of ladder ``slot`` for a tile of (grids,) errors ``error``."""
    return float(LADDER[slot] * float(np.asarray(error)[0]))


def _split_first(err: NDArray[np.float32], st: TileStats, cut: int) -> NDArray[np.float32]:
    """``err`` (grids, N) with the grids finer than ``cut`` costing ``cut``'s error where a
    tile can split: a tile that needs less splits."""
    can_split = True if st.leaf is None else ~np.asarray(st.leaf, bool)
    err[cut + 1 :] = np.where(can_split, err[cut], err[cut + 1 :])
    return err


class _Level:
    """A level of a tree over another's, its tiles' errors as ``errors(stats, finest)`` says."""

    def __init__(
        self,
        base: Any,
        finest: bool,
        errors: Callable[[TileStats, bool], NDArray[np.float32]],
    ) -> None:
        self.base = base
        self.z = base.z
        self.finest = finest
        self.errors = errors

    def stats(self, x: NDArray[np.int64], y: NDArray[np.int64]) -> TileStats:
        st = self.base.stats(x, y)
        return TileStats(st.exists, st.min_h, st.max_h, self.errors(st, self.finest), st.leaf)


class _Over:
    """A tile tree over another: the same tiles, heights and levels, each tile's errors as
    ``_errors`` gives them (``finest``: on the finest level, where no tile splits); everything
    else is the wrapped tree's (a tree made on demand stays one: ``wait``, ``ready``,
    ``epoch``)."""

    def __init__(self, tree: Any) -> None:
        object.__setattr__(self, "base", tree)

    def level(self, z: int) -> _Level:
        return _Level(self.base.level(z), z >= self.base.zmax, self._errors)

    def _errors(self, st: TileStats, finest: bool) -> NDArray[np.float32]:
        raise NotImplementedError

    def __getattr__(self, name: str) -> Any:
        return getattr(self.base, name)

    def __setattr__(self, name: str, value: Any) -> None:
        # the selection's switches (``wait``) are the base tree's
        setattr(self.base, name, value)


class ErrorLadder(_Over):
    """A tile tree whose "grids" are the ``LADDER``'s slots over its finest grid: the same tiles,
    heights and levels, each slot's error as ``ladder_errors`` says, the rungs below
    ``SPLIT_RUNG`` (the whole grid among them) only where a tile cannot split."""

    #: A tile holds on to last frame's rung while it needs one at most two rungs coarser (a
    #: factor of 1.41, the hysteresis one step of regular grids or of eight rungs gave): a
    #: moving camera does not cut a tile's mesh anew at every rung it passes.
    hysteresis_steps = 2

    def __init__(self, tree: Any) -> None:
        super().__init__(tree)
        #: Every slot meshes the base tree's finest grid (twice as fine on ``from_truth``).
        object.__setattr__(self, "grids", (int(tree.grids[-1]),) * len(LADDER))
        #: The level whose tiles are meshed from the truth itself: the one above the finest,
        #: whose grid twice as fine as its finest is the truth's where the tree's finest
        #: level's finest grid samples the truth (``finest_is_truth``: ``terrain.pyramid``'s
        #: and ``terrain.lazy``'s trees; not a server's). Its RTINs are measured against the
        #: data, not against a grid that misses it by that grid's own error, so its slots
        #: cost their bounds alone. None: no such level.
        top = int(tree.zmax) - 1
        truth = getattr(tree, "finest_is_truth", False) and top >= int(tree.zmin)
        object.__setattr__(self, "from_truth", top if truth else None)

    def level(self, z: int) -> _Level:
        if z == self.from_truth:
            return _Level(self.base.level(z), False, self._truth_errors)
        return super().level(z)

    def segments(self, z: int) -> int:
        """Segments a side of the grid level ``z``'s tiles are meshed from."""
        return int(self.grids[-1]) * (2 if z == self.from_truth else 1)

    def _errors(self, st: TileStats, finest: bool) -> NDArray[np.float32]:
        err = ladder_errors(st.error)
        return err if finest else _split_first(err, st, SPLIT_RUNG)

    def _truth_errors(self, st: TileStats, finest: bool) -> NDArray[np.float32]:
        """A tile meshed from the truth: each slot's error is its bound (the whole grid's, 0)."""
        e = np.asarray(st.error, np.float64)
        err: NDArray[np.float32] = (_LADDER * e[0]).astype(np.float32)
        return _split_first(err, st, TRUTH_SPLIT_RUNG)

    def threshold(self, z: int, x: int, y: int, slot: int) -> float:
        """The RTIN bound of tile (z, x, y)'s ladder slot, from its recorded grid errors."""
        st = self.base.level(z).stats(np.array([x], np.int64), np.array([y], np.int64))
        return ladder_threshold(np.asarray(st.error)[:, 0], slot)

    def cut(self, z: int, x: int, y: int, slot: int) -> tuple[float, NDArray[np.float64] | None]:
        """What tile (z, x, y)'s ladder slot is cut at (``TinTile.mesh``'s bound and blocks):
        where the tree knows the finest grid's own error block by block, the slot's whole
        charge (its bound plus that grid's error, what the selection charged) against each
        triangle's error over the grid plus its blocks' (``rtin_numpy.with_blocks``), so
        that a block the grid samples well takes the allowance the roughest block does not
        use; else its bound over the grid (``threshold``).

        The blocks are the tile's descendants ``k`` levels down (the finest level's at most,
        ``k`` the tree's grids less one: 4×4 of them; fewer near the finest level), whose
        grid of 16·2^(depth-k) segments has the tile's finest grid's vertices and triangles
        there, so that their recorded error is that grid's own over their square; each capped
        by the tile's own recorded error (two bounds of one error). A tree made on demand
        keeps each tile's blocks with its chunk (``LazyTree.grid_blocks``): no other chunk is
        made for them. Only a tree whose errors are measured against the data
        (``finest_is_truth``; not a server's, whose errors are stated)."""
        base = self.base
        one = (np.array([x], np.int64), np.array([y], np.int64))
        e = np.asarray(base.level(z).stats(*one).error, np.float64)[:, 0]
        bound = ladder_threshold(e, slot)
        depth = len(base.grids) - 1
        measured = getattr(base, "finest_is_truth", False)  # not a server's stated errors
        if z == self.from_truth or not measured or not e[-1] > 0.0:
            return bound, None
        kept = getattr(base, "grid_blocks", None)
        if kept is not None:  # a tree made on demand keeps them with the tile's chunk
            got = kept(z, x, y)
            if got is None:
                return bound, None
            return bound + float(e[-1]), np.minimum(np.asarray(got, np.float64), e[-1])
        k = min(depth, int(base.zmax) - z)
        if k <= 0:
            return bound, None
        n = 1 << k
        dy, dx = np.divmod(np.arange(n * n, dtype=np.int64), n)
        st = base.level(z + k).stats((x << k) + dx, (y << k) + dy)
        own = np.where(st.exists, np.asarray(st.error, np.float64)[depth - k], 0.0)
        return bound + float(e[-1]), np.minimum(own, e[-1]).reshape(n, n)


class SplitBeforeFinest(_Over):
    """A tile tree of regular grids whose tiles that can split are not drawn with their finest
    grid: it costs what their next grid does, so a tile that needs it splits. Four children at
    the next grid draw as many triangles as their parent at its finest (the same vertices), and
    fewer where some of them can be coarser, each charged at its own nearer box: on
    ``bench_morph``'s approach with geomorphing, the 513² fBm's frames 35,008 → 14,720
    triangles (median) and the sample's 11,776 → 5,120, the largest jump the same or less
    (BENCHMARKS, ninth pass)."""

    def _errors(self, st: TileStats, finest: bool) -> NDArray[np.float32]:
        err = np.array(st.error, dtype=np.float32, copy=True)
        return err if finest else _split_first(err, st, len(err) - 2)


@cache
def _z_codes(n: int) -> NDArray[np.int64]:
    """Morton codes of 0 .. n-1: each number's bits spread to the even bit positions."""
    v = np.arange(n, dtype=np.int64)
    out = np.zeros(n, np.int64)
    for bit in range(max(1, int(n - 1).bit_length())):
        out |= ((v >> bit) & 1) << (2 * bit)
    out.setflags(write=False)  # shared by every caller (cached)
    return out


def cache_order(verts: NDArray[np.integer], tris: NDArray[np.integer]) -> NDArray[np.integer]:
    """The triangles of a grid mesh (vertices as (column, row)) in Z order of their centres,
    so that neighbours are drawn together and a GPU's post-transform cache reuses the vertices
    they share. The RTIN's cut emits its triangles level by level, each far from the last: 2.98
    vertices shaded per triangle on a 65² tile of 8,000 triangles against 0.66 in this order (a
    32-entry FIFO; tests/test_tin_tiles.py), for about 0.5 ms on the development machine."""
    col = np.asarray(verts[:, 0], np.int64)
    row = np.asarray(verts[:, 1], np.int64)
    t = np.asarray(tris)
    # three times the centre: integers, ordered as the centres are
    cx = col[t[:, 0]] + col[t[:, 1]] + col[t[:, 2]]
    cy = row[t[:, 0]] + row[t[:, 1]] + row[t[:, 2]]
    z = _z_codes(int(max(cx.max(initial=0), cy.max(initial=0))) + 1)
    return tris[np.argsort(z[cx] | (z[cy] << 1), kind="stable")]


class TinTile:
    """A tile's RTIN before any cut: its (S+1)² grid ``heights`` (row 0 north, S a power of
    two; ``data``: the bytes a provider fetched them as, if any), where they stand, and the
    RTIN's errors; ``mesh`` cuts it at any bound. A tile's ladder slots all mesh the same grid, so a
    provider that keeps a tile's ``TinTile`` makes a rung change a cut alone: no heights read,
    no errors measured again (``store.provider.RasterProvider``)."""

    def __init__(
        self,
        z: int,
        x: int,
        y: int,
        heights: NDArray[np.floating],
        data: bytes = b"",
        blocks: NDArray[np.floating] | None = None,
    ) -> None:
        self.z, self.x, self.y = z, x, y
        self.data = data
        #: What the grid misses of the data block by block (``ErrorLadder.cut``), if given:
        #: the errors are then each triangle's over the grid plus its blocks'
        #: (``rtin_numpy.with_blocks``), and a cut keeps them within its bound against the data.
        self.blocks = None if blocks is None else np.asarray(blocks, np.float64)
        self.heights = np.asarray(heights)
        s = self.heights.shape[0] - 1
        xs, ys = grid_coordinates(z, x, y, s)
        self.lon, self.lat = merc_to_lonlat(xs, ys)
        #: None where the heights are not all finite: no RTIN (a regular grid is made instead).
        self.errors: NDArray[np.float64] | None = None
        if np.isfinite(self.heights).all():
            lon = np.broadcast_to(self.lon[None, :], self.heights.shape)
            lat = np.broadcast_to(self.lat[:, None], self.heights.shape)
            # heights above the tangent plane at the centre: the RTIN's flat triangles are
            # measured against the curved lattice, sag included
            mid = s // 2
            c = geodetic_to_ecef(float(self.lon[mid]), float(self.lat[mid]), 0.0)
            up = up_vector(float(self.lon[mid]), float(self.lat[mid]))
            above = (geodetic_to_ecef(lon, lat, self.heights.astype(np.float64)) - c) @ up
            self.errors = rtin_numpy.errors(above)
            if self.blocks is not None:
                self.errors = rtin_numpy.with_blocks(self.errors, self.blocks)

    @property
    def nbytes(self) -> int:
        # the heights are a view of ``data`` where it was given
        errors = 0 if self.errors is None else self.errors.nbytes
        return (len(self.data) or self.heights.nbytes) + errors

    def mesh(self, key: int, threshold: float) -> TileMesh | None:
        """The RTIN mesh within ``threshold`` metres of every grid point, with skirts (of the
        data, with ``blocks``: ``threshold`` no less than the largest); None where the heights
        are not all finite."""
        if self.errors is None:
            return None
        s = self.heights.shape[0] - 1
        verts, tris = rtin_numpy.mesh(self.errors, max(float(threshold), 0.0))
        ordered = cache_order(verts, tris)
        col = verts[:, 0].astype(np.int64)
        row = verts[:, 1].astype(np.int64)
        sides = [
            np.nonzero(col == 0)[0],
            np.nonzero(row == s)[0],
            np.nonzero(col == s)[0],
            np.nonzero(row == 0)[0],
        ]
        lon, lat = self.lon[col], self.lat[row]
        h = self.heights[row, col].astype(np.float64)
        return tin_mesh(key, self.z, self.x, self.y, lon, lat, h, ordered, sides)


def tin_tile_mesh(
    key: int, z: int, x: int, y: int, heights: NDArray[np.floating], threshold: float
) -> TileMesh | None:
    """Tile (z, x, y)'s RTIN mesh of its (S+1)² grid ``heights`` (row 0 north, S a power of
    two), within ``threshold`` metres of every grid point, with skirts; None where the heights
    are not all finite (a regular grid is made instead)."""
    return TinTile(z, x, y, heights).mesh(key, threshold)
