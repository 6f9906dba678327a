"""``terrain.rtin``'s RTIN in NumPy alone, for the tiles a picture meshes (``terrain.tin_tiles``).

The same errors and the same meshes as ``rtin.Rtin`` with every triangle's error exact (its
``EXACT_SPAN`` at least the grid's side, as for tiles of 65² heights), without numba: importing
numba and loading its compiled kernels costs about 0.8 s, more than a whole first picture of the
sample. A level of the RTIN is one array expression over all its squares (``rtin``'s docstring
says what the levels are), and a mesh is cut one tree level at a time, so a 65² tile takes a
millisecond or two. ``tests/test_rtin.py`` checks both against each other.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

__all__ = ["errors", "mesh"]

F64 = NDArray[np.float64]


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


def _diamond(h: F64, s: int, err: F64) -> None:
    """The level whose triangles have the squares' edges as hypotenuses and their centres as
    apexes: slots at the edge midpoints, shared by the squares on either side."""
    size = h.shape[0]
    n = (size - 1) // s
    half, quarter = s // 2, s // 4
    w = _windows(h, s)
    tl, tr = w[:, :, 0, 0, None, None], w[:, :, 0, s, None, None]
    bl, br = w[:, :, s, 0, None, None], w[:, :, s, s, None, None]
    c2 = 2.0 * w[:, :, half, half, None, None]
    v, u = np.mgrid[0 : s + 1, 0 : s + 1].astype(np.float64)
    inv = 1.0 / s
    top = v <= np.minimum(u, s - u)
    bottom = v >= np.maximum(u, s - u)
    left = u <= np.minimum(v, s - v)
    right = u >= np.maximum(v, s - v)
    r_top = tl + (tr - tl) * inv * u + (c2 - tl - tr) * inv * v - w
    r_bottom = bl + (c2 - bl - br) + (br - bl) * inv * u - (c2 - bl - br) * inv * v - w
    r_left = tl + (c2 - tl - bl) * inv * u + (bl - tl) * inv * v - w
    r_right = tr + (c2 - tr - br) - (c2 - tr - br) * inv * u + (br - tr) * inv * v - w

    def rng(r: F64, m: NDArray[np.bool_]) -> tuple[F64, F64]:
        return (
            np.where(m, r, np.inf).min(axis=(2, 3)),
            np.where(m, r, -np.inf).max(axis=(2, 3)),
        )

    # horizontal edge slots (rows 0, s, … n·s; columns half + k·s): tops and bottoms
    lo_h = np.zeros((n + 1, n))
    hi_h = np.zeros((n + 1, n))
    a, b = rng(r_top, top)
    lo_h[:-1] = np.minimum(lo_h[:-1], a)
    hi_h[:-1] = np.maximum(hi_h[:-1], b)
    a, b = rng(r_bottom, bottom)
    lo_h[1:] = np.minimum(lo_h[1:], a)
    hi_h[1:] = np.maximum(hi_h[1:], b)
    # vertical edge slots (rows half + k·s; columns 0, s, … n·s): lefts and rights
    lo_v = np.zeros((n, n + 1))
    hi_v = np.zeros((n, n + 1))
    a, b = rng(r_left, left)
    lo_v[:, :-1] = np.minimum(lo_v[:, :-1], a)
    hi_v[:, :-1] = np.maximum(hi_v[:, :-1], b)
    a, b = rng(r_right, right)
    lo_v[:, 1:] = np.minimum(lo_v[:, 1:], a)
    hi_v[:, 1:] = np.maximum(hi_v[:, 1:], b)
    # merged with the children's errors, a quarter square off on both sides (inside the grid)
    pad = np.pad(err, quarter, constant_values=0.0)
    for (lo, hi), (y0, x0) in (((lo_h, hi_h), (0, half)), ((lo_v, hi_v), (half, 0))):
        ys = np.arange(y0, size, s)[:, None]
        xs = np.arange(x0, size, s)[None, :]
        e = np.maximum(-lo, hi)
        for dy in (-quarter, quarter):
            for dx in (-quarter, quarter):
                e = np.maximum(e, pad[ys + dy + quarter, xs + dx + quarter])
        err[y0::s, x0::s] = e


def _square(h: F64, s: int, err: F64) -> None:
    """The level whose squares are cut by one diagonal, leaning by their parity: a slot at each
    square's centre, shared by its two triangles."""
    half = s // 2
    w = _windows(h, s)
    n = w.shape[0]
    tl, tr = w[:, :, 0, 0, None, None], w[:, :, 0, s, None, None]
    bl, br = w[:, :, s, 0, None, None], w[:, :, s, s, None, None]
    v, u = np.mgrid[0 : s + 1, 0 : s + 1].astype(np.float64)
    inv = 1.0 / s
    qy, qx = np.mgrid[0:n, 0:n]
    even = ((qx + qy) % 2 == 0)[:, :, None, None]
    # even: the diagonal top-left to bottom-right; odd: top-right to bottom-left
    r_even = np.where(
        u >= v,
        tl + (tr - tl) * inv * u + (br - tr) * inv * v,
        tl + (br - bl) * inv * u + (bl - tl) * inv * v,
    )
    r_odd = np.where(
        u + v <= s,
        tl + (tr - tl) * inv * u + (bl - tl) * inv * v,
        (tr + bl - br) + (br - bl) * inv * u + (br - tr) * inv * v,
    )
    r = np.where(even, r_even, r_odd) - w
    lo = np.minimum(r.min(axis=(2, 3)), 0.0)
    hi = np.maximum(r.max(axis=(2, 3)), 0.0)
    e = np.maximum(-lo, hi)
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
