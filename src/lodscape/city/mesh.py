"""Meshes of city objects in a local frame: buildings (walls and roofs, full and box levels of
detail) and the shared models of street objects. Pure numpy/shapely, no GL.

Coordinates are metres in the east-north-up frame of the city's origin (``Frame``), so a whole
city fits float32 to the millimetre; the renderer places the frame on the globe in float64.

Roofs are the lower envelope of a few planes over the footprint's smallest rotated rectangle
(gabled: two, hipped and pyramidal: four; flat: one), so every roof face is planar. Each face is
the footprint clipped to where its plane is the lowest, triangulated with holes (constrained
Delaunay), and the walls' top edges are cut where two planes meet: walls and roof share their
vertices, and the building is closed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from lodscape.city.osm import Building
from lodscape.geo.frames import enu_basis, geodetic_to_ecef

__all__ = ["MODELS", "Frame", "Geometry", "box_mesh", "building_mesh", "model_mesh"]

F64 = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Frame:
    """The east-north-up frame at a city's origin (lon, lat, height 0 on the ellipsoid)."""

    lon: float
    lat: float

    @cached_property
    def basis(self) -> F64:
        basis: F64 = enu_basis(self.lon, self.lat)
        return basis

    @cached_property
    def origin(self) -> F64:
        origin: F64 = geodetic_to_ecef(self.lon, self.lat, 0.0)
        return origin

    def local(self, lon: F64, lat: F64, h: F64 | float = 0.0) -> F64:
        """(…, 3) metres east, north, up of geodetic points (the Earth's curve included)."""
        out: F64 = (geodetic_to_ecef(lon, lat, h) - self.origin) @ self.basis.T
        return out


@dataclass(frozen=True, eq=False)
class Geometry:
    """Triangles of one material: positions and normals (N, 3) float32, texture coordinates
    (N, 2) float32 in metres (``materials`` says how far a texture repeats), triangles (M, 3)."""

    positions: NDArray[np.float32]
    normals: NDArray[np.float32]
    uvs: NDArray[np.float32]
    triangles: NDArray[np.uint32]

    @staticmethod
    def join(parts: list[Geometry]) -> Geometry:
        parts = [p for p in parts if len(p.triangles)]
        if not parts:
            return Geometry(
                np.zeros((0, 3), np.float32),
                np.zeros((0, 3), np.float32),
                np.zeros((0, 2), np.float32),
                np.zeros((0, 3), np.uint32),
            )
        offsets = np.cumsum([0] + [len(p.positions) for p in parts[:-1]])
        return Geometry(
            np.concatenate([p.positions for p in parts]),
            np.concatenate([p.normals for p in parts]),
            np.concatenate([p.uvs for p in parts]),
            np.concatenate(
                [p.triangles + np.uint32(o) for p, o in zip(parts, offsets, strict=True)]
            ),
        )

    def vertices(self) -> NDArray[np.float32]:
        """(N, 8) interleaved position, normal, texture coordinates: the vertex buffer."""
        return np.ascontiguousarray(np.hstack([self.positions, self.normals, self.uvs]))


def planar_uv(pos: F64, nrm: F64) -> F64:
    """Texture coordinates (metres) projected along each vertex's dominant axis: plan x, y on
    faces that look up or down, (along the face, up) on the others."""
    pos = np.asarray(pos, np.float64).reshape(-1, 3)
    nrm = np.asarray(nrm, np.float64).reshape(-1, 3)
    flat = np.abs(nrm[:, 2]) >= np.hypot(nrm[:, 0], nrm[:, 1])
    horiz = np.hypot(nrm[:, 0], nrm[:, 1])
    tx = np.where(horiz > 1e-9, -nrm[:, 1] / np.maximum(horiz, 1e-9), 1.0)
    ty = np.where(horiz > 1e-9, nrm[:, 0] / np.maximum(horiz, 1e-9), 0.0)
    along = pos[:, 0] * tx + pos[:, 1] * ty
    return np.where(
        flat[:, None],
        pos[:, :2],
        np.stack([along, pos[:, 2]], axis=1),
    )


