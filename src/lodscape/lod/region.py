"""The visible region (paper 003): the part of the ground the view frustum can reach.

Paper 003 intersects the view frustum with the mean ground plane and processes only the quadtree
nodes that meet the resulting quadrangle. A mean plane is not a bound (a peak above it or a valley
below it can be in view while its node lies outside the quadrangle), so lodscape intersects the
frustum with the *slab* between the lowest and highest ground the tiles can hold, in the local
east-north-up frame at the camera's nadir, and projects that polytope onto the ground plane: a
convex polygon (the quadrangle when the slab is thin and the far plane does not cut it). A tile
whose footprint misses the polygon cannot hold a visible point, so the selection drops it before
asking for its bounds.

What keeps the test conservative on an ellipsoid:
- the slab's floor is lowered by the Earth's drop over the far distance (s²/R, twice the sphere's
  s²/2R, with R the smallest radius of curvature), and heights are taken along the local normal,
  which tilts by at most s/R from the frame's up;
- a tile's footprint is the convex hull of its four corners, widened by the sag of its edges (an
  orthographic projection is a contraction, so an arc strays from its chord on the plane by no
  more than its 3D sag, R·Δλ²/8 for a Web Mercator tile Δλ radians wide) and by the sideways
  shift of its highest points (|h|·s/R);
- no region is made when the far distance reaches a quarter of the Earth's radius (the plane
  picture stops being worth having), nor for tiles above ``MIN_LEVEL`` (too large for a hull of
  four corners).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import (
    WGS84_A,
    WGS84_B,
    ecef_to_geodetic,
    enu_basis,
    geodetic_to_ecef,
)
from lodscape.geo.tiles import bounds_array, merc_to_lonlat
from lodscape.lod.camera import Camera

__all__ = ["MIN_LEVEL", "RegionView", "VisibleRegion", "region_view", "visible_region"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: The smallest radius of curvature of the ellipsoid (meridian, at the equator), metres.
R_MIN = WGS84_B * WGS84_B / WGS84_A
#: The largest (at the poles).
R_MAX = WGS84_A * WGS84_A / WGS84_B
#: Tiles of coarser levels are never dropped by the region.
MIN_LEVEL = 5
#: 12 edges of the frustum's 8 corners (near 0..3, far 4..7, in the same order).
_EDGES = np.array(
    [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
)


@dataclass(frozen=True, eq=False)
class VisibleRegion:
    """A convex polygon on the ground plane at the camera's nadir holding every visible ground
    point's projection (``polygon`` (K, 2), counter-clockwise, east/north metres; empty when the
    frustum misses the slab, so nothing on the ground is visible)."""

    lon: float
    lat: float
    polygon: F64
    #: Rows east, north, up of the frame (ECEF), and its origin (the nadir, ECEF).
    basis: F64
    origin: F64
    #: Slab bounds in the frame (metres along its up).
    floor: float
    ceiling: float
    #: Horizontal slack for heights seen off the frame's up, metres.
    slack: float

    @property
    def empty(self) -> bool:
        return len(self.polygon) == 0

    @property
    def area(self) -> float:
        """Square metres of the polygon (shoelace)."""
        if len(self.polygon) < 3:
            return 0.0
        x, y = self.polygon[:, 0], self.polygon[:, 1]
        return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))

    def lonlat(self) -> F64:
        """The polygon's corners as (lon, lat) degrees on the ellipsoid (for display)."""
        if self.empty:
            return np.zeros((0, 2))
        p = self.origin + self.polygon @ self.basis[:2]
        lon, lat, _ = ecef_to_geodetic(p)
        return np.stack([lon, lat], axis=1)

    def hits(self, z: int, x: I64, y: I64) -> NDArray[np.bool_]:
        """Whether each tile (z, x, y) may hold a visible point (False only when it cannot)."""
        if z < MIN_LEVEL:
            return np.ones(x.shape, dtype=bool)
        if self.empty:
            return np.zeros(x.shape, dtype=bool)
        left, bottom, right, top = bounds_array(z, x, y)
        cx = np.stack([left, right, right, left], axis=1)
        cy = np.stack([bottom, bottom, top, top], axis=1)
        lon, lat = merc_to_lonlat(cx, cy)
        q = (geodetic_to_ecef(lon, lat, 0.0) - self.origin) @ self.basis[:2].T  # (N, 4, 2)
        dlon = 2.0 * math.pi / (1 << z)
        margin = R_MAX * dlon * dlon / 8.0 + self.slack + 1.0
        p = self.polygon
        # the polygon's edges: outward normals (counter-clockwise order) and offsets
        e = np.roll(p, -1, axis=0) - p
        n = np.stack([e[:, 1], -e[:, 0]], axis=1)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        off = np.einsum("kj,kj->k", n, p)
        qmin = np.einsum("kj,nij->nki", n, q).min(axis=2)
        apart = (qmin - off > margin).any(axis=1)
        # the quad's edges, oriented outward whatever the corners' turn
        f = np.roll(q, -1, axis=1) - q
        m = np.stack([f[..., 1], -f[..., 0]], axis=2)
        qn = np.roll(q, -1, axis=1)
        area2 = (q[..., 0] * qn[..., 1] - q[..., 1] * qn[..., 0]).sum(axis=1)
        m *= np.where(area2 < 0.0, -1.0, 1.0)[:, None, None]
        m /= np.maximum(np.linalg.norm(m, axis=2, keepdims=True), 1e-300)
        qoff = np.einsum("nij,nij->ni", m, q)
        pmin = np.einsum("nij,kj->nik", m, p).min(axis=2)
        apart |= (pmin - qoff > margin).any(axis=1)
        keep: NDArray[np.bool_] = ~apart
        return keep


