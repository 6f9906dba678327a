"""Tiles as height textures for hardware tessellation (paper 001's GPU terrain): what the GPU
terrain mode uploads instead of a mesh, made off the GL thread. Pure numpy.

A tile of S cells a side is drawn as P×P quad patches of C = min(S, 16) cells each (P = S / C),
plus a ring of skirt patches. The tessellator splits each patch edge into 1, 2, 4 … C segments,
so every vertex lands on a grid point of the height texture: a patch at level l samples the grid
at a stride of C / l, and ``error_table`` measures, for every patch and every patch edge, how far
that sampling strays from the full grid (metres), so the control shader can keep the projected
error under its budget (the screen-space error of paper 000, per patch).

Positions: each tile has a frame at the ellipsoid under its centre (east, north, up), and
``tile_frame`` gives the grid points on the ellipsoid (height 0) and their normals in it. A
vertex is ``base + h · normal``, bilinear between grid points, so at the grid points it is the
exact geodetic position. The frame depends only on the tile's row (z, y) and grid size: the
tiles of one row are the same shape turned about the Earth's axis, so one frame serves them all.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import enu_basis, geodetic_to_ecef, up_vector
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.terrain.mesh import TileMesh, grid_coordinates

__all__ = [
    "LEVELS",
    "PATCH_CELLS",
    "HeightTile",
    "error_table",
    "height_tile",
    "patch_layout",
    "tile_frame",
]

#: Cells a side of a tessellation patch (the finest level splits each patch edge this often).
PATCH_CELLS = 16
#: Columns of the error table: errors at 1, 2, 4 … PATCH_CELLS segments, then min and max height.
LEVELS = 5

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


def patch_layout(segments: int) -> tuple[int, int]:
    """(patches a side P, cells a patch side C) for a grid of ``segments`` cells a side."""
    c = min(PATCH_CELLS, segments)
    if segments % c:
        c = segments
    return segments // c, c


@dataclass(frozen=True, eq=False)
class HeightTile:
    """What the GPU terrain mode uploads for one tile."""

    key: int
    z: int
    x: int
    y: int
    segments: int
    #: (S+1, S+1) float32 metres, row 0 north.
    heights: F32
    #: (rows, LEVELS + 2) float32: per patch (P² rows), per horizontal patch edge (P·(P+1)),
    #: per vertical patch edge (P·(P+1)): the error at each level, then min and max height.
    errors: F32
    #: The tile's frame: origin (ECEF, on the ellipsoid under the centre) and its east, north,
    #: up rows.
    origin: F64
    basis: F64
    #: The ellipsoid normal at the centre (ECEF): where skirts hang, and for back-face culling.
    up: F32
    #: Normal cones of the tile's patches (``lodscape.geo.cones``), as the mesh had them.
    cone: F64 | None = None

    @property
    def nbytes(self) -> int:
        """GPU bytes: the height texture with its mipmaps, and the error table."""
        return int(self.heights.nbytes * 4 // 3 + self.errors.nbytes)


@lru_cache(maxsize=512)
def tile_frame(z: int, y: int, segments: int) -> tuple[F32, F64, F64]:
    """The grid of a tile row on the ellipsoid: (S+1, S+1, 8) float32 (base position east,
    north, up in metres, 0; normal east, north, up, 0) in the frame of the tile at x = 0, and
    that tile's frame (origin, basis). Read-only; shared by every tile of the row."""
    xs, ys = grid_coordinates(z, 0, y, segments)
    lon, lat = merc_to_lonlat(xs[None, :], ys[:, None])
    clon, clat = merc_to_lonlat((xs[0] + xs[-1]) / 2.0, (ys[0] + ys[-1]) / 2.0)
    origin = geodetic_to_ecef(float(clon), float(clat), 0.0)
    basis = enu_basis(float(clon), float(clat))
    lon_b, lat_b = np.broadcast_arrays(lon, lat)
    base = (geodetic_to_ecef(lon_b, lat_b, np.zeros(lon_b.shape)) - origin) @ basis.T
    normal = up_vector(lon_b, lat_b) @ basis.T
    out = np.zeros((segments + 1, segments + 1, 8), np.float32)
    out[..., :3] = base
    out[..., 4:7] = normal
    out.setflags(write=False)
    return out, np.asarray(origin, np.float64), np.asarray(basis, np.float64)


def tile_origin(z: int, x: int, y: int, segments: int) -> tuple[F64, F64]:
    """Origin and basis of tile (z, x, y)'s frame: its row's frame turned to its longitude."""
    xs, ys = grid_coordinates(z, x, y, segments)
    clon, clat = merc_to_lonlat((xs[0] + xs[-1]) / 2.0, (ys[0] + ys[-1]) / 2.0)
    origin = np.asarray(geodetic_to_ecef(float(clon), float(clat), 0.0), np.float64)
    basis = np.asarray(enu_basis(float(clon), float(clat)), np.float64)
    return origin, basis