def _geometry(pos: F64, nrm: F64, tri: NDArray[Any], uv: F64 | None = None) -> Geometry:
    if uv is None:
        uv = planar_uv(pos, nrm)
    return Geometry(
        np.asarray(pos, np.float32),
        np.asarray(nrm, np.float32),
        np.asarray(uv, np.float32).reshape(-1, 2),
        np.asarray(tri, np.uint32),
    )


# --- roofs -------------------------------------------------------------------------------


def _rectangle(poly: Polygon) -> tuple[F64, F64, F64, float, float]:
    """The smallest rotated rectangle: centre, unit long axis u, unit short axis v, half sides
    a >= b."""
    rect = shapely.minimum_rotated_rectangle(poly)
    c = np.asarray(rect.exterior.coords)[:4] if isinstance(rect, Polygon) else None
    if c is None or len(c) < 4:
        x0, y0, x1, y1 = poly.bounds
        c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)
    e1, e2 = c[1] - c[0], c[2] - c[1]
    l1, l2 = float(np.linalg.norm(e1)), float(np.linalg.norm(e2))
    if l1 < l2:
        e1, e2, l1, l2 = e2, e1, l2, l1
    centre = c.mean(axis=0)
    u = e1 / max(l1, 1e-9)
    v = np.array([-u[1], u[0]])
    return centre, u, v, l1 / 2.0, l2 / 2.0


def _planes(shape: str, a: float, b: float, rise: float) -> F64:
    """(K, 3) planes z = c + gu·u + gv·v (metres above the eaves) whose lower envelope is the
    roof, in the rectangle's frame."""
    if shape == "flat" or rise <= 0.0 or b <= 1e-6:
        return np.array([[0.0, 0.0, 0.0]])
    s = rise / b
    sides = [[rise, 0.0, -s], [rise, 0.0, s]]
    if shape == "gabled":
        return np.array(sides)
    if shape == "hipped":
        return np.array([*sides, [s * a, -s, 0.0], [s * a, s, 0.0]])
    # pyramidal: every face rises to the centre
    su = rise / max(a, 1e-6)
    return np.array([*sides, [rise, -su, 0.0], [rise, su, 0.0]])


def _roof_z(planes: F64, uv: F64) -> F64:
    z: F64 = (planes[:, 0] + uv @ planes[:, 1:].T).min(axis=-1)
    return np.maximum(z, 0.0)


def _clip(poly: F64, a: F64, c: float) -> F64:
    """Sutherland–Hodgman: the part of a convex polygon where a·p <= c."""
    if len(poly) == 0:
        return poly
    out = []
    d = poly @ a - c
    for i in range(len(poly)):
        p, q = poly[i], poly[(i + 1) % len(poly)]
        dp, dq = d[i], d[(i + 1) % len(poly)]
        if dp <= 0.0:
            out.append(p)
        if (dp < 0.0 < dq) or (dq < 0.0 < dp):
            out.append(p + (q - p) * (dp / (dp - dq)))
    return np.array(out) if out else np.zeros((0, 2))


def _cut_ring(ring: F64, planes: F64, to_uv: tuple[F64, F64, F64]) -> F64:
    """The ring's vertices with the points where the roof's lowest plane changes inserted."""
    if len(planes) == 1:
        return ring
    centre, u, v = to_uv
    out = []
    n = len(ring)
    for i in range(n):
        p, q = ring[i], ring[(i + 1) % n]
        out.append(p)
        pu = np.array([(p - centre) @ u, (p - centre) @ v])
        qu = np.array([(q - centre) @ u, (q - centre) @ v])
        zp = planes[:, 0] + planes[:, 1:] @ pu
        zq = planes[:, 0] + planes[:, 1:] @ qu
        ts = []
        for k in range(len(planes)):
            for j in range(k + 1, len(planes)):
                dp, dq = zp[k] - zp[j], zq[k] - zq[j]
                if (dp < 0.0 < dq) or (dq < 0.0 < dp):
                    t = dp / (dp - dq)
                    if 1e-6 < t < 1.0 - 1e-6:
                        z = zp + t * (zq - zp)
                        # only where these two are the lowest (a real fold of the roof)
                        if abs(z[k] - z.min()) < 1e-6 * (1.0 + abs(z.min())):
                            ts.append(t)
        for t in sorted(ts):
            out.append(p + t * (q - p))
    return np.array(out)