@dataclass(frozen=True, eq=False)
class RegionView:
    """What the visible regions of one camera share, whatever the slab: its frame and its
    frustum's corners in it (made once per frame; ``slab`` is then a few small numpy calls)."""

    lon: float
    lat: float
    basis: F64
    origin: F64
    #: (8, 3) the frustum's corners in the frame (near 0..3, far 4..7).
    corners: F64
    #: The farthest the frustum reaches from the eye, metres.
    reach: float

    def slab(self, min_h: float, max_h: float) -> VisibleRegion | None:
        """The region of ground heights ``min_h``..``max_h`` (metres above the ellipsoid);
        None when the frustum only grazes it or a bound is not finite."""
        if not (math.isfinite(min_h) and math.isfinite(max_h)):
            return None
        far = self.reach
        theta = far / R_MIN
        cos_t = math.cos(theta)
        hmax = max(abs(min_h), abs(max_h))
        ceiling = (max_h if max_h >= 0.0 else max_h * cos_t) + 1e-6 * far + 0.01
        floor = (min_h * cos_t if min_h >= 0.0 else min_h) - far * far / R_MIN
        floor -= 1e-6 * far + 0.01
        local = self.corners
        pts = [local[(local[:, 2] >= floor) & (local[:, 2] <= ceiling), :2]]
        a, b = local[_EDGES[:, 0]], local[_EDGES[:, 1]]
        dz = b[:, 2] - a[:, 2]
        for level in (floor, ceiling):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (level - a[:, 2]) / dz
            ok = (dz != 0.0) & (t >= 0.0) & (t <= 1.0)
            pts.append((a[ok] + t[ok, None] * (b[ok] - a[ok]))[:, :2])
        hull = _hull(np.concatenate(pts))
        if 0 < len(hull) < 3:
            # the frustum grazes the slab along an edge: nothing worth bounding
            return None
        slack = hmax * math.sin(min(theta, 1.0))
        return VisibleRegion(
            self.lon, self.lat, hull, self.basis, self.origin, floor, ceiling, slack
        )


def region_view(camera: Camera) -> RegionView | None:
    """The camera's frame for visible regions; None when none is worth making (the frustum
    reaching beyond R/4, or no clip set)."""
    if camera.near is None or camera.far is None:
        return None
    # the far plane's corners are the frustum's farthest points from the eye
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    reach = camera.far * math.sqrt(1.0 + ty * ty * (1.0 + camera.aspect * camera.aspect))
    if reach > R_MIN / 4.0:
        return None
    basis = enu_basis(camera.lon, camera.lat)
    # the frame's origin is the nadir; the camera stands alt above it along the frame's up
    local = _frustum_corners(camera) @ basis.T + np.array([0.0, 0.0, camera.alt])
    origin = geodetic_to_ecef(camera.lon, camera.lat, 0.0)
    return RegionView(camera.lon, camera.lat, basis, origin, local, reach)


def visible_region(camera: Camera, min_h: float, max_h: float) -> VisibleRegion | None:
    """The region of ground heights ``min_h``..``max_h`` (metres above the ellipsoid) that the
    camera's frustum can see; None when none is worth making (the frustum reaching beyond R/4,
    no clip set, or a frustum that only grazes the slab)."""
    view = region_view(camera)
    return None if view is None else view.slab(min_h, max_h)


def _frustum_corners(camera: Camera) -> F64:
    """The frustum's 8 corners relative to the camera (ECEF axes): near 0..3, then far."""
    near, far = camera.near, camera.far
    assert near is not None
    assert far is not None
    right, up, back = camera.rotation
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    tx = ty * camera.aspect
    sx = np.array([-1.0, 1.0, 1.0, -1.0])
    sy = np.array([-1.0, -1.0, 1.0, 1.0])
    out = []
    for d in (near, far):
        out.append(d * (-back + (sx * tx)[:, None] * right + (sy * ty)[:, None] * up))
    return np.concatenate(out)


def _hull(p: F64) -> F64:
    """Convex hull (Andrew's monotone chain), counter-clockwise, of a few dozen points."""
    if len(p) == 0:
        return np.zeros((0, 2))
    pts = sorted({(float(a), float(b)) for a, b in p})
    if len(pts) < 3:
        return np.array(pts)

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for q in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], q) <= 0.0:
            lower.pop()
        lower.append(q)
    upper: list[tuple[float, float]] = []
    for q in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], q) <= 0.0:
            upper.pop()
        upper.append(q)
    return np.array(lower[:-1] + upper[:-1])
