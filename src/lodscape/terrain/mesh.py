"""Tile meshes: a regular grid of heights per tile, with skirts; vertices relative to the centre.

Grid constants (indices) depend only on the segment count, so they are built once per size and
shared by every tile (STYLE 1, 7). Each grid cell is split along the diagonal from its north-west
to its south-east corner; `lodscape.terrain.pyramid` measures errors on the same triangulation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import geodetic_to_ecef, up_vector
from lodscape.geo.tiles import ORIGIN, merc_to_lonlat

__all__ = [
    "GRIDS",
    "TileMesh",
    "build_mesh",
    "grid_coordinates",
    "grid_indices",
    "ring_indices",
]

#: Segment counts a tile grid may have, coarsest first (grid k has 16·2^k segments). Finer detail
#: comes from smaller tiles, which adapt to the distance better than finer grids would.
GRIDS: tuple[int, ...] = (16, 32, 64)


@dataclass(frozen=True, eq=False)
class TileMesh:
    """Everything the renderer needs for one tile at one grid size; made off the GL thread."""

    key: int
    segments: int
    #: (N, 6) float32: x, y, z relative to ``center``; u, v; skirt flag (0 grid, 1 skirt).
    vertices: NDArray[np.float32]
    center: NDArray[np.float64]
    up: NDArray[np.float32]

    @property
    def triangles(self) -> int:
        return 2 * self.segments * self.segments + 8 * self.segments

    @property
    def nbytes(self) -> int:
        return int(self.vertices.nbytes)


@cache
def ring_indices(segments: int) -> NDArray[np.int64]:
    """Grid vertex numbers around the tile edge, clockwise from the north-west corner."""
    s = segments
    n = s + 1
    top = np.arange(0, s)
    right = np.arange(0, s) * n + s
    bottom = s * n + np.arange(s, 0, -1)
    left = np.arange(s, 0, -1) * n
    return np.concatenate([top, right, bottom, left])


@cache
def grid_indices(segments: int) -> NDArray[np.uint32]:
    """Triangle list for an (S+1)² grid followed by its 4·S skirt vertices (shared per S)."""
    if segments < 1:
        raise ValueError(f"Expected at least one segment, got {segments}")
    s = segments
    n = s + 1
    i, j = np.meshgrid(np.arange(s), np.arange(s), indexing="ij")
    a = (i * n + j).ravel()  # north-west corner of each cell
    b, c, d = a + 1, a + n, a + n + 1  # north-east, south-west, south-east
    # diagonal a-d in both triangles; counter-clockwise seen from above (north up, east right)
    cells = np.stack([a, c, d, a, d, b], axis=1).reshape(-1, 3)
    ring = ring_indices(s)
    nxt = np.roll(ring, -1)
    skirt = n * n + np.arange(4 * s)
    skirt_next = np.roll(skirt, -1)
    skirts = np.stack([ring, skirt, nxt, nxt, skirt, skirt_next], axis=1).reshape(-1, 3)
    out = np.concatenate([cells, skirts]).astype(np.uint32)
    out.setflags(write=False)
    return out


def grid_coordinates(
    z: int, x: int, y: int, segments: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Web Mercator x (columns) and y (rows, north first) of a tile's grid vertices.

    Computed from global vertex numbers in units that are exact powers of two, so a vertex shared
    by two tiles, of the same or different levels, gets bit-identical coordinates in both.
    """
    step = 2.0 * ORIGIN / float(1 << z) / segments
    cols = (x * segments + np.arange(segments + 1)).astype(np.float64)
    rows = (y * segments + np.arange(segments + 1)).astype(np.float64)
    return -ORIGIN + cols * step, ORIGIN - rows * step


def build_mesh(
    key: int,
    z: int,
    x: int,
    y: int,
    heights: NDArray[np.floating],
) -> TileMesh:
    """The tile's mesh from its (S+1)² heights (row 0 north), vertices relative to its centre."""
    s = heights.shape[0] - 1
    if heights.shape != (s + 1, s + 1) or s < 1:
        raise ValueError(f"Expected square (S+1)x(S+1) heights, got {heights.shape}")
    xs, ys = grid_coordinates(z, x, y, s)
    lon, lat = merc_to_lonlat(xs[None, :], ys[:, None])
    xyz = geodetic_to_ecef(lon, lat, heights.astype(np.float64)).reshape(-1, 3)
    mid = s // 2
    clon, clat = merc_to_lonlat((xs[0] + xs[-1]) / 2.0, (ys[0] + ys[-1]) / 2.0)
    center = geodetic_to_ecef(clon, clat, float(heights[mid, mid]))
    rel = xyz - center
    u, v = np.meshgrid(np.arange(s + 1) / s, np.arange(s + 1) / s)
    grid = np.column_stack([rel, u.ravel(), v.ravel(), np.zeros((s + 1) ** 2)])
    skirt = grid[ring_indices(s)].copy()
    skirt[:, 5] = 1.0
    vertices = np.concatenate([grid, skirt]).astype(np.float32)
    up = up_vector(clon, clat).astype(np.float32)
    return TileMesh(key, s, vertices, center, up)