def building_mesh(b: Building, xy: Polygon, base: float) -> dict[str, Geometry]:
    """Full level of detail: walls and roof by material. ``xy`` is the footprint in the local
    frame (metres) and ``base`` the ground under it (local z)."""
    centre, u, v, a, bb = _rectangle(xy)
    eave = base + b.height - b.roof_height
    bottom = base + b.min_height
    planes = _planes(b.roof_shape, a, bb, b.roof_height)
    if len(planes) == 1:
        eave = base + b.height

    axes = (centre, u, v)
    walls = _walls(xy, planes, axes, eave, bottom)
    roof = _roof(xy, planes, axes, (a, bb), eave)
    return {b.wall_material: walls, b.roof_material: roof}


def _uv(p: F64, axes: tuple[F64, F64, F64]) -> F64:
    """Points in the footprint rectangle's own axes (from its centre)."""
    centre, u, v = axes
    d = p - centre
    out: F64 = np.stack([d @ u, d @ v], axis=-1)
    return out


def _walls(
    xy: Polygon, planes: F64, axes: tuple[F64, F64, F64], eave: float, bottom: float
) -> Geometry:
    """The walls from ``bottom`` up to the roof: each ring (holes included) cut where the roof
    folds, one quad per edge."""
    centre, u, v = axes
    wpos, wnrm, wuv, wtri = [], [], [], []
    count = 0
    rings = [np.asarray(xy.exterior.coords)[:-1]] + [
        np.asarray(r.coords)[:-1] for r in xy.interiors
    ]
    for ring in rings:
        ring = _cut_ring(ring, planes, (centre, u, v))
        top = eave + _roof_z(planes, _uv(ring, axes))
        nxt = np.roll(np.arange(len(ring)), -1)
        p0, p1 = ring, ring[nxt]
        edge = p1 - p0
        length = np.linalg.norm(edge, axis=1)
        # texture coordinates run on around the ring, so windows continue round corners
        s0 = np.concatenate([[0.0], np.cumsum(length)[:-1]])
        keep = length > 1e-6
        p0, p1, t0, t1, edge = p0[keep], p1[keep], top[keep], top[nxt][keep], edge[keep]
        s0, s1 = s0[keep], s0[keep] + length[keep]
        m = len(p0)
        if m == 0:
            continue
        normal = np.stack([edge[:, 1], -edge[:, 0], np.zeros(m)], axis=1)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        quad = np.stack(
            [
                np.column_stack([p0, np.full(m, bottom)]),
                np.column_stack([p1, np.full(m, bottom)]),
                np.column_stack([p1, t1]),
                np.column_stack([p0, t0]),
            ],
            axis=1,
        )
        wpos.append(quad.reshape(-1, 3))
        wnrm.append(np.repeat(normal, 4, axis=0))
        wuv.append(
            np.stack(
                [
                    np.column_stack([s0, np.zeros(m)]),
                    np.column_stack([s1, np.zeros(m)]),
                    np.column_stack([s1, t1 - bottom]),
                    np.column_stack([s0, t0 - bottom]),
                ],
                axis=1,
            ).reshape(-1, 2)
        )
        base_i = count + 4 * np.arange(m)[:, None]
        wtri.append((base_i + np.array([[0, 1, 2], [0, 2, 3]]).reshape(1, 6)).reshape(-1, 3))
        count += 4 * m
    return (
        _geometry(
            np.concatenate(wpos), np.concatenate(wnrm), np.concatenate(wtri), np.concatenate(wuv)
        )
        if wpos
        else Geometry.join([])
    )


