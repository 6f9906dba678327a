"""A naive recursive selection, one tile per Python call: the baseline for tests and benchmarks.

It applies the rules of ``lodscape.lod.select`` tile by tile, depth first, with no residency; the
vectorised selection must return the same tiles and grids. Its geometry is its own: each tile's
box, distance and frustum test are made here from the textbook formulas (spherical Mercator,
WGS84 to ECEF, the local east-north-up frame, clip-space corners through the camera's OpenGL
matrices), not from ``select.tile_boxes``, so a culling or distance bug there is caught.
"""

from __future__ import annotations

import math

import numpy as np

from lodscape.geo.keys import grid_of, tile_id_of
from lodscape.geo.tiles import Tile, tile_id
from lodscape.lod.camera import EARTH_MIN_RADIUS, MIN_DISTANCE, Camera
from lodscape.lod.select import (
    SLOPE_ROOM,
    SUB_MAX,
    SUB_MIN_SPAN,
    SUB_PER_VIEW,
    Selection,
    SelectOptions,
    TreeLike,
    hysteresis_steps,
)

_A = 6378137.0  # WGS84 semi-major axis
_E2 = (1.0 / 298.257223563) * (2.0 - 1.0 / 298.257223563)  # first eccentricity squared
_HALF = math.pi * _A  # half the Web Mercator square's side
#: The box's margin, a share of the tile's ground size (the selection's rule).
_MARGIN = 1e-3


def _ecef(lon: np.ndarray, lat: np.ndarray, h: np.ndarray | float) -> np.ndarray:
    lam, phi = np.radians(lon), np.radians(lat)
    n = _A / np.sqrt(1.0 - _E2 * np.sin(phi) ** 2)
    return np.stack(
        [
            (n + h) * np.cos(phi) * np.cos(lam),
            (n + h) * np.cos(phi) * np.sin(lam),
            (n * (1.0 - _E2) + h) * np.sin(phi),
        ],
        axis=-1,
    )


