"""Greedy meshes of a height grid for tileset builds (``lodscape build --mesher greedy``).

Delaunay refinement by greedy insertion (Garland & Heckbert's "greedy insertion", as Mapbox's
delatin and Fogleman's hmm do it): start from the grid's two corner triangles, and insert the
sample farthest from the mesh, re-triangulating Delaunay around it, until every sample lies
within the bound. Unlike RTIN, whose triangles must be halves of halves of the tile, a point
goes where the error is, so the same bound takes fewer triangles; but there is no hierarchy:
the meshes cannot be cut coarser at draw time, which is why raw DEMs (meshed per frame from
RTIN's error pyramid, with geomorphing between its levels) keep RTIN, and builds choose.

The insertion runs in hmm's C++ through ``pydelatin``. ``tin_sample_error`` measures any TIN
(RTIN's too) against scattered samples, for the build's per-tile error.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["MESHERS", "barycentric", "greedy_mesh", "tin_sample_error", "tin_sample_errors"]

#: The meshers a tileset build can use.
MESHERS = ("rtin", "greedy")


def greedy_mesh(
    heights: NDArray[np.floating], max_error: float
) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """(vertices (N, 2) as (column, row), triangles (M, 3)) within ``max_error`` of every height
    of the grid (any (R, C) shape of at least 2×2, row 0 first), as :meth:`Rtin.mesh` gives."""
    from pydelatin import Delatin

    h = np.ascontiguousarray(heights, dtype=np.float32)
    if h.ndim != 2 or min(h.shape) < 2:
        raise ValueError(f"Expected a grid of at least 2x2 heights, got shape {h.shape}")
    if not np.isfinite(h).all():
        raise ValueError("Expected finite heights (fill nodata before meshing)")
    if not max_error >= 0.0:
        raise ValueError(f"Expected a non-negative max_error, got {max_error}")
    tin = Delatin(h, max_error=float(max_error))
    xy = np.rint(np.asarray(tin.vertices)[:, :2]).astype(np.int32)
    # hmm numbers rows from the last one up
    vertices = np.column_stack([xy[:, 0], h.shape[0] - 1 - xy[:, 1]]).astype(np.int32)
    triangles = np.asarray(tin.triangles, dtype=np.int32).reshape(-1, 3)
    return vertices, triangles


@numba.njit(cache=True, nogil=True)  # type: ignore[misc]
def tin_sample_error(
    triangles: NDArray[np.int32],
    vertices: NDArray[np.int32],
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    h: NDArray[np.float64],
    plon: NDArray[np.float64],
    plat: NDArray[np.float64],
    ph: NDArray[np.float64],
) -> float:
    """The largest |mesh − sample| over the samples (``plon``, ``plat``, ``ph``) that lie in a
    triangle, interpolated in lon/lat as the quantized-mesh format does: grid vertex (col, row)
    sits at (lon[col], lat[row]) (lon rising, lat falling), height h[row, col]. Each sample is
    looked for among the triangles whose grid box covers its cell."""
    out = np.zeros(plon.size)
    return tin_sample_errors(triangles, vertices, lon, lat, h, plon, plat, ph, out)


@numba.njit(cache=True, nogil=True)  # type: ignore[misc]
def tin_sample_errors(
    triangles: NDArray[np.int32],
    vertices: NDArray[np.int32],
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    h: NDArray[np.float64],
    plon: NDArray[np.float64],
    plat: NDArray[np.float64],
    ph: NDArray[np.float64],
    out: NDArray[np.float64],
) -> float:
    """``tin_sample_error``, with each sample's |mesh − sample| written to ``out`` (0 where it
    lies in no triangle); returns the largest."""
    ncol = lon.size - 1
    nrow = lat.size - 1
    cells = ncol * nrow
    start = np.zeros(cells + 1, np.int64)
    m = triangles.shape[0]
    for t in range(m):
        c0, c1, r0, r1 = _box(triangles, vertices, t)
        for r in range(r0, r1):
            for c in range(c0, c1):
                start[r * ncol + c + 1] += 1
    for i in range(cells):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    members = np.empty(start[-1], np.int64)
    for t in range(m):
        c0, c1, r0, r1 = _box(triangles, vertices, t)
        for r in range(r0, r1):
            for c in range(c0, c1):
                k = r * ncol + c
                members[fill[k]] = t
                fill[k] += 1
    neg_lat = -lat
    worst = 0.0
    for k in range(plon.size):
        px, py = plon[k], plat[k]
        c = min(max(np.searchsorted(lon, px) - 1, 0), ncol - 1)
        r = min(max(np.searchsorted(neg_lat, -py) - 1, 0), nrow - 1)
        cell = r * ncol + c
        best = -1.0e30
        value = 0.0
        for j in range(start[cell], start[cell + 1]):
            t = members[j]
            a, b, d = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            ok, w0, w1 = barycentric(
                lon[vertices[a, 0]], lat[vertices[a, 1]],
                lon[vertices[b, 0]], lat[vertices[b, 1]],
                lon[vertices[d, 0]], lat[vertices[d, 1]],
                px, py,
            )  # fmt: skip
            if not ok:
                continue
            w2 = 1.0 - w0 - w1
            low = min(w0, w1, w2)
            if low > best:
                best = low
                value = (
                    w0 * h[vertices[a, 1], vertices[a, 0]]
                    + w1 * h[vertices[b, 1], vertices[b, 0]]
                    + w2 * h[vertices[d, 1], vertices[d, 0]]
                )
        if best < -1e-9:
            continue  # in no triangle: a hole the mesh leaves
        e = abs(value - ph[k])
        out[k] = e
        if e > worst:
            worst = e
    return worst


@numba.njit(cache=True, inline="always")  # type: ignore[misc]
def barycentric(
    x0: float, y0: float, x1: float, y1: float, x2: float, y2: float, px: float, py: float
) -> tuple[bool, float, float]:
    """Whether the triangle is not degenerate, and the weights of its first two corners at
    (px, py) (the third's is 1 − both)."""
    det = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
    if det == 0.0:
        return False, 0.0, 0.0
    w0 = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / det
    w1 = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / det
    return True, w0, w1


@numba.njit(cache=True, inline="always")  # type: ignore[misc]
def _box(
    triangles: NDArray[np.int32], vertices: NDArray[np.int32], t: int
) -> tuple[int, int, int, int]:
    """The grid cells a triangle's box covers: columns c0..c1 - 1, rows r0..r1 - 1."""
    a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
    c0 = min(vertices[a, 0], vertices[b, 0], vertices[c, 0])
    c1 = max(vertices[a, 0], vertices[b, 0], vertices[c, 0])
    r0 = min(vertices[a, 1], vertices[b, 1], vertices[c, 1])
    r1 = max(vertices[a, 1], vertices[b, 1], vertices[c, 1])
    return c0, c1, r0, r1