def _roof(
    xy: Polygon, planes: F64, axes: tuple[F64, F64, F64], half: tuple[float, float], eave: float
) -> Geometry:
    """The roof: each plane over the part of the footprint where it is the lowest."""
    centre, u, v = axes
    a, bb = half
    rect = np.array(
        [
            centre + sa * (a * 1.01 + 0.01) * u + sb * (bb * 1.01 + 0.01) * v
            for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))
        ]
    )
    parts = []
    for k in range(len(planes)):
        region = rect
        for j in range(len(planes)):
            if j == k:
                continue
            # plane_k <= plane_j  ⇔  (g_k − g_j)·uv <= c_j − c_k, in xy: uv = M·(p − centre)
            g = planes[k, 1:] - planes[j, 1:]
            axis = g[0] * u + g[1] * v
            region = _clip(region, axis, planes[j, 0] - planes[k, 0] + axis @ centre)
        if len(region) < 3:
            continue
        piece = shapely.intersection(xy, Polygon(region))
        tris = shapely.constrained_delaunay_triangles(piece)
        coords = [np.asarray(t.exterior.coords)[:3] for t in getattr(tris, "geoms", [])]
        if not coords:
            continue
        t = np.stack(coords)  # (T, 3, 2)
        # counter-clockwise seen from above, so the normal points up
        cross = (t[:, 1, 0] - t[:, 0, 0]) * (t[:, 2, 1] - t[:, 0, 1]) - (
            t[:, 1, 1] - t[:, 0, 1]
        ) * (t[:, 2, 0] - t[:, 0, 0])
        t = np.where((cross < 0.0)[:, None, None], t[:, ::-1], t)
        t = t[np.abs(cross) > 1e-9]
        if not len(t):
            continue
        flat = t.reshape(-1, 2)
        z = eave + _roof_z(planes, _uv(flat, axes))
        gu, gv = planes[k, 1], planes[k, 2]
        grad = gu * u + gv * v
        n = np.array([-grad[0], -grad[1], 1.0])
        n /= np.linalg.norm(n)
        parts.append(
            _geometry(
                np.column_stack([flat, z]),
                np.tile(n, (len(flat), 1)),
                np.arange(len(flat)).reshape(-1, 3),
            )
        )
    return Geometry.join(parts)


def box_mesh(b: Building, xy: Polygon, base: float) -> dict[str, Geometry]:
    """The simplified level: the smallest rotated rectangle raised to the roof's mid height
    (five faces, ten triangles): walls in the wall material, the top in the roof's."""
    centre, u, v, a, bb = _rectangle(xy)
    top = base + b.height - 0.5 * b.roof_height
    bottom = base + b.min_height
    corners = np.array(
        [centre + sa * a * u + sb * bb * v for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    )
    pos: list[Any] = []
    nrm: list[Any] = []
    uvs: list[Any] = []
    tri: list[Any] = []
    s = 0.0
    for i in range(4):
        p0, p1 = corners[i], corners[(i + 1) % 4]
        e = p1 - p0
        length = float(np.linalg.norm(e))
        n = np.array([e[1], -e[0], 0.0])
        n /= max(length, 1e-9)
        pos += [[*p0, bottom], [*p1, bottom], [*p1, top], [*p0, top]]
        nrm += [list(n)] * 4
        h = top - bottom
        uvs += [[s, 0.0], [s + length, 0.0], [s + length, h], [s, h]]
        s += length
        tri += [[4 * i, 4 * i + 1, 4 * i + 2], [4 * i, 4 * i + 2, 4 * i + 3]]
    walls = _geometry(np.array(pos), np.array(nrm), np.array(tri), np.array(uvs))
    top_pos = np.array([[*c, top] for c in corners])
    roof = _geometry(top_pos, np.tile([0.0, 0.0, 1.0], (4, 1)), np.array([[0, 1, 2], [0, 2, 3]]))
    if b.wall_material == b.roof_material:
        return {b.wall_material: Geometry.join([walls, roof])}
    return {b.wall_material: walls, b.roof_material: roof}


# --- shared models of street objects ---------------------------------------------------------


def _prism(r: float, z0: float, z1: float, sides: int) -> tuple[F64, F64, F64]:
    ang = np.linspace(0.0, 2.0 * math.pi, sides, endpoint=False)
    ring = np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
    pos: list[Any] = []
    nrm: list[Any] = []
    tri: list[Any] = []
    for i in range(sides):
        p0, p1 = ring[i], ring[(i + 1) % sides]
        mid = (p0 + p1) / 2.0
        n = np.array([mid[0], mid[1], 0.0]) / max(float(np.linalg.norm(mid)), 1e-9)
        k = len(pos)
        pos += [[*p0, z0], [*p1, z0], [*p1, z1], [*p0, z1]]
        nrm += [list(n)] * 4
        tri += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    k = len(pos)
    pos += [[0.0, 0.0, z1]] + [[*p, z1] for p in ring]
    nrm += [[0.0, 0.0, 1.0]] * (sides + 1)
    tri += [[k, k + 1 + i, k + 1 + (i + 1) % sides] for i in range(sides)]
    return np.array(pos), np.array(nrm), np.array(tri)


def _box(x0: float, y0: float, z0: float, x1: float, y1: float, z1: float) -> tuple[F64, F64, F64]:
    c = np.array([[x, y, z] for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)], float)
    faces = [
        ([0, 1, 3, 2], [0, 0, -1]),
        ([4, 6, 7, 5], [0, 0, 1]),
        ([0, 4, 5, 1], [0, -1, 0]),
        ([2, 3, 7, 6], [0, 1, 0]),
        ([0, 2, 6, 4], [-1, 0, 0]),
        ([1, 5, 7, 3], [1, 0, 0]),
    ]
    pos: list[Any] = []
    nrm: list[Any] = []
    tri: list[Any] = []
    for idx, n in faces:
        k = len(pos)
        pos += [c[i] for i in idx]
        nrm += [list(n)] * 4
        tri += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    return np.array(pos), np.array(nrm, float), np.array(tri)