def _box(
    camera: Camera, z: int, x: int, y: int, lo_h: float, hi_h: float
) -> tuple[bool, float, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(in the view, distance to the nearest point of the box, ground size, the box's corners
    relative to the camera, the ENU rows, the box's low and high corners in that frame about
    the camera) of one tile: its lattice at both heights, boxed with
    a margin in the ENU frame at the tile's centre."""
    side = 2.0 * _HALF / 2**z
    left, top = -_HALF + x * side, _HALF - y * side
    right, bottom = left + side, top - side
    # enough lattice points that the Earth's curve between them stays inside the margin
    n = min(2 + math.ceil(math.sqrt(side / (8.0 * _A * _MARGIN))), 33)
    f = np.linspace(0.0, 1.0, n)
    mx, my = np.meshgrid(left + f * side, bottom + f * side)
    lon = np.degrees(mx / _A)
    lat = np.degrees(2.0 * np.arctan(np.exp(my / _A)) - math.pi / 2.0)
    clon = math.degrees((left + right) / 2.0 / _A)
    clat = math.degrees(2.0 * math.atan(math.exp((bottom + top) / 2.0 / _A)) - math.pi / 2.0)
    sl, cl = math.sin(math.radians(clon)), math.cos(math.radians(clon))
    sp, cp = math.sin(math.radians(clat)), math.cos(math.radians(clat))
    enu = np.array([[-sl, cl, 0.0], [-sp * cl, -sp * sl, cp], [cp * cl, cp * sl, sp]])
    eye = _ecef(np.array(camera.lon), np.array(camera.lat), camera.alt)
    pts = np.concatenate([_ecef(lon, lat, lo_h), _ecef(lon, lat, hi_h)]).reshape(-1, 3)
    local = (pts - eye) @ enu.T
    ground = side * cp
    lo = local.min(axis=0) - _MARGIN * ground
    hi = local.max(axis=0) + _MARGIN * ground
    corners = _corners(lo, hi) @ enu
    return _in_view(camera, corners), _gap(lo, hi), ground, corners, enu, lo, hi


def _in_view(camera: Camera, corners: np.ndarray) -> bool:
    """Whether a box (its eight corners relative to the camera) is not wholly beyond one clip
    plane: its corners in clip space."""
    view = corners @ camera.rotation.T
    clip = np.c_[view, np.ones(8)] @ camera.projection().T
    w = clip[:, 3]
    return not any(
        bool(np.all(w + sign * clip[:, axis] < 0.0)) for axis in range(3) for sign in (1.0, -1.0)
    )


def _parts(camera: Camera, corners: np.ndarray) -> int:
    """How many parts a side a box is measured in: SUB_PER_VIEW times the share of the view
    its image spans, rounded up (the whole view where it reaches behind the
    near plane), at most SUB_MAX."""
    view = corners @ camera.rotation.T
    depth = -view[:, 2]
    floor = max(camera.near or 0.0, MIN_DISTANCE)
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    tx = ty * camera.width / camera.height
    if depth.min() < floor:
        span = 1.0
    else:
        ra = np.clip(view[:, 0] / depth, -tx, tx)
        rb = np.clip(view[:, 1] / depth, -ty, ty)
        span = max(float(np.ptp(ra)) / (2 * tx), float(np.ptp(rb)) / (2 * ty))
    if span < SUB_MIN_SPAN:
        return 1
    return min(max(math.ceil(span * SUB_PER_VIEW - 1e-9), 1), SUB_MAX)


def _vertical(
    camera: Camera, lo: np.ndarray, hi: np.ndarray, enu: np.ndarray, ground: float
) -> float:
    """Pixels per metre of height error: the worst over the box's parts in view (all of them
    where none is), each part a k-th of the box's east and north sides at its full height."""
    corners = _corners(lo, hi) @ enu
    k = _parts(camera, corners)
    if k == 1:
        return _scales(camera, corners, enu, ground, _gap(lo, hi))[0]
    seen, unseen = 0.0, 0.0
    for i in range(k):
        for j in range(k):
            plo = np.array(
                [lo[0] + (hi[0] - lo[0]) * i / k, lo[1] + (hi[1] - lo[1]) * j / k, lo[2]]
            )
            phi = np.array(
                [
                    lo[0] + (hi[0] - lo[0]) * (i + 1) / k,
                    lo[1] + (hi[1] - lo[1]) * (j + 1) / k,
                    hi[2],
                ]
            )
            c = _corners(plo, phi) @ enu
            v = _scales(camera, c, enu, ground, _gap(plo, phi))[0]
            if _in_view(camera, c):
                seen = max(seen, v)
            unseen = max(unseen, v)
    return seen if seen > 0.0 else unseen


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.array(
        [[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])]
    )


def _gap(lo: np.ndarray, hi: np.ndarray) -> float:
    gap = np.maximum(lo, 0.0) + np.maximum(-hi, 0.0)
    return float(math.sqrt(float(gap @ gap)))


def _scales(
    camera: Camera, corners: np.ndarray, enu: np.ndarray, ground: float, dist: float
) -> tuple[float, float]:
    """Pixels per metre of height error and along the ground at the box's worst point, written
    out per corner of the image rectangle (the projection's first derivative, as the selection's
    ``Camera.box_scales``)."""
    d = camera.scale
    rot = camera.rotation
    view = corners @ rot.T
    depth = -view[:, 2]
    floor = max(camera.near or 0.0, MIN_DISTANCE)
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    tx = ty * camera.width / camera.height
    if depth.min() < floor:
        xs, ys = (-tx, tx), (-ty, ty)
    else:
        ra, rb = view[:, 0] / depth, view[:, 1] / depth
        xs = (min(max(float(ra.min()), -tx), tx), min(max(float(ra.max()), -tx), tx))
        ys = (min(max(float(rb.min()), -ty), ty), min(max(float(rb.max()), -ty), ty))
    east, north, up = (rot @ v * np.array([1.0, 1.0, -1.0]) for v in enu)
    turn = ground * math.sqrt(0.5) / EARTH_MIN_RADIUS
    vertical = horizontal = 0.0
    for a in xs:
        for b in ys:
            jac = np.array([[1.0, 0.0, -a], [0.0, 1.0, -b]])
            slack = turn * math.sqrt(1.0 + a * a + b * b)
            vertical = max(vertical, float(np.linalg.norm(jac @ up)) + slack)
            plane = jac @ np.stack([east, north], axis=1)
            horizontal = max(horizontal, float(np.linalg.svd(plane, compute_uv=False)[0]) + slack)
    # a visible point is within the viewport's corner angle of the axis: no shallower than
    # its distance times that angle's cosine
    seen = max(float(depth.min()), dist / math.sqrt(1.0 + tx * tx + ty * ty), floor)
    return d / seen * vertical, d / seen * horizontal


