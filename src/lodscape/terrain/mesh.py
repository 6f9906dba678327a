"""Tile meshes: a regular grid of heights per tile, with skirts; vertices relative to the centre.

Grid constants (indices) depend only on the segment count, so they are built once per size and
shared by every tile (STYLE 1, 7). Each grid cell is split along the diagonal from its north-west
to its south-east corner; `lodscape.terrain.pyramid` measures errors on the same triangulation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.cones import patch_cones
from lodscape.geo.frames import geodetic_to_ecef, up_vector
from lodscape.geo.tiles import ORIGIN, Tile, lonlat_to_merc, merc_to_lonlat, xy_bounds

__all__ = [
    "GRIDS",
    "PATCH",
    "TileMesh",
    "adaptive_indices",
    "build_mesh",
    "cell_corners",
    "grid_coordinates",
    "grid_indices",
    "patches",
    "ring_indices",
    "tin_mesh",
    "vertex_normals",
    "without_holes",
]

#: Segment counts a tile grid may have, coarsest first (grid k has 16·2^k segments). Finer detail
#: comes from smaller tiles, which adapt to the distance better than finer grids would.
GRIDS: tuple[int, ...] = (16, 32, 64)


@dataclass(frozen=True, eq=False)
class TileMesh:
    """Everything the renderer needs for one tile's mesh; made off the GL thread.

    A regular grid (``segments`` > 0) shares its index buffer with every tile of that size; an
    irregular mesh (a TIN read from a tileset) brings its own ``indices`` and has segments 0.
    """

    key: int
    segments: int
    #: (N, 6) float32: x, y, z relative to ``center``; u, v; skirt flag (0 surface, 1 skirt).
    vertices: NDArray[np.float32]
    center: NDArray[np.float64]
    up: NDArray[np.float32]
    #: (M, 3) uint32 triangles of an irregular mesh, skirts included; None for a grid.
    indices: NDArray[np.uint32] | None = None
    #: (P, 10) each surface patch's normal cone and bounding sphere (``lodscape.geo.cones``; NaN
    #: rows: none); a grid's patches are runs of 2·PATCH² triangles, a TIN is one patch.
    cone: NDArray[np.float64] | None = None
    #: The (S+1)² heights a grid was built from (row 0 north), for the GPU terrain mode's
    #: height textures; None for an irregular mesh.
    heights: NDArray[np.float32] | None = None
    #: The GPU terrain mode's height texture and error table (``terrain.heightmap.HeightTile``),
    #: made by a worker; None: made at upload.
    height_tile: Any = None
    #: (N, 3) float32 per vertex (skirts included): how far to move it to lie on the next
    #: coarser surface (the grid at half the segments, the parent's vertices), for
    #: geomorphing; None: not morphed (an irregular or terrain-adaptive mesh).
    morph: NDArray[np.float32] | None = None

    @property
    def triangles(self) -> int:
        if self.indices is not None:
            return int(self.indices.shape[0])
        return 2 * self.segments * self.segments + 8 * self.segments

    @property
    def nbytes(self) -> int:
        own = 0 if self.indices is None else self.indices.nbytes
        if self.morph is not None:
            own += self.morph.nbytes
        if self.height_tile is not None:
            own += self.height_tile.heights.nbytes + self.height_tile.errors.nbytes
        return int(self.vertices.nbytes + own)


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


#: Cells a side of the patches a grid's triangles are ordered by (each patch's triangles are one
#: contiguous run of the index buffer, with its own normal cone, so patches can be skipped).
PATCH = 8


def patches(segments: int) -> int:
    """Patches of a grid of ``segments`` cells a side."""
    p = max(1, segments // PATCH)
    return p * p


@cache
def cell_corners(segments: int) -> NDArray[np.int64]:
    """North-west corner vertex of each cell, patch by patch (PATCH² cells each, row-major
    within a patch, patches row-major)."""
    s = segments
    n = s + 1
    b = min(PATCH, s)
    if s % b:
        b = s
    pi, pj, i, j = np.meshgrid(
        np.arange(s // b), np.arange(s // b), np.arange(b), np.arange(b), indexing="ij"
    )
    rows, cols = pi * b + i, pj * b + j
    out = (rows * n + cols).ravel()
    out.setflags(write=False)
    return out


@cache
def grid_indices(segments: int) -> NDArray[np.uint32]:
    """Triangle list for an (S+1)² grid followed by its 4·S skirt vertices (shared per S)."""
    if segments < 1:
        raise ValueError(f"Expected at least one segment, got {segments}")
    s = segments
    n = s + 1
    a = cell_corners(s)  # north-west corner of each cell, patch by patch
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


def adaptive_indices(diag: NDArray[np.bool_]) -> NDArray[np.uint32]:
    """Triangle list of an (S+1)² grid and its skirts with each cell split along its own
    diagonal: north-east to south-west where ``diag`` (S, S) is True (the terrain-adaptive split
    of paper 003, along the diagonal joining the two lowest corners), north-west to south-east
    elsewhere."""
    s = diag.shape[0]
    n = s + 1
    a = cell_corners(s)
    b, c, d = a + 1, a + n, a + n + 1
    # a cell's north-west corner (row r, column q) is vertex r·n + q
    flip = diag[a // n, a % n][:, None]
    # both counter-clockwise seen from above
    nwse = np.stack([a, c, d, a, d, b], axis=1)
    nesw = np.stack([a, c, b, b, c, d], axis=1)
    cells = np.where(flip, nesw, nwse).reshape(-1, 3)
    return np.concatenate([cells, grid_indices(s)[2 * s * s :]]).astype(np.uint32)


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
    *,
    adaptive: bool = False,
) -> TileMesh:
    """The tile's mesh from its (S+1)² heights (row 0 north), vertices relative to its centre;
    with ``adaptive``, each cell split along the diagonal joining its two lowest corners."""
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
    indices = None
    if adaptive:
        h = np.asarray(heights, np.float64)
        diag = (h[:-1, 1:] + h[1:, :-1]) < (h[:-1, :-1] + h[1:, 1:])
        indices = adaptive_indices(diag)
    surface = (grid_indices(s) if indices is None else indices)[: 2 * s * s]
    cone = patch_cones(vertices[: (s + 1) ** 2], surface.reshape(patches(s), -1, 3), up)
    morph = None if adaptive or s % 2 else morph_offsets(rel.reshape(s + 1, s + 1, 3))
    return TileMesh(
        key, s, vertices, center, up, indices, cone, np.asarray(heights, np.float32), morph=morph
    )


def morph_offsets(grid: NDArray[np.float64]) -> NDArray[np.float32]:
    """For an (S+1, S+1, 3) grid of positions (S even, cells split north-west to south-east),
    each vertex's move onto the grid of S/2 segments triangulated the same way (the parent's,
    where the tile's vertices are its own): 0 at the even vertices, to the midpoint of the coarse
    edge or diagonal under the others; skirt vertices follow their ring vertex. (N, 3) float32
    in the mesh's vertex order."""
    s = grid.shape[0] - 1
    g = grid
    coarse = g.copy()
    coarse[1::2, ::2] = (g[:-1:2, ::2] + g[2::2, ::2]) / 2.0  # on a north-south coarse edge
    coarse[::2, 1::2] = (g[::2, :-1:2] + g[::2, 2::2]) / 2.0  # on an east-west one
    coarse[1::2, 1::2] = (g[:-1:2, :-1:2] + g[2::2, 2::2]) / 2.0  # on a cell's diagonal
    d = (coarse - g).reshape(-1, 3)
    return np.concatenate([d, d[ring_indices(s)]]).astype(np.float32)


