"""Right-triangulated irregular networks (RTIN) on a (2^k+1)² height grid, with a kept error bound.

Martini's method (mapbox/martini, after Evans, Kirkpatrick and Townsend) in numba: every right
triangle of the implicit binary tree over the grid is visited once, from the smallest up, to
compute an error; a mesh for a given bound then descends from the two root triangles and splits
a triangle at its hypotenuse midpoint while its error exceeds the bound.

Martini's own error is the height error at the hypotenuse midpoint alone, merged with the
children's; measured on real terrain its meshes exceed the requested error by up to 2× (see
ENVIRONMENT.md). Here the error of a triangle is the largest vertical distance between its plane
and *every* grid height inside it, merged with its children's as Martini does, so a mesh keeps to
its bound exactly. (A cheaper bound, the children's signed residual ranges shifted by the "tent"
between a triangle's plane and its children's, kept the bound too but drew three times the
triangles on fBm terrain: the tents add up over the levels.)

A triangle and its neighbour across the hypotenuse share the midpoint; the split test reads the
larger of their errors there, so both split together and the mesh has no T-junction inside the
tile. Vertices on the tile's edge depend on the tile's own errors: neighbours hide the difference
with skirts.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["Rtin", "mesh_error", "rtin"]


#: Triangles with hypotenuses up to this many cells get their exact error from every grid point
#: they hold; bigger ones (a few, and seldom final) a bound from their children's.
EXACT_SPAN = 64


@numba.njit(cache=True)  # type: ignore[misc]
def _errors_kernel(h: NDArray[np.float64], exact_span: int) -> NDArray[np.float64]:
    """Per grid point: the error of the two triangles whose hypotenuse midpoint it is, merged with
    their children's (so a triangle splits whenever a descendant must, and meshes have no cracks).

    The RTIN's levels, finest first, alternate two regular patterns over squares of side S: the
    "diamond" level (each square cut by both diagonals into four triangles whose hypotenuses are
    the square's edges) and the "square" level (each square cut by one diagonal, leaning by the
    parity of the square). So a level is a sweep over its squares, not a walk of a triangle tree:
    each point's residual against its triangle's plane goes to that triangle's slot, its
    hypotenuse midpoint, which the triangle across the hypotenuse shares.
    """
    size = h.shape[0]
    tile = size - 1
    lo = np.zeros((size, size), dtype=np.float64)
    hi = np.zeros((size, size), dtype=np.float64)
    err = np.zeros((size, size), dtype=np.float64)
    s = 2
    while s <= tile:
        # the smallest squares need no sweep: every point they hold is a corner, an edge
        # midpoint (the diamond level's slots) or the centre, and _settle reads those exactly
        exact = 2 < s <= exact_span
        for square in range(2):
            if exact:
                if square:
                    _sweep_square(h, s, lo, hi)
                else:
                    _sweep_diamond(h, s, lo, hi)
            _settle(h, s, square, exact, lo, hi, err)
        s *= 2
    return err


@numba.njit(cache=True, inline="always")  # type: ignore[misc]
def _touch(
    lo: NDArray[np.float64], hi: NDArray[np.float64], y: int, x: int, a: float, b: float
) -> None:
    lo[y, x] = min(lo[y, x], a)
    hi[y, x] = max(hi[y, x], b)


@numba.njit(cache=True, fastmath=True)  # type: ignore[misc]
def _range(
    h: NDArray[np.float64],
    y0: int,
    x0: int,
    z0: float,
    gu: float,
    gv: float,
    v0: int,
    v1: int,
    ua: int,
    ub: int,
    uc: int,
    ud: int,
) -> tuple[float, float]:
    """Range of the plane z0 + gu·u + gv·v minus the heights over rows v0..v1 of a triangle whose
    row v spans columns ua + ub·v .. uc + ud·v (offsets from (x0, y0))."""
    a = 0.0
    b = 0.0
    for v in range(v0, v1 + 1):
        row = h[y0 + v]
        base = z0 + gv * v
        for u in range(ua + ub * v, uc + ud * v + 1):
            r = base + gu * u - row[x0 + u]
            a = min(a, r)
            b = max(b, r)
    return a, b


@numba.njit(cache=True)  # type: ignore[misc]
def _sweep_square(
    h: NDArray[np.float64], s: int, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> None:
    n = (h.shape[0] - 1) // s
    half = s // 2
    inv = 1.0 / s
    for qy in range(n):
        y0 = qy * s
        for qx in range(n):
            x0 = qx * s
            tl, tr = h[y0, x0], h[y0, x0 + s]
            bl, br = h[y0 + s, x0], h[y0 + s, x0 + s]
            if (qx + qy) & 1 == 0:
                # diagonal from top-left to bottom-right: above it (u >= v), then below
                a1, b1 = _range(h, y0, x0, tl, (tr - tl) * inv, (br - tr) * inv, 0, s, 0, 1, s, 0)
                a2, b2 = _range(h, y0, x0, tl, (br - bl) * inv, (bl - tl) * inv, 0, s, 0, 0, 0, 1)
            else:
                # diagonal from top-right to bottom-left: above it (u + v <= s), then below
                a1, b1 = _range(h, y0, x0, tl, (tr - tl) * inv, (bl - tl) * inv, 0, s, 0, 0, s, -1)
                a2, b2 = _range(
                    h, y0, x0, tr + bl - br, (br - bl) * inv, (br - tr) * inv, 0, s, s, -1, s, 0
                )
            # the two triangles share the hypotenuse, and so the slot at the square's centre;
            # points on the square's edges are counted again by the neighbouring squares
            _touch(lo, hi, y0 + half, x0 + half, min(a1, a2), max(b1, b2))


@numba.njit(cache=True)  # type: ignore[misc]
def _sweep_diamond(
    h: NDArray[np.float64], s: int, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> None:
    n = (h.shape[0] - 1) // s
    half = s // 2
    inv = 1.0 / s
    for qy in range(n):
        y0 = qy * s
        for qx in range(n):
            x0 = qx * s
            tl, tr = h[y0, x0], h[y0, x0 + s]
            bl, br = h[y0 + s, x0], h[y0 + s, x0 + s]
            c2 = 2.0 * h[y0 + half, x0 + half]
            # four triangles with the square's edges as hypotenuses and its centre as apex
            a, b = _range(
                h, y0, x0, tl, (tr - tl) * inv, (c2 - tl - tr) * inv, 0, half, 0, 1, s, -1
            )
            _touch(lo, hi, y0, x0 + half, a, b)
            a, b = _range(
                h,
                y0,
                x0,
                bl + (c2 - bl - br),
                (br - bl) * inv,
                (c2 - bl - br) * -inv,
                half,
                s,
                s,
                -1,
                0,
                1,
            )
            _touch(lo, hi, y0 + s, x0 + half, a, b)
            # the left and right triangles widen to the middle row, then narrow: two runs each
            gl, gv = (c2 - tl - bl) * inv, (bl - tl) * inv
            a1, b1 = _range(h, y0, x0, tl, gl, gv, 0, half, 0, 0, 0, 1)
            a2, b2 = _range(h, y0, x0, tl, gl, gv, half + 1, s, 0, 0, s, -1)
            _touch(lo, hi, y0 + half, x0, min(a1, a2), max(b1, b2))
            gr, gv = (c2 - tr - br) * -inv, (br - tr) * inv
            z0 = tr + (c2 - tr - br)
            a1, b1 = _range(h, y0, x0, z0, gr, gv, 0, half, s, -1, s, 0)
            a2, b2 = _range(h, y0, x0, z0, gr, gv, half + 1, s, 0, 1, s, 0)
            _touch(lo, hi, y0 + half, x0 + s, min(a1, a2), max(b1, b2))


@numba.njit(cache=True)  # type: ignore[misc]
def _settle(
    h: NDArray[np.float64],
    s: int,
    square: int,
    exact: bool,
    lo: NDArray[np.float64],
    hi: NDArray[np.float64],
    err: NDArray[np.float64],
) -> None:
    """Errors of one level's slots: their range (swept, or bounded from the children's), merged
    with the children's errors."""
    size = h.shape[0]
    half = s // 2
    quarter = s // 4
    if square:
        # slots at square centres; children at the four edge midpoints
        for y in range(half, size, s):
            for x in range(half, size, s):
                if not exact:
                    if (x // s + y // s) % 2 == 0:
                        d = 0.5 * (h[y - half, x - half] + h[y + half, x + half]) - h[y, x]
                    else:
                        d = 0.5 * (h[y - half, x + half] + h[y + half, x - half]) - h[y, x]
                    a = min(lo[y - half, x], lo[y + half, x], lo[y, x - half], lo[y, x + half])
                    b = max(hi[y - half, x], hi[y + half, x], hi[y, x - half], hi[y, x + half])
                    if s == 2:
                        # the children's points lie on this triangle's legs, where the tent is 0
                        lo[y, x] = min(a, d)
                        hi[y, x] = max(b, d)
                    else:
                        lo[y, x] = a + min(0.0, d)
                        hi[y, x] = b + max(0.0, d)
                e = max(-lo[y, x], hi[y, x], err[y - half, x], err[y + half, x])
                err[y, x] = max(e, err[y, x - half], err[y, x + half])
        return
    # slots at edge midpoints: horizontal edges (rows at multiples of s), then vertical ones;
    # a slot's children (the level has some from s = 4) sit a quarter square off, on both sides
    for vertical in range(2):
        dy, dx = (half, 0) if vertical else (0, half)
        for y in range(dy, size, s):
            for x in range(dx, size, s):
                a = b = e = 0.0
                if quarter > 0:
                    a, b = np.inf, -np.inf
                    for cy in (y - quarter, y + quarter):
                        if cy < 0 or cy >= size:
                            continue
                        for cx in (x - quarter, x + quarter):
                            if cx < 0 or cx >= size:
                                continue
                            a = min(a, lo[cy, cx])
                            b = max(b, hi[cy, cx])
                            e = max(e, err[cy, cx])
                if not exact:
                    d = 0.5 * (h[y - dy, x - dx] + h[y + dy, x + dx]) - h[y, x]
                    lo[y, x] = a + min(0.0, d)
                    hi[y, x] = b + max(0.0, d)
                err[y, x] = max(e, -lo[y, x], hi[y, x])


@numba.njit(cache=True)  # type: ignore[misc]
def _mesh_kernel(
    err: NDArray[np.float64], max_error: float
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    size = err.shape[0]
    last = size - 1
    index = np.zeros((size, size), dtype=np.int64)
    # an explicit stack instead of recursion; each row is one triangle (a, b, c)
    stack = np.empty((512, 6), dtype=np.int64)
    vertices = np.empty((size * size, 2), dtype=np.int32)
    triangles = np.empty((2 * last * last, 3), dtype=np.int32)
    nverts = 0
    ntris = 0
    for root in range(2):
        if root == 0:
            _put(stack, 0, 0, 0, last, last, last, 0)
        else:
            _put(stack, 0, last, last, 0, 0, 0, last)
        top = 1
        while top > 0:
            top -= 1
            ax, ay, bx, by = stack[top, 0], stack[top, 1], stack[top, 2], stack[top, 3]
            cx, cy = stack[top, 4], stack[top, 5]
            mx = (ax + bx) >> 1
            my = (ay + by) >> 1
            if abs(ax - cx) + abs(ay - cy) > 1 and err[my, mx] > max_error:
                # triangle doesn't keep to the bound: drill down (the left half comes out first)
                _put(stack, top, bx, by, cx, cy, mx, my)
                _put(stack, top + 1, cx, cy, ax, ay, mx, my)
                top += 2
            else:
                for px, py in ((ax, ay), (bx, by), (cx, cy)):
                    if index[py, px] == 0:
                        vertices[nverts, 0] = px
                        vertices[nverts, 1] = py
                        nverts += 1
                        index[py, px] = nverts
                triangles[ntris, 0] = index[ay, ax] - 1
                triangles[ntris, 1] = index[by, bx] - 1
                triangles[ntris, 2] = index[cy, cx] - 1
                ntris += 1
    return vertices[:nverts].copy(), triangles[:ntris].copy()


@numba.njit(cache=True)  # type: ignore[misc]
def _put(
    stack: NDArray[np.int64], row: int, a: int, b: int, c: int, d: int, e: int, f: int
) -> None:
    stack[row, 0] = a
    stack[row, 1] = b
    stack[row, 2] = c
    stack[row, 3] = d
    stack[row, 4] = e
    stack[row, 5] = f


class Rtin:
    """The error pyramid of one height grid, ready to give meshes for any error bound.

    ``heights`` is a (2^k+1)² grid, row 0 first; the meshes' vertices are (column, row) grid
    coordinates. Build once per tile, then call :meth:`mesh` per bound (STYLE 1).
    """

    def __init__(self, heights: NDArray[np.floating], exact_span: int = EXACT_SPAN) -> None:
        h = np.ascontiguousarray(heights, dtype=np.float64)
        size = h.shape[0]
        if h.ndim != 2 or h.shape[1] != size or size < 2 or (size - 1) & (size - 2):
            raise ValueError(f"Expected a square grid of 2^k+1 heights, got shape {h.shape}")
        if not np.isfinite(h).all():
            raise ValueError("Expected finite heights (fill nodata before meshing)")
        self.heights = h
        self.size = size
        if size == 2:
            self.errors = np.zeros((2, 2))
        else:
            self.errors = _errors_kernel(h, exact_span)

    def mesh(self, max_error: float = 0.0) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        """(vertices (N, 2) as (column, row), triangles (M, 3)) within ``max_error`` of every
        grid height, counter-clockwise with rows growing down (clockwise seen north-up)."""
        if not max_error >= 0.0:
            raise ValueError(f"Expected a non-negative max_error, got {max_error}")
        vertices, triangles = _mesh_kernel(self.errors, float(max_error))
        return vertices, triangles


def rtin(
    heights: NDArray[np.floating], max_error: float
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """One-shot :class:`Rtin` mesh of a (2^k+1)² grid within ``max_error``."""
    return Rtin(heights).mesh(max_error)


def mesh_error(
    heights: NDArray[np.floating], vertices: NDArray[np.integer], triangles: NDArray[np.integer]
) -> float:
    """The largest |mesh − height| over every point of the grid (the mesh drawn back onto it)."""
    h = np.ascontiguousarray(heights, dtype=np.float64)
    return float(
        _raster_error(
            h,
            np.ascontiguousarray(vertices, dtype=np.float64),
            np.ascontiguousarray(triangles, dtype=np.int64),
        )
    )


@numba.njit(cache=True)  # type: ignore[misc]
def _raster_error(h: NDArray[np.float64], v: NDArray[np.float64], t: NDArray[np.int64]) -> float:
    rows, cols = h.shape
    worst = 0.0
    for k in range(t.shape[0]):
        i0, i1, i2 = t[k, 0], t[k, 1], t[k, 2]
        x0, y0, x1, y1, x2, y2 = v[i0, 0], v[i0, 1], v[i1, 0], v[i1, 1], v[i2, 0], v[i2, 1]
        z0 = h[int(y0), int(x0)]
        z1 = h[int(y1), int(x1)]
        z2 = h[int(y2), int(x2)]
        det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
        if det == 0.0:
            continue
        for y in range(int(min(y0, y1, y2)), int(max(y0, y1, y2)) + 1):
            for x in range(int(min(x0, x1, x2)), int(max(x0, x1, x2)) + 1):
                w0 = ((y1 - y2) * (x - x2) + (x2 - x1) * (y - y2)) / det
                w1 = ((y2 - y0) * (x - x2) + (x0 - x2) * (y - y2)) / det
                w2 = 1.0 - w0 - w1
                if w0 < -1e-9 or w1 < -1e-9 or w2 < -1e-9:
                    continue
                if 0 <= y < rows and 0 <= x < cols:
                    e = abs(w0 * z0 + w1 * z1 + w2 * z2 - h[y, x])
                    if e > worst:
                        worst = e
    return worst
