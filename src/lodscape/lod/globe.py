"""The whole globe on the QTM grid (paper 002): which facets to draw from a viewpoint, and their
mesh without cracks. Pure numpy.

Two selections:
- ``thinning``, the paper's: every facet at a base level, except the blocks (facets of a block
  level) nearest the viewpoint, the "thinning area", drawn ``extra`` levels finer;
- ``by_error``, beyond the paper: the spine's rule in QTM form, level by level from the
  octahedron, a facet split while its geometric error (its flat triangle's sag under the
  ellipsoid's curve, plus the terrain's relief within it) projects to more than ``max_sse``
  pixels from the nearest it can be to the camera; facets beyond the horizon or outside the
  frustum are dropped at the first level that proves it.

``mesh`` turns a selection into triangles in Earth-centred coordinates and removes the cracks
between levels by vertex extension: a finer facet's vertex that lies on a coarser neighbour's
edge is moved onto that edge (the straight line between the edge's ends, heights included).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import WGS84_A, WGS84_B, geodetic_to_ecef
from lodscape.geo.qtm import facet_vertices, locate, split, vertex_keys
from lodscape.lod.camera import Camera

__all__ = [
    "GlobeMesh",
    "Selection",
    "block_count",
    "by_error",
    "mesh",
    "pole_longitudes",
    "thinning",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
#: Heights (metres) at (lat, lon) arrays; 0 where there is no data.
Heights = Callable[[F64, F64], F64]


@dataclass(frozen=True)
class Selection:
    """Facets to draw: per level, the ids at that level."""

    levels: dict[int, I64]

    @property
    def count(self) -> int:
        return int(sum(len(v) for v in self.levels.values()))


def block_count(k: int) -> int:
    """The paper's number of blocks, T = 2·4^(k-2) (its figure: 512 at k = 6). They are the QTM
    facets of level k - 2 (8·4^(k-3) = 2·4^(k-2)): ``thinning`` takes its blocks from a level."""
    return int(2 * 4 ** (k - 2))


def thinning(
    lat: float, lon: float, *, base: int = 7, block_level: int = 6, extra: int = 2, blocks: int = 1
) -> Selection:
    """The paper's refinement: every facet at ``base``; the ``blocks`` facets of
    ``block_level`` nearest the viewpoint (the thinning area) at ``base + extra``."""
    if not 1 <= block_level <= base:
        raise ValueError(f"block level must be within 1..{base}, got {block_level}")
    here = int(locate([lat], [lon], block_level)[0])
    area = _nearest_blocks(here, block_level, blocks, lat, lon)
    fine = base + extra
    shift_base = 2 * (base - block_level)
    shift_fine = 2 * (fine - block_level)
    coarse_all = np.arange(8 * 4 ** (base - 1), dtype=np.int64)
    keep = ~np.isin(coarse_all >> shift_base, area)
    fine_ids = (area[:, None] << shift_fine) + np.arange(1 << shift_fine)
    return Selection({base: coarse_all[keep], fine: np.sort(fine_ids.ravel())})


def _nearest_blocks(here: int, level: int, n: int, lat: float, lon: float) -> I64:
    """The ``n`` facets of ``level`` whose centres are nearest (lat, lon), ``here`` first."""
    if n <= 1:
        return np.array([here], np.int64)
    ids = np.arange(8 * 4 ** (level - 1), dtype=np.int64)
    c = _centres(facet_vertices(level, ids))
    p = _unit(np.array([lat]), np.array([lon]))[0]
    order = np.argsort(-(c @ p))
    return np.sort(ids[order[:n]])


def _unit(lat: F64, lon: F64) -> F64:
    la, lo = np.radians(lat), np.radians(lon)
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)


def _centres(v: F64) -> F64:
    """Unit vectors of facet centres (mean of the vertices' unit vectors)."""
    u = _unit(v[..., 0], v[..., 1]).mean(axis=1)
    out: F64 = u / np.linalg.norm(u, axis=1, keepdims=True)
    return out


@dataclass(frozen=True)
class _Caps:
    """What culling and refinement need of facets (F): geocentric centre directions, angular
    radii, bounding spheres, the highest radius from the Earth's centre, and the error (the
    flat triangle's sag under the ellipsoid plus the terrain's departure from its plane)."""

    direction: F64
    rho: F64
    centre: F64
    radius: F64
    r_top: F64
    error: F64

    def hidden(self, eye: F64) -> NDArray[np.bool_]:
        """Beyond the horizon of the sphere inside the ellipsoid (its polar radius, so never
        too much): the nearest the facet's cap comes to the eye's direction is behind the
        horizon plane."""
        r_eye = float(np.linalg.norm(eye))
        if r_eye <= WGS84_B:
            return np.zeros(len(self.rho), bool)
        alpha = np.arccos(np.clip(self.direction @ (eye / r_eye), -1.0, 1.0))
        out: NDArray[np.bool_] = (
            self.r_top * np.cos(np.maximum(alpha - self.rho, 0.0)) < WGS84_B**2 / r_eye - 1.0
        )
        return out

    def outside(self, eye: F64, planes: F64) -> NDArray[np.bool_]:
        rel = self.centre - eye
        out: NDArray[np.bool_] = np.any(
            rel @ planes[:, :3].T + planes[:, 3] < -self.radius[:, None], axis=1
        )
        return out

    def sse(self, eye: F64, camera: Camera) -> F64:
        return camera.screen_error(
            self.error, np.linalg.norm(self.centre - eye, axis=1) - self.radius
        )


def _caps(v: F64, relief: F64 | None = None) -> _Caps:
    """Caps of facets (F, 3, 2 lat/lon) with ``relief`` (F, 3: lowest and highest terrain height,
    departure from the plane; none: the ellipsoid). Positions are geodetic: the ellipsoid's
    point at latitude φ is not along the unit vector of φ (up to 0.19° off, 21 km), so the
    spheres are built from the corners' Earth-centred positions."""
    p = geodetic_to_ecef(v[..., 1], v[..., 0], 0.0)  # (F, 3, 3)
    u = p / np.linalg.norm(p, axis=2, keepdims=True)
    c = u.mean(axis=1)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    rho = np.arccos(np.clip(np.einsum("fk,fvk->fv", c, u).min(axis=1), -1.0, 1.0))
    t = relief if relief is not None else np.zeros((len(v), 3))
    lo, hi, dev = np.minimum(t[:, 0], 0.0), np.maximum(t[:, 1], 0.0), t[:, 2]
    sag = WGS84_A * (1.0 - np.cos(np.minimum(rho, math.pi / 2)))
    # about the flat triangle's centroid: its corners, the ellipsoid's bulge above it, and the
    # terrain's heights either way
    m = p.mean(axis=1)
    reach = np.linalg.norm(p - m[:, None, :], axis=2).max(axis=1)
    radius = reach + sag + np.maximum(hi, -lo)
    return _Caps(c, rho, m, radius, WGS84_A + hi + 100.0, sag + dev)


def by_error(
    camera: Camera,
    *,
    max_sse: float = 2.0,
    max_level: int = 20,
    relief: Callable[[int, I64, F64], F64] | None = None,
) -> Selection:
    """Facets whose error projects to at most ``max_sse`` pixels (or of ``max_level``), in view
    and above the horizon. ``relief(level, ids, vertices)`` gives each facet's (F, 3) lowest and
    highest terrain height and how far its terrain strays from the facet's plane, metres;
    none: the ellipsoid."""
    eye = camera.position
    planes = camera.frustum_planes()
    out: dict[int, I64] = {}
    ids = np.arange(8, dtype=np.int64)
    v = facet_vertices(1, ids)
    level = 1
    while len(ids):
        caps = _caps(v, relief(level, ids, v) if relief is not None else None)
        keep = ~(caps.hidden(eye) | caps.outside(eye, planes))
        sse = caps.sse(eye, camera)
        split_ = keep & (sse > max_sse) & (level < max_level)
        done = keep & ~split_
        if done.any():
            out[level] = ids[done]
        if not split_.any():
            break
        kids = split(v[split_])  # (S, 4, 3, 2)
        ids = ((ids[split_][:, None] << 2) + np.arange(4)).ravel()
        v = kids.reshape(-1, 3, 2)
        level += 1
    return Selection({k: np.sort(x) for k, x in out.items()})


@dataclass(frozen=True, eq=False)
class GlobeMesh:
    """Triangles of a selection: three vertices each (not shared: texture coordinates follow
    each facet's own longitudes), Earth-centred metres, and lat/lon."""

    #: (T, 3, 3) ECEF metres.
    positions: F64
    #: (T, 3, 2) lat, lon degrees.
    latlon: F64
    #: (T,) each triangle's level.
    level: I64
    #: Vertices moved onto a coarser neighbour's edge.
    extended: int


def mesh(sel: Selection, heights: Heights | None = None, *, extend: bool = True) -> GlobeMesh:
    """The selection's triangles; with ``extend``, cracks between levels removed."""
    vs, lv = [], []
    for lvl, ids in sorted(sel.levels.items()):
        vs.append(facet_vertices(lvl, ids))
        lv.append(np.full(len(ids), lvl, np.int64))
    v = np.concatenate(vs) if vs else np.zeros((0, 3, 2))
    level: I64 = np.concatenate(lv) if lv else np.zeros(0, np.int64)
    flat = v.reshape(-1, 2)
    keys = vertex_keys(flat)
    uniq, inv = np.unique(keys, return_inverse=True)
    first = np.zeros(len(uniq), np.int64)
    first[inv[::-1]] = np.arange(len(inv))[::-1]
    ulat, ulon = flat[first, 0], flat[first, 1]
    h = heights(ulat, ulon) if heights is not None else np.zeros(len(uniq))
    pos = geodetic_to_ecef(ulon, ulat, h)
    if not (extend and len(sel.levels) > 1):
        return GlobeMesh(pos[inv].reshape(-1, 3, 3), v, level, 0)
    pos, on_edges = _extend(v, level, keys, uniq, pos)
    moved = len(np.unique(on_edges[3])) if len(on_edges[0]) else 0
    positions, latlon, tri_level = _fans(v, level, inv.reshape(-1, 3), pos, on_edges)
    return GlobeMesh(positions, latlon, tri_level, moved)


def _fans(
    v: F64,
    level: I64,
    corners: NDArray[np.int64],
    pos: F64,
    on_edges: tuple[I64, I64, F64, I64, F64],
) -> tuple[F64, F64, I64]:
    """The triangles, with no T-junction: a facet with finer vertices on its edges is drawn as
    a fan about its centroid through its corners and those vertices in order, so every vertex
    on an edge is a corner of the triangles on both sides (a vertex merely lying on an edge
    leaves pixel-wide cracks where rounding puts it a hair off). The fan is in the facet's
    plane: the picture is the facet's."""
    f_i, e_i, t_i, v_i, ll_i = on_edges
    split_ = np.zeros(len(v), bool)
    split_[f_i] = True
    keep = ~split_
    out_pos = [pos[corners[keep]]]
    out_ll = [v[keep]]
    out_lv = [level[keep]]
    fs = np.nonzero(split_)[0]
    if len(fs):
        # the boundary of each split facet: its corners (at t = 0 of their edge) and the
        # vertices found on its edges, in (facet, edge, t) order
        f_all = np.concatenate([np.repeat(fs, 3), f_i])
        e_all = np.concatenate([np.tile(np.arange(3), len(fs)), e_i])
        t_all = np.concatenate([np.zeros(3 * len(fs)), t_i])
        vid = np.concatenate([corners[fs].ravel(), v_i])
        own = pole_longitudes(v[fs])
        ll = np.concatenate([own.reshape(-1, 2), ll_i])
        order = np.lexsort((t_all, e_all, f_all))
        f_all, vid, ll = f_all[order], vid[order], ll[order]
        start = np.r_[0, np.nonzero(np.diff(f_all))[0] + 1]
        nxt = np.arange(len(f_all)) + 1
        last = np.r_[start[1:], len(f_all)] - 1
        nxt[last] = start  # each facet's boundary closes on itself
        slot = np.searchsorted(fs, f_all)  # the facet of each boundary vertex, among fs
        centre = pos[corners[fs]].mean(axis=1)
        c_ll = own.mean(axis=1)
        out_pos.append(np.stack([centre[slot], pos[vid], pos[vid[nxt]]], axis=1))
        out_ll.append(np.stack([c_ll[slot], ll, ll[nxt]], axis=1))
        out_lv.append(level[f_all])
    return np.concatenate(out_pos), np.concatenate(out_ll), np.concatenate(out_lv)


def pole_longitudes(tri: F64) -> F64:
    """Facets' (F, 3, 2) lat/lon with a pole taking the longitude of the facet's other corners
    (their mean): the texture row of a pole is one colour, and a mean of the corners must
    not swing across the whole row."""
    out = tri.copy()
    pole = np.abs(tri[..., 0]) == 90.0
    others = np.where(pole, np.nan, tri[..., 1])
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(np.where(pole.all(axis=1)[:, None], 0.0, others), axis=1)
    out[..., 1] = np.where(pole, mean[:, None], tri[..., 1])
    return out


def _extend(
    v: F64, level: I64, keys: NDArray[np.int64], uniq: NDArray[np.int64], pos: F64
) -> tuple[F64, tuple[I64, I64, F64, I64, F64]]:
    """Vertex extension: every vertex that lies inside the edge of a coarser facet goes onto that
    edge, linearly between its ends. Along an edge of level L the vertices of level L + d are
    its dyadic points (the averages of its ends, halved again), so they are found by key.
    Returns the positions and what was found: (facet, edge, t along the edge, vertex, lat/lon)
    for each vertex inside a coarser facet's edge."""
    out = pos.copy()
    top = int(level.max())
    found_f: list[I64] = []
    found_e: list[I64] = []
    found_t: list[F64] = []
    found_v: list[I64] = []
    found_ll: list[F64] = []
    for lv in np.unique(level):  # coarsest first
        depth = top - int(lv)
        if depth <= 0:
            continue
        facet = np.nonzero(level == lv)[0]
        tri = v[facet]  # (F, 3, 2)
        for a_i, b_i in ((0, 1), (1, 2), (2, 0)):
            a, b = tri[:, a_i].copy(), tri[:, b_i].copy()
            # a pole takes the other end's longitude, as the midpoints did
            a[:, 1] = np.where(np.abs(a[:, 0]) == 90.0, b[:, 1], a[:, 1])
            b[:, 1] = np.where(np.abs(b[:, 0]) == 90.0, a[:, 1], b[:, 1])
            t = np.arange(1, 1 << depth) / float(1 << depth)
            pts = a[:, None, :] + (b - a)[:, None, :] * t[None, :, None]  # (F, K, 2)
            k = vertex_keys(pts)
            ka = vertex_keys(tri[:, a_i])
            kb = vertex_keys(tri[:, b_i])
            found = np.isin(k, uniq)
            if not found.any():
                continue
            fi, ti = np.nonzero(found)
            # uniq is sorted (np.unique): keys to vertex numbers by binary search
            ia = np.searchsorted(uniq, ka[fi])
            ib = np.searchsorted(uniq, kb[fi])
            iv = np.searchsorted(uniq, k[fi, ti])
            tt = t[ti][:, None]
            # the ends as they stand now: a coarser level may have moved them already
            out[iv] = out[ia] * (1.0 - tt) + out[ib] * tt
            found_f.append(facet[fi])
            found_e.append(np.full(len(fi), a_i, np.int64))
            found_t.append(t[ti])
            found_v.append(iv)
            found_ll.append(pts[fi, ti])
    if not found_f:
        nothing = np.zeros(0, np.int64)
        return out, (nothing, nothing, np.zeros(0), nothing, np.zeros((0, 2)))
    return out, (
        np.concatenate(found_f),
        np.concatenate(found_e),
        np.concatenate(found_t),
        np.concatenate(found_v),
        np.concatenate(found_ll),
    )


def screen_error(sel: Selection, camera: Camera) -> float:
    """The largest projected error (pixels) of a selection's facets in view, by the same rule
    ``by_error`` refines with (the ellipsoid's sag; no terrain)."""
    eye = camera.position
    planes = camera.frustum_planes()
    worst = 0.0
    for level, ids in sel.levels.items():
        caps = _caps(facet_vertices(level, ids))
        seen = ~(caps.hidden(eye) | caps.outside(eye, planes))
        if seen.any():
            worst = max(worst, float(caps.sse(eye, camera)[seen].max()))
    return worst


def naive_by_error(camera: Camera, *, max_sse: float = 2.0, max_level: int = 20) -> Selection:
    """``by_error`` one facet at a time, recursively (the benchmark's baseline)."""
    eye = camera.position
    planes = camera.frustum_planes()
    r_eye = float(np.linalg.norm(eye))
    out: dict[int, list[int]] = {}

    def visit(level: int, fid: int, v: F64) -> None:
        # _caps and its tests, for one facet
        p = geodetic_to_ecef(v[:, 1], v[:, 0], 0.0)
        u = p / np.linalg.norm(p, axis=1, keepdims=True)
        c = u.mean(axis=0)
        c /= np.linalg.norm(c)
        rho = math.acos(min(max(float((u @ c).min()), -1.0), 1.0))
        sag = WGS84_A * (1.0 - math.cos(min(rho, math.pi / 2)))
        m = p.mean(axis=0)
        radius = float(np.linalg.norm(p - m, axis=1).max()) + sag
        alpha = math.acos(min(max(float(c @ (eye / r_eye)), -1.0), 1.0))
        if r_eye > WGS84_B and (WGS84_A + 100.0) * math.cos(max(alpha - rho, 0.0)) < (
            WGS84_B**2 / r_eye - 1.0
        ):
            return
        rel = m - eye
        if np.any(planes[:, :3] @ rel + planes[:, 3] < -radius):
            return
        dist = float(np.linalg.norm(rel)) - radius
        if float(camera.screen_error(sag, dist)) > max_sse and level < max_level:
            kids = split(v[None])[0]
            for d in range(4):
                visit(level + 1, fid * 4 + d, kids[d])
        else:
            out.setdefault(level, []).append(fid)

    for o in range(8):
        visit(1, o, facet_vertices(1, np.array([o]))[0])
    return Selection({k: np.sort(np.array(x, np.int64)) for k, x in out.items()})