__all__ = ["select_reference"]


def select_reference(
    options: SelectOptions, camera: Camera, tree: TreeLike, previous: Selection | None = None
) -> list[tuple[int, int, int, int, int]]:
    """Drawn tiles as (z, x, y, grid index, levels up to the texture), in depth-first order."""
    assert camera.near is not None
    t = tree.tile_size
    zmax = tree.zmax if options.max_level is None else min(tree.zmax, options.max_level)
    ztex = tree.zmax if tree.texture_zmax is None else tree.texture_zmax
    was = set(previous.refined.tolist()) if previous is not None else set()
    steps = hysteresis_steps(tree)
    grid_before = (
        {tile_id_of(int(k)): grid_of(int(k)) for k in previous.keys.tolist()}
        if previous is not None
        else {}
    )
    tex_before = (
        {
            int(tile_id(Tile(x, y, z))): int(u)
            for z, x, y, u in zip(
                previous.z, previous.x, previous.y, previous.texture_up, strict=True
            )
        }
        if previous is not None
        else {}
    )
    out: list[tuple[int, int, int, int, int]] = []

    boxes: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray, np.ndarray, float]] = {}

    def metrics(z: int, x: int, y: int) -> tuple[bool, bool, float, np.ndarray, float] | None:
        st = tree.level(z).stats(np.array([x]), np.array([y]))
        if not st.exists[0]:
            return None
        inside, dist, ground, corners, enu, lo, hi = _box(
            camera, z, x, y, float(st.min_h[0]), float(st.max_h[0])
        )
        vertical, horizontal = _scales(camera, corners, enu, ground, dist)
        boxes[(z, x, y)] = (lo, hi, enu, ground)
        return inside, True, ground * horizontal, st.error[:, 0], vertical

    def visit(z: int, x: int, y: int, parent_k: int = -1) -> None:
        m = metrics(z, x, y)
        if m is None or not m[0]:
            return
        _, _, px, err, scale = m
        k = next((i for i, e in enumerate(err) if e * scale <= options.max_sse), None)
        least = int(np.argmin(err))  # the coarsest of the least error
        big = px > options.split * t and z < ztex
        refine = z < zmax and (big or k is None)
        if z < zmax and not refine and tile_id(Tile(x, y, z)) in was:
            # kept split while still rough, or while every visible child stays in the band
            refine = err[-1] * scale > options.sse_merge * options.max_sse
            hold = z < ztex
            for cx, cy in (
                (2 * x, 2 * y),
                (2 * x + 1, 2 * y),
                (2 * x, 2 * y + 1),
                (2 * x + 1, 2 * y + 1),
            ):
                c = metrics(z + 1, cx, cy)
                if c is not None and c[0] and c[2] < options.merge * t:
                    hold = False
            refine = refine or hold
        if refine:
            for cx, cy in (
                (2 * x, 2 * y),
                (2 * x + 1, 2 * y),
                (2 * x, 2 * y + 1),
                (2 * x + 1, 2 * y + 1),
            ):
                visit(z + 1, cx, cy, least if k is None else k)
        else:
            k = least if k is None else k
            if k > 0 and px >= SUB_MIN_SPAN * min(camera.width, camera.height):
                # a tile drawn large on screen is charged at the worst of its parts in view
                v = min(_vertical(camera, *boxes[(z, x, y)]), scale)
                k = min(k, next((i for i, e in enumerate(err) if e * v <= options.max_sse), least))
            before_k = grid_before.get(tile_id(Tile(x, y, z)))
            if before_k is not None and k < before_k <= k + steps:
                k = before_k
            if options.hold_parent_grid:
                k = min(max(k, parent_k - steps), len(err) - 1)
            up = max(0, z - ztex)
            while up < z - tree.zmin and px * 2 ** (up + 1) <= options.split / SLOPE_ROOM * t:
                up += 1
            before = tex_before.get(tile_id(Tile(x, y, z)))
            if before is not None and options.merge * t <= px * 2**before <= options.split * t:
                up = before
            out.append((z, x, y, k, up))

    xs, ys = tree.roots()
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        visit(tree.zmin, x, y)
    return out
