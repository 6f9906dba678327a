"""The octahedral Quaternary Triangular Mesh (Dutton's QTM, paper 002) on the WGS84 ellipsoid.

The octahedron's vertices are the poles and four points of the equator (longitudes 0, 90, 180
and -90). Its eight faces are the octants, numbered 0–3 in the north (longitudes 0..90, 90..180,
-180..-90, -90..0) and 4–7 below them in the south. Each facet splits in four at the midpoints
of its edges; a midpoint's latitude and longitude are the averages of its edge ends' (Dutton),
where a pole, whose longitude means nothing, takes the other end's. Child 0 is the central
facet, child k (1..3) the one at the parent's vertex k-1. Level 1 is the octahedron (8 facets),
level n has 8·4^(n-1).

A facet's address is its octant and one digit 0–3 per level below the first; as a number,
``id = octant·4^(n-1) + digits`` in base 4, so a facet's children are ``4·id + d``. In the
plane of longitude and latitude every facet is a triangle (a polar facet's pole stands for the
segment of the pole over its longitudes), and the four children tile their parent exactly, so
finding the facet of a point is one barycentric test per level. Facets of one octant never
straddle the antimeridian: the eastern octants end at 180, the western start at -180, and
vertices are compared with -180 folded onto 180.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "OCTANT_LON",
    "children",
    "facet_count",
    "facets",
    "locate",
    "neighbours",
    "parent",
    "vertex_keys",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: West longitude of each octant (0–3 north, 4–7 south).
OCTANT_LON = np.array([0.0, 90.0, -180.0, -90.0, 0.0, 90.0, -180.0, -90.0])


def facet_count(level: int) -> int:
    """Facets at ``level`` (1: the octahedron's 8)."""
    if level < 1:
        raise ValueError(f"QTM levels start at 1, got {level}")
    return int(8 * 4 ** (level - 1))


def parent(ids: ArrayLike) -> I64:
    """Ids of the parents (one level up) of facets ``ids``."""
    return np.asarray(ids, np.int64) >> 2


def children(ids: ArrayLike) -> I64:
    """(F, 4) ids of each facet's children (one level down): central first."""
    ids = np.asarray(ids, np.int64)
    out: I64 = (ids[..., None] << 2) + np.arange(4)
    return out


def _octants() -> F64:
    """(8, 3, 2) lat/lon of the octahedron's faces: pole, west, east on the equator."""
    out = np.zeros((8, 3, 2))
    for o in range(8):
        w = OCTANT_LON[o]
        out[o, 0] = (90.0 if o < 4 else -90.0, w)
        out[o, 1] = (0.0, w)
        out[o, 2] = (0.0, w + 90.0)
    return out


def _mid(a: F64, b: F64) -> F64:
    """Dutton's midpoints: lat and lon averaged; a pole takes the other end's longitude."""
    lat = (a[..., 0] + b[..., 0]) / 2.0
    pole_a = np.abs(a[..., 0]) == 90.0
    pole_b = np.abs(b[..., 0]) == 90.0
    lon = np.where(pole_a, b[..., 1], np.where(pole_b, a[..., 1], (a[..., 1] + b[..., 1]) / 2.0))
    return np.stack([lat, lon], axis=-1)


def split(v: F64) -> F64:
    """(F, 3, 2) facets to (F, 4, 3, 2) children: central, then at vertices 0, 1, 2."""
    v0, v1, v2 = v[:, 0], v[:, 1], v[:, 2]
    m01, m12, m20 = _mid(v0, v1), _mid(v1, v2), _mid(v2, v0)
    return np.stack(
        [
            np.stack([m12, m20, m01], axis=1),
            np.stack([v0, m01, m20], axis=1),
            np.stack([m01, v1, m12], axis=1),
            np.stack([m20, m12, v2], axis=1),
        ],
        axis=1,
    )


def facets(level: int) -> F64:
    """(facet_count(level), 3, 2) lat/lon degrees of every facet's vertices, in id order."""
    v = _octants()
    for _ in range(level - 1):
        v = split(v).reshape(-1, 3, 2)
    out: F64 = v
    return out


def facet_vertices(level: int, ids: ArrayLike) -> F64:
    """(F, 3, 2) vertices of facets ``ids`` at ``level``, by descending their addresses."""
    ids = np.asarray(ids, np.int64)
    v: F64 = _octants()[ids >> (2 * (level - 1))]
    for k in range(level - 2, -1, -1):
        digit = (ids >> (2 * k)) & 3
        v = split(v)[np.arange(len(ids)), digit]
    return v


def vertex_keys(v: F64) -> NDArray[np.int64]:
    """Integer keys of vertices (..., 2): equal for the same point (poles at any longitude, and
    -180 folded onto 180), at a nano-degree."""
    lat = np.round(v[..., 0] * 1e9).astype(np.int64)
    lon = np.where(np.abs(v[..., 0]) == 90.0, 0.0, v[..., 1])
    lon = np.where(lon == -180.0, 180.0, lon)
    lonk = np.round(lon * 1e9).astype(np.int64)
    return lat * np.int64(400_000_000_000) + lonk


def neighbours(level: int) -> I64:
    """(F, 3) the facet across each edge of every facet at ``level`` (edge k is the one
    opposite vertex k)."""
    v = facets(level)
    keys = vertex_keys(v)  # (F, 3)
    a = keys[:, [1, 2, 0]]
    b = keys[:, [2, 0, 1]]
    lo, hi = np.minimum(a, b).ravel(), np.maximum(a, b).ravel()
    order = np.lexsort((hi, lo))
    lo_s, hi_s = lo[order], hi[order]
    same = (lo_s[1:] == lo_s[:-1]) & (hi_s[1:] == hi_s[:-1])
    out = np.full(lo.size, -1, np.int64)
    i = np.nonzero(same)[0]
    out[order[i]] = order[i + 1] // 3
    out[order[i + 1]] = order[i] // 3
    return out.reshape(-1, 3)


def _octant_of(lat: F64, lon: F64) -> I64:
    lon = np.where(lon >= 180.0, lon - 360.0, lon)
    q = np.floor((lon + 180.0) / 90.0).astype(np.int64) % 4  # 0: -180..-90 … 3: 90..180
    north = np.array([2, 3, 0, 1])[q]
    return np.where(lat >= 0.0, north, north + 4)


def locate(lat: ArrayLike, lon: ArrayLike, level: int) -> I64:
    """Ids of the facets at ``level`` holding points (lat, lon degrees); on an edge, either."""
    lat = np.asarray(lat, np.float64).ravel()
    lon = np.asarray(lon, np.float64).ravel()
    lon = np.where(lon >= 180.0, lon - 360.0, lon)
    ids = _octant_of(lat, lon)
    v = _octants()[ids]
    # the western octants hold -180: a point at 180 is at their west edge
    for _ in range(level - 1):
        kids = split(v)  # (P, 4, 3, 2)
        x = np.where(np.abs(kids[..., 0]) == 90.0, lon[:, None, None], kids[..., 1])
        y = kids[..., 0]
        ax, ay = x[..., 0], y[..., 0]
        bx, by = x[..., 1], y[..., 1]
        cx, cy = x[..., 2], y[..., 2]
        det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
        px, py = lon[:, None], lat[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            wa = ((by - cy) * (px - cx) + (cx - bx) * (py - cy)) / det
            wb = ((cy - ay) * (px - cx) + (ax - cx) * (py - cy)) / det
        wc = 1.0 - wa - wb
        score = np.minimum(np.minimum(wa, wb), wc)
        score = np.where(np.isfinite(score), score, -np.inf)
        d = np.argmax(score, axis=1)
        ids = ids * 4 + d
        v = kids[np.arange(len(ids)), d]
    return ids