def _sphere(r: float, z: float, levels: int) -> tuple[F64, F64, F64]:
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        float,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ]
    )
    for _ in range(levels):
        v, f = _subdivide(v, f)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    return n * r + np.array([0.0, 0.0, z]), n, f


def _subdivide(v: F64, f: NDArray[np.int64]) -> tuple[F64, NDArray[np.int64]]:
    """Each triangle into four, new vertices at the edges' midpoints (shared)."""
    verts = [tuple(p) for p in v]
    index = {p: i for i, p in enumerate(verts)}
    out = []

    def mid(i: int, j: int) -> int:
        p = tuple((v[i] + v[j]) / 2.0)
        if p not in index:
            index[p] = len(verts)
            verts.append(p)
        return index[p]

    for a, b, c in f:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        out += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.array(verts), np.array(out)


def _model(parts: dict[str, list[tuple[F64, F64, F64]]]) -> dict[str, Geometry]:
    return {m: Geometry.join([_geometry(*p) for p in ps]) for m, ps in parts.items()}


#: Shared models (metres, z up, base at 0) by street object kind, parts by material.
MODELS: dict[str, dict[str, Geometry]] = {
    "tree": _model({"bark": [_prism(0.18, 0.0, 3.0, 6)], "foliage": [_sphere(2.4, 4.6, 1)]}),
    "street_lamp": _model(
        {
            "metal": [_prism(0.08, 0.0, 6.0, 6), _box(-0.1, -0.6, 5.8, 0.1, 0.1, 6.05)],
            "lamp": [_box(-0.15, -0.7, 5.6, 0.15, -0.4, 5.8)],
        }
    ),
    "bench": _model(
        {
            "wood": [
                _box(-0.9, -0.25, 0.42, 0.9, 0.2, 0.47),
                _box(-0.9, 0.2, 0.47, 0.9, 0.25, 0.9),
            ],
            "metal": [
                _box(-0.85, -0.25, 0.0, -0.8, 0.25, 0.42),
                _box(0.8, -0.25, 0.0, 0.85, 0.25, 0.42),
            ],
        }
    ),
}


def model_mesh(kind: str) -> dict[str, Geometry]:
    return MODELS[kind]