def tin_mesh(
    key: int,
    z: int,
    x: int,
    y: int,
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    heights: NDArray[np.floating],
    triangles: NDArray[np.integer],
    sides: Sequence[NDArray[np.integer]],
) -> TileMesh:
    """An irregular tile mesh (a TIN) with skirts along its four ``sides`` (west, south, east,
    north lists of the vertices on each, in any order): each side's vertices, in order along it,
    are joined to copies of themselves flagged as skirt, which the vertex shader lowers."""
    lon = np.asarray(lon, np.float64)
    lat = np.asarray(lat, np.float64)
    h = np.asarray(heights, np.float64)
    b = xy_bounds(Tile(x, y, z))
    xm, ym = lonlat_to_merc(lon, lat)
    # texture coordinates follow the Web Mercator tile (row 0 north), like the imagery
    u = (xm - b.left) / (b.right - b.left)
    v = (b.top - ym) / (b.top - b.bottom)
    clon, clat = merc_to_lonlat((b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0)
    center = geodetic_to_ecef(clon, clat, (float(h.min()) + float(h.max())) / 2.0)
    rel = geodetic_to_ecef(lon, lat, h) - center
    surface = np.column_stack([rel, u, v, np.zeros(lon.size)])
    rings, skirt_tris = [], []
    start = lon.size
    for k, side in enumerate(sides):
        idx = np.unique(np.asarray(side, dtype=np.int64))
        if idx.size < 2:
            continue
        along = lat if k in (0, 2) else lon
        idx = idx[np.argsort(along[idx], kind="stable")]
        ring = surface[idx].copy()
        ring[:, 5] = 1.0
        rings.append(ring)
        a, b2 = idx[:-1], idx[1:]
        sa = start + np.arange(idx.size - 1)
        skirt_tris.append(np.column_stack([a, sa, b2, b2, sa, sa + 1]).reshape(-1, 3))
        start += idx.size
    vertices = np.concatenate([surface, *rings]).astype(np.float32)
    tris = np.asarray(triangles, np.int64).reshape(-1, 3)
    indices = np.concatenate([tris, *skirt_tris])
    up = up_vector(clon, clat).astype(np.float32)
    cone = patch_cones(vertices[: lon.size], tris[None], up)
    return TileMesh(key, 0, vertices, center, up, indices.astype(np.uint32), cone)


def vertex_normals(
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    h: NDArray[np.float64],
    tris: NDArray[np.integer],
) -> NDArray[np.float64]:
    """Area-weighted vertex normals in ECEF, pointing away from the Earth."""
    p = geodetic_to_ecef(lon, lat, h).reshape(-1, 3)
    t = tris.astype(np.int64)
    face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    up = p[t[:, 0]]
    face *= np.where(np.einsum("ij,ij->i", face, up) < 0.0, -1.0, 1.0)[:, None]
    n = np.zeros_like(p)
    for c in range(3):
        np.add.at(n, t[:, c], face)
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    out: NDArray[np.float64] = n / np.where(norm > 0.0, norm, 1.0)
    return out


def without_holes(
    verts: NDArray[np.integer], tris: NDArray[np.integer], valid: NDArray[np.bool_]
) -> tuple[NDArray[np.int32], NDArray[np.int32]] | None:
    """A grid mesh (vertices as (column, row)) without the triangles that touch a grid point
    without data (``valid`` False) nor the vertices only they used, renumbered; None where no
    triangle is left. Meshed with the holes raised far up, a triangle over data and hole has a
    huge error and splits down to the grid, so what is left follows the data's rim within a
    cell."""
    keep = valid[verts[:, 1], verts[:, 0]][tris].all(axis=1)
    if not keep.any():
        return None
    used = np.unique(tris[keep])
    renumber = np.full(len(verts), -1, np.int64)
    renumber[used] = np.arange(used.size)
    return (
        np.asarray(verts[used], np.int32),
        renumber[tris[keep]].astype(np.int32),
    )
