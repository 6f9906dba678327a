"""``terrain.rtin``'s RTIN in NumPy alone, for the tiles a picture meshes (``terrain.tin_tiles``).

The same errors and the same meshes as ``rtin.Rtin`` with every triangle's error exact (its
``EXACT_SPAN`` at least the grid's side, as for tiles of 65² heights), without numba: importing
numba and loading its compiled kernels costs about 0.8 s, more than a whole first picture of the
sample. A level of the RTIN is one array expression over all its squares (``rtin``'s docstring
says what the levels are), and a mesh is cut one tree level at a time: a 65² tile's errors take
about 2 ms and its cut up to 1.5 ms on the development machine (numba's whole tile: 0.3 ms,
once loaded). ``tests/test_rtin.py`` checks both against each other.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

__all__ = ["errors", "merged", "mesh", "with_blocks"]

F64 = NDArray[np.float64]
Idx = NDArray[np.intp]


def _windows(h: F64, s: int) -> F64:
    """(n, n, s+1, s+1) views of the squares of side s (sharing their edges)."""
    w: F64 = sliding_window_view(h, (s + 1, s + 1))[::s, ::s]
    return w


def errors(heights: NDArray[np.floating]) -> F64:
    """Per grid point: the error of the triangles whose hypotenuse midpoint it is (the largest
    |plane − height| over every grid point inside them), merged with their children's, as
    ``rtin._errors_kernel`` with every level exact."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    size = h.shape[0]
    if h.ndim != 2 or h.shape[1] != size or size < 2 or (size - 1) & (size - 2):
        raise ValueError(f"Expected a square grid of 2^k+1 heights, got shape {h.shape}")
    err = np.zeros((size, size))
    if size == 2:
        return err
    tile = size - 1
    # s = 2: every point is a corner, an edge midpoint or the centre; the error is the height's
    # distance from its hypotenuse's midpoint, merged with the children's
    d_h = np.abs(0.5 * (h[::2, :-1:2] + h[::2, 2::2]) - h[::2, 1::2])  # horizontal edges
    d_v = np.abs(0.5 * (h[:-1:2, ::2] + h[2::2, ::2]) - h[1::2, ::2])  # vertical edges
    err[::2, 1::2] = d_h
    err[1::2, ::2] = d_v
    # the centres: each square's diagonal leans by the square's parity
    qy, qx = np.mgrid[0 : tile // 2, 0 : tile // 2]
    even = (qx + qy) % 2 == 0
    main = 0.5 * (h[:-1:2, :-1:2] + h[2::2, 2::2]) - h[1::2, 1::2]
    anti = 0.5 * (h[:-1:2, 2::2] + h[2::2, :-1:2]) - h[1::2, 1::2]
    d = np.where(even, main, anti)
    # merged with the children's, at the four edge midpoints (whose ranges their errors hold)
    sq = np.maximum.reduce([np.abs(d), d_h[:-1, :], d_h[1:, :], d_v[:, :-1], d_v[:, 1:]])
    err[1::2, 1::2] = sq
    s = 4
    while s <= tile:
        _diamond(h, s, err)
        _square(h, s, err)
        s *= 2
    return err


def merged(field: NDArray[np.floating]) -> F64:
    """``field`` (a value per grid point, slots as ``errors`` has them) merged as ``errors``
    merges its own: each slot raised to the largest of the slots of the triangles inside its
    own, so that a cut on it (``mesh``) that splits a triangle has split its parents, on both
    sides of its edge (no T-junction)."""
    out = np.array(field, dtype=np.float64, copy=True)
    size = out.shape[0]
    tile = size - 1
    if size <= 2:
        return out
    d_h, d_v = out[::2, 1::2], out[1::2, ::2]
    out[1::2, 1::2] = np.maximum.reduce(
        [out[1::2, 1::2], d_h[:-1, :], d_h[1:, :], d_v[:, :-1], d_v[:, 1:]]
    )
    s = 4
    while s <= tile:
        half, quarter = s // 2, s // 4
        pad = np.pad(out, quarter, constant_values=0.0)
        for y0, x0 in ((0, half), (half, 0)):
            e = out[y0::s, x0::s]
            for dy in (0, 2 * quarter):
                for dx in (0, 2 * quarter):
                    e = np.maximum(e, pad[y0 + dy :: s, x0 + dx :: s][: e.shape[0], : e.shape[1]])
            out[y0::s, x0::s] = e
        n = tile // s
        c = out
        out[half::s, half::s] = np.maximum.reduce(
            [
                c[half::s, half::s],
                c[0:-1:s, half::s][:n, :n],
                c[s::s, half::s][:n, :n],
                c[half::s, 0:-1:s][:n, :n],
                c[half::s, s::s][:n, :n],
            ]
        )
        s *= 2
    return out


def with_blocks(err: NDArray[np.floating], blocks: NDArray[np.floating]) -> F64:
    """``errors``' ``err`` plus, at each slot, the largest of ``blocks`` (an m×m map over the
    grid, m a power of two dividing its side: a bound on each block's own error, as a grid's
    against the data it samples) over the blocks its triangles reach, merged (``merged``).
    Cut at a bound E (``mesh``), every triangle left is within E of what the blocks bound:
    its own error against the grid is its slot's ``err``, the grid's under it its blocks'."""
    size = err.shape[0]
    tile = size - 1
    b = np.asarray(blocks, np.float64)
    m = b.shape[0]
    if b.shape != (m, m) or m < 1 or tile % m or (m & (m - 1)):
        raise ValueError(f"Expected an m×m map of blocks, m a power of two dividing {tile}")
    side = tile // m
    # the largest block over each rectangle of blocks [k0, k1] × [j0, j1]
    table = np.zeros((m, m, m, m))
    for k0 in range(m):
        rows = np.maximum.accumulate(b[k0:], axis=0)  # rows k0 .. k1, per column
        for j0 in range(m):
            table[k0, k0:, j0, j0:] = np.maximum.accumulate(rows[:, j0:], axis=1)
    r, c = np.mgrid[0:size, 0:size]
    # a slot's triangles lie within half its level's square of it: the lowest bit of r | c
    rc = r | c
    h = np.where(rc == 0, tile, rc & -rc)
    lo_r = np.clip((r - h) // side, 0, m - 1)
    hi_r = np.clip(-(-(r + h) // side) - 1, 0, m - 1)
    lo_c = np.clip((c - h) // side, 0, m - 1)
    hi_c = np.clip(-(-(c + h) // side) - 1, 0, m - 1)
    return merged(np.asarray(err, np.float64) + table[lo_r, hi_r, lo_c, hi_c])


@cache
def _points(s: int) -> tuple[Idx, Idx, Idx, Idx]:
    """The grid points (rows, columns, as (k, m) arrays) of a square of side s inside each of
    its k triangles: the diamond level's top, bottom, left and right ones (edges as
    hypotenuses, the centre as apex), then the square level's pairs, leaning one way (above and
    below the diagonal from the top-left) and the other (above and below the other diagonal).
    Triangles of a kind hold as many points as each other, so one gather serves them all."""
    v, u = np.mgrid[0 : s + 1, 0 : s + 1]
    diamond = [
        v <= np.minimum(u, s - u),
        v >= np.maximum(u, s - u),
        u <= np.minimum(v, s - v),
        u >= np.maximum(v, s - v),
    ]
    square = [u >= v, u <= v, u + v <= s, u + v >= s]

    def rows_cols(masks: list[NDArray[np.bool_]]) -> tuple[Idx, Idx]:
        rr = np.stack([v[m] for m in masks])
        cc = np.stack([u[m] for m in masks])
        rr.setflags(write=False)
        cc.setflags(write=False)
        return rr, cc

    return (*rows_cols(diamond), *rows_cols(square))


def _ranges(w: F64, rows: Idx, cols: Idx, planes: F64) -> tuple[F64, F64]:
    """(n, n, k) least and largest plane − height over each square's k triangles: ``planes``
    (3, n, n, k) the planes' a + b·u + c·v (u the column, v the row in the square)."""
    got = w[:, :, rows, cols]  # (n, n, k, m)
    a, b, c = planes[..., None]
    r = a + b * cols + c * rows - got
    return r.min(axis=-1), r.max(axis=-1)


def _corners(w: F64, s: int) -> tuple[F64, F64, F64, F64, F64]:
    half = s // 2
    return w[:, :, 0, 0], w[:, :, 0, s], w[:, :, s, 0], w[:, :, s, s], 2.0 * w[:, :, half, half]


def _diamond(h: F64, s: int, err: F64) -> None:
    """The level whose triangles have the squares' edges as hypotenuses and their centres as
    apexes: slots at the edge midpoints, shared by the squares on either side."""
    size = h.shape[0]
    n = (size - 1) // s
    half, quarter = s // 2, s // 4
    w = _windows(h, s)
    tl, tr, bl, br, c2 = _corners(w, s)
    inv = 1.0 / s
    rows, cols = _points(s)[:2]
    planes = np.stack(
        [
            np.stack([tl, bl + (c2 - bl - br), tl, tr + (c2 - tr - br)], axis=-1),
            np.stack([tr - tl, br - bl, c2 - tl - bl, tr + br - c2], axis=-1) * inv,
            np.stack([c2 - tl - tr, bl + br - c2, bl - tl, br - tr], axis=-1) * inv,
        ]
    )
    lo, hi = _ranges(w, rows, cols, planes)
    lo, hi = np.minimum(lo, 0.0), np.maximum(hi, 0.0)
    # horizontal edge slots (rows 0, s, … n·s; columns half + k·s): tops and bottoms;
    # vertical ones (rows half + k·s; columns 0, s, … n·s): lefts and rights
    lo_h, hi_h = np.zeros((n + 1, n)), np.zeros((n + 1, n))
    lo_h[:-1], hi_h[:-1] = lo[..., 0], hi[..., 0]
    lo_h[1:], hi_h[1:] = np.minimum(lo_h[1:], lo[..., 1]), np.maximum(hi_h[1:], hi[..., 1])
    lo_v, hi_v = np.zeros((n, n + 1)), np.zeros((n, n + 1))
    lo_v[:, :-1], hi_v[:, :-1] = lo[..., 2], hi[..., 2]
    lo_v[:, 1:] = np.minimum(lo_v[:, 1:], lo[..., 3])
    hi_v[:, 1:] = np.maximum(hi_v[:, 1:], hi[..., 3])
    # merged with the children's errors, a quarter square off on both sides (inside the grid)
    pad = np.pad(err, quarter, constant_values=0.0)
    for lo_, hi_, (y0, x0) in ((lo_h, hi_h, (0, half)), (lo_v, hi_v, (half, 0))):
        e = np.maximum(-lo_, hi_)
        for dy in (0, 2 * quarter):
            for dx in (0, 2 * quarter):
                e = np.maximum(e, pad[y0 + dy :: s, x0 + dx :: s][: e.shape[0], : e.shape[1]])
        err[y0::s, x0::s] = e


def _square(h: F64, s: int, err: F64) -> None:
    """The level whose squares are cut by one diagonal, leaning by their parity: a slot at each
    square's centre, shared by its two triangles."""
    half = s // 2
    w = _windows(h, s)
    n = w.shape[0]
    tl, tr, bl, br, _ = _corners(w, s)
    inv = 1.0 / s
    rows, cols = _points(s)[2:]
    # even squares: the diagonal from the top-left (above it, then below); odd: the other
    planes = np.stack(
        [
            np.stack([tl, tl, tl, tr + bl - br], axis=-1),
            np.stack([tr - tl, br - bl, tr - tl, br - bl], axis=-1) * inv,
            np.stack([br - tr, bl - tl, bl - tl, br - tr], axis=-1) * inv,
        ]
    )
    lo, hi = _ranges(w, rows, cols, planes)
    qy, qx = np.mgrid[0:n, 0:n]
    even = (qx + qy) % 2 == 0
    lo = np.where(even, np.minimum(lo[..., 0], lo[..., 1]), np.minimum(lo[..., 2], lo[..., 3]))
    hi = np.where(even, np.maximum(hi[..., 0], hi[..., 1]), np.maximum(hi[..., 2], hi[..., 3]))
    e = np.maximum(-np.minimum(lo, 0.0), np.maximum(hi, 0.0))
    # merged with the children's: the four edge midpoints
    c = err
    e = np.maximum.reduce(
        [
            e,
            c[0:-1:s, half::s][:n, :n],
            c[s::s, half::s][:n, :n],
            c[half::s, 0:-1:s][:n, :n],
            c[half::s, s::s][:n, :n],
        ]
    )
    err[half::s, half::s] = e


def mesh(err: F64, max_error: float) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """(vertices (N, 2) as (column, row), triangles (M, 3)) of the RTIN within ``max_error``,
    the triangles ``rtin.Rtin.mesh`` gives (in another order), wound as it winds them."""
    size = err.shape[0]
    last = size - 1
    tri = np.array([[0, 0, last, last, last, 0], [last, last, 0, 0, 0, last]], np.int64)
    leaves = []
    while tri.shape[0]:
        ax, ay, bx, by, cx, cy = tri.T
        mx, my = (ax + bx) >> 1, (ay + by) >> 1
        split = (np.abs(ax - cx) + np.abs(ay - cy) > 1) & (err[my, mx] > max_error)
        leaves.append(tri[~split])
        t, m = tri[split], np.column_stack([mx[split], my[split]])
        # (b, c, m) and (c, a, m): rtin's two children of (a, b, c)
        tri = np.concatenate(
            [np.column_stack([t[:, 2:4], t[:, 4:6], m]), np.column_stack([t[:, 4:6], t[:, 0:2], m])]
        )
    out = np.concatenate(leaves).reshape(-1, 3, 2)
    flat = out[:, :, 1] * size + out[:, :, 0]
    index = np.zeros(size * size, np.int64)
    index[flat.ravel()] = 1
    used = np.flatnonzero(index)
    index[used] = np.arange(used.size)
    vertices = np.column_stack([used % size, used // size]).astype(np.int32)
    return vertices, index[flat].astype(np.int32)