def _upsampled(h: F64, k: int) -> F64:
    """The grid sampled every ``k`` points and filled back bilinearly (what a patch level whose
    vertices are ``k`` cells apart draws, up to the split of its quads)."""
    n = h.shape[0]
    idx = np.arange(n)
    c0 = (idx // k) * k
    c1 = np.minimum(c0 + k, n - 1)
    f = (idx - c0) / k
    fy, fx = f[:, None], f[None, :]
    top = h[np.ix_(c0, c0)] * (1 - fx) + h[np.ix_(c0, c1)] * fx
    bottom = h[np.ix_(c1, c0)] * (1 - fx) + h[np.ix_(c1, c1)] * fx
    out: F64 = top * (1 - fy) + bottom * fy
    return out


def error_table(heights: NDArray[np.floating]) -> F32:
    """Per patch and patch edge, the vertical error (metres) of each tessellation level against
    the full grid, and the min and max height (see ``HeightTile.errors``)."""
    h = np.asarray(heights, np.float64)
    s = h.shape[0] - 1
    p, c = patch_layout(s)
    rows_p, rows_e = p * p, p * (p + 1)
    out = np.zeros((rows_p + 2 * rows_e, LEVELS + 2), np.float32)
    for i in range(LEVELS):
        segs = 1 << i
        if segs > c:
            out[:, i] = 0.0
            continue
        k = c // segs
        diff = np.abs(_upsampled(h, k) - h)
        if segs < c:
            # the tessellator splits each quad in two triangles: up to half the quad's twist
            # more than the bilinear fill (none at the finest level: its vertices are the grid)
            idx = np.arange(0, s + 1, k)
            q = h[np.ix_(idx, idx)]
            twist = np.abs(q[:-1, :-1] + q[1:, 1:] - q[:-1, 1:] - q[1:, :-1]) / 2.0
            tw = twist.reshape(p, c // k, p, c // k).max(axis=(1, 3))
        else:
            tw = np.zeros((p, p))
        # a patch: the cells inside it
        inner = diff[:s, :s].reshape(p, c, p, c).max(axis=(1, 3)) + tw
        out[:rows_p, i] = inner.ravel()
        # its edges: the grid lines between patches, segment by segment
        lines = diff[::c, :s].reshape(p + 1, p, c).max(axis=2)  # horizontal, row-major
        out[rows_p : rows_p + rows_e, i] = lines.ravel()
        cols = diff[:s, ::c].T.reshape(p + 1, p, c).max(axis=2)  # vertical, by column
        out[rows_p + rows_e :, i] = cols.ravel()
    # a finer level never strays further than a coarser one (whichever level a rule picks at
    # or above the one the error allows, the error stays within it)
    out[:, :LEVELS] = np.maximum.accumulate(out[:, LEVELS - 1 :: -1], axis=1)[:, ::-1]
    # heights: patches, horizontal edges, vertical edges
    blocks = h[:s, :s].reshape(p, c, p, c)
    lo_p = np.minimum(blocks.min(axis=(1, 3)), _corner_ext(h, p, c, np.min))
    hi_p = np.maximum(blocks.max(axis=(1, 3)), _corner_ext(h, p, c, np.max))
    lo_h = _line_ext(h[::c, :], p, c, np.min)
    hi_h = _line_ext(h[::c, :], p, c, np.max)
    lo_v = _line_ext(h[:, ::c].T, p, c, np.min)
    hi_v = _line_ext(h[:, ::c].T, p, c, np.max)
    out[:, LEVELS] = np.concatenate([lo_p.ravel(), lo_h.ravel(), lo_v.ravel()])
    out[:, LEVELS + 1] = np.concatenate([hi_p.ravel(), hi_h.ravel(), hi_v.ravel()])
    return out


def _line_ext(lines: F64, p: int, c: int, fn: object) -> F64:
    """Per line and segment of ``c`` cells (both ends included), ``fn`` (np.min or np.max)."""
    n = lines.shape[0]
    body = lines[:, : p * c].reshape(n, p, c)
    ends = lines[:, c::c][:, :p]
    out: F64 = (
        np.minimum(body.min(axis=2), ends) if fn is np.min else np.maximum(body.max(axis=2), ends)
    )
    return out


def _corner_ext(h: F64, p: int, c: int, fn: object) -> F64:
    """``fn`` (np.min or np.max) over each patch's last row and column (outside the [:s, :s]
    blocks)."""
    s = p * c
    right = h[:s, c::c].reshape(p, c, p)
    bottom = h[c::c, :s].reshape(p, p, c)
    corner = h[c::c, c::c]
    if fn is np.min:
        out: F64 = np.minimum(np.minimum(right.min(axis=1), bottom.min(axis=2)), corner)
    else:
        out = np.maximum(np.maximum(right.max(axis=1), bottom.max(axis=2)), corner)
    return out


def height_tile(mesh: TileMesh, z: int, x: int, y: int) -> HeightTile:
    """A tile's height texture and error table from its mesh: the grid heights it was built
    from, or for an irregular mesh (a TIN from a tileset) its surface sampled on a 64-cell
    grid."""
    heights = mesh.heights
    if heights is None:
        heights = _sample_tin(mesh, 64)
    heights = np.ascontiguousarray(heights, np.float32)
    s = heights.shape[0] - 1
    origin, basis = tile_origin(z, x, y, s)
    return HeightTile(
        mesh.key,
        z,
        x,
        y,
        s,
        heights,
        error_table(heights),
        origin,
        basis,
        np.asarray(mesh.up, np.float32),
        mesh.cone,
    )


def _sample_tin(mesh: TileMesh, segments: int) -> F32:
    """Heights of an irregular mesh on a regular grid, linear between its vertices (by the
    mesh's texture coordinates, the tile's unit square)."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    from lodscape.geo.frames import ecef_to_geodetic

    verts = np.asarray(mesh.vertices, np.float64)
    surface = verts[:, 5] == 0.0
    pts = np.asarray(mesh.center, np.float64) + verts[surface, :3]
    _, _, h = ecef_to_geodetic(pts)
    uv = verts[surface, 3:5]
    g = np.linspace(0.0, 1.0, segments + 1)
    gu, gv = np.meshgrid(g, g)
    out = LinearNDInterpolator(uv, h)(gu, gv)
    gaps = ~np.isfinite(out)
    if gaps.any():
        # grid points a hair outside the hull (rounding at the edges): the nearest vertex
        out[gaps] = NearestNDInterpolator(uv, h)(gu[gaps], gv[gaps])
    return np.asarray(out, np.float32)
