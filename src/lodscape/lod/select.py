"""Tile selection: which tiles to draw this frame, at which grid size, and which to load.

``select`` is a pure function (cesium-native's ViewUpdateResult, not CesiumJS's queue-editing
visitTile): it walks the quadtree one level per step with numpy, returns the render list, the load
requests and the counters, and touches no IO and no GPU.

The rules, per tile, with H = h·d/dist (paper 000) the pixels its texture covers:
- culled when its oriented box (its min/max heights included) lies outside a frustum plane;
- split when H > split·T (T texels per tile side), kept split while the previous frame had it
  split and every child still covers merge·T pixels or more (hysteresis, no flicker);
- split when even its finest grid cannot keep the screen-space error within ``max_sse``;
- otherwise drawn, with the coarsest grid whose error stays within ``max_sse`` at the larger of its
  real screen scale and the top of the pixel band, so the mesh follows the terrain's roughness.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import enu_basis, geodetic_to_ecef
from lodscape.geo.tiles import bounds_array, merc_to_lonlat, tile_id_array
from lodscape.lod.camera import Camera

__all__ = ["LevelLike", "SelectOptions", "Selection", "TreeLike", "select", "tile_boxes"]

_EMPTY_U = np.zeros(0, dtype=np.uint64)
_EMPTY_I = np.zeros(0, dtype=np.int64)
_EMPTY_F = np.zeros(0, dtype=np.float64)


class LevelLike(Protocol):
    z: int
    min_h: NDArray[np.float32]
    max_h: NDArray[np.float32]
    error: NDArray[np.float32]

    def index(
        self, x: NDArray[np.int64], y: NDArray[np.int64]
    ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]: ...


class TreeLike(Protocol):
    grids: tuple[int, ...]
    tile_size: int

    @property
    def zmin(self) -> int: ...

    @property
    def zmax(self) -> int: ...

    def level(self, z: int) -> LevelLike: ...

    def roots(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]: ...


@dataclass(frozen=True)
class SelectOptions:
    """How selection trades detail for speed; the defaults follow paper 000's 128..384 px band."""

    #: Split a tile that covers more than split × its texture size in pixels.
    split: float = 1.5
    #: Merge four children back only when one would cover less than merge × its texture size.
    merge: float = 0.5
    #: Bound on every drawn tile's geometric screen-space error, pixels.
    max_sse: float = 2.0
    #: Deepest level to use (None: the tree's finest).
    max_level: int | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.merge < self.split:
            raise ValueError(f"Expected 0 < merge < split, got {self.merge} and {self.split}")
        if not self.max_sse > 0.0:
            raise ValueError(f"Expected a positive max_sse, got {self.max_sse}")


@dataclass(frozen=True, eq=False)
class Selection:
    """A frame's render list, load requests and counters. Arrays run over the drawn tiles."""

    z: NDArray[np.int64]
    x: NDArray[np.int64]
    y: NDArray[np.int64]
    #: Index into the tree's grids of the grid each tile is drawn with.
    grid: NDArray[np.int64]
    #: Resource keys (tile id << 3 | grid index) of the drawn tiles.
    keys: NDArray[np.uint64]
    screen_px: NDArray[np.float64]
    sse: NDArray[np.float64]
    dist_near: NDArray[np.float64]
    #: Metres to hang each tile's skirt: its own error plus what a neighbour's may be.
    skirt: NDArray[np.float64]
    #: Levels each drawn tile stands above the one wanted (0: drawn as wanted).
    fallback: NDArray[np.int64]
    #: Ids of the tiles refined this frame, sorted (the next frame's hysteresis).
    refined: NDArray[np.uint64]
    #: Keys wanted but not resident, most urgent first (coarse levels, then near tiles).
    loads: NDArray[np.uint64]
    visited: int = 0
    culled: int = 0
    #: Tiles drawn above split·T because the data has no finer level or the near plane cuts them.
    magnified: int = 0
    texture_size: int = 256
    grids: tuple[int, ...] = field(default=(16, 32, 64, 128, 256))

    @property
    def count(self) -> int:
        return int(self.z.size)

    @property
    def max_depth(self) -> int:
        return int(self.z.max()) if self.z.size else -1

    @property
    def max_sse(self) -> float:
        return float(self.sse.max()) if self.sse.size else 0.0

    @property
    def triangles(self) -> int:
        s = np.asarray(self.grids, dtype=np.int64)[self.grid]
        return int((2 * s * s + 8 * s).sum())

    @property
    def px_per_texel(self) -> tuple[float, float]:
        """Range over drawn tiles of screen pixels per texel (1 is the texture's own size)."""
        if not self.z.size:
            return (0.0, 0.0)
        r = self.screen_px / self.texture_size
        return float(r.min()), float(r.max())

    def stats(self) -> dict[str, float | int]:
        lo, hi = self.px_per_texel
        return {
            "tiles": self.count,
            "visited": self.visited,
            "culled": self.culled,
            "refined": int(self.refined.size),
            "max_depth": self.max_depth,
            "max_sse_px": round(self.max_sse, 3),
            "px_per_texel_min": round(lo, 3),
            "px_per_texel_max": round(hi, 3),
            "magnified": self.magnified,
            "triangles": self.triangles,
            "loads": int(self.loads.size),
            "fallback_max": int(self.fallback.max()) if self.fallback.size else 0,
        }


@dataclass(frozen=True, eq=False)
class Boxes:
    """Oriented boxes of tiles, relative to the camera, with their screen metrics."""

    inside: NDArray[np.bool_]
    dist_near: NDArray[np.float64]
    dist_far: NDArray[np.float64]
    ground: NDArray[np.float64]


def tile_boxes(
    camera: Camera,
    z: int,
    x: NDArray[np.int64],
    y: NDArray[np.int64],
    min_h: NDArray[np.floating],
    max_h: NDArray[np.floating],
) -> Boxes:
    """Frustum test and distances for N tiles of one level, each boxed in its local ENU frame.

    The box holds a 5×5 lattice of the tile at its min and max height; for the coarse levels,
    where the Earth's curve bulges between lattice points, the margin below covers it.
    """
    left, bottom, right, top = bounds_array(z, x, y)
    f = np.linspace(0.0, 1.0, 5)
    xs = left[:, None] + f * (right - left)[:, None]
    ys = bottom[:, None] + f * (top - bottom)[:, None]
    lon, lat = merc_to_lonlat(xs[:, None, :], ys[:, :, None])
    clon, clat = merc_to_lonlat((left + right) / 2.0, (bottom + top) / 2.0)
    basis = enu_basis(clon, clat)
    lo_h = np.asarray(min_h, np.float64)[:, None, None]
    hi_h = np.asarray(max_h, np.float64)[:, None, None]
    pts = (
        np.concatenate(
            [geodetic_to_ecef(lon, lat, lo_h), geodetic_to_ecef(lon, lat, hi_h)], axis=1
        ).reshape(len(x), -1, 3)
        - camera.position
    )
    local = np.einsum("nij,npj->npi", basis, pts)
    ground = (right - left) * np.cos(np.radians(clat))
    margin = (1e-3 * ground)[:, None]
    lo = local.min(axis=1) - margin
    hi = local.max(axis=1) + margin
    # the camera sits at the origin of these camera-relative coordinates
    gap = np.maximum(lo, 0.0) + np.maximum(-hi, 0.0)
    dist_near = np.linalg.norm(gap, axis=1)
    dist_far = np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)), axis=1)
    centre = np.einsum("ni,nij->nj", (lo + hi) / 2.0, basis)
    half = (hi - lo) / 2.0
    planes = camera.frustum_planes()
    s = centre @ planes[:, :3].T + planes[:, 3]
    r = np.einsum("ni,npi->np", half, np.abs(np.einsum("pj,nij->npi", planes[:, :3], basis)))
    inside = np.all(s + r >= 0.0, axis=1)
    return Boxes(inside, dist_near, dist_far, ground)


def _grid_choice(
    options: SelectOptions,
    camera: Camera,
    err: NDArray[np.float32],
    scale: NDArray[np.float64],
    band_scale: NDArray[np.float64],
) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """Coarsest grid meeting the bound at max(real, band-top) scale; and whether none does."""
    fits = err * np.maximum(scale, band_scale) <= options.max_sse
    k = np.where(fits.any(axis=0), fits.argmax(axis=0), err.shape[0] - 1)
    return k.astype(np.int64), ~fits.any(axis=0)


def select(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    previous: Selection | None = None,
    resident: NDArray[np.uint64] | None = None,
) -> Selection:
    """The tiles to draw for ``camera``; ``resident`` (sorted keys) None means everything is."""
    if camera.near is None or camera.far is None:
        raise ValueError("select needs a camera with near/far set (Camera.with_clip)")
    near = camera.near
    d = camera.scale
    tsize = tree.tile_size
    zmax = tree.zmax if options.max_level is None else min(tree.zmax, options.max_level)
    prev = previous.refined if previous is not None else _EMPTY_U
    drawn: list[tuple[NDArray[np.generic], ...]] = []
    refined_ids: list[NDArray[np.uint64]] = []
    visited = culled = magnified = 0

    x, y = tree.roots()
    for z in range(tree.zmin, zmax + 1):
        if x.size == 0:
            break
        lv = tree.level(z)
        ok, idx = lv.index(x, y)
        x, y, idx = x[ok], y[ok], idx[ok]
        visited += int(x.size)
        box = tile_boxes(camera, z, x, y, lv.min_h.ravel()[idx], lv.max_h.ravel()[idx])
        culled += int((~box.inside).sum())
        keep = box.inside
        x, y, idx = x[keep], y[keep], idx[keep]
        dn, df, ground = box.dist_near[keep], box.dist_far[keep], box.ground[keep]
        eff = np.maximum(dn, near)
        px = ground * d / eff
        err = lv.error[:, idx // lv.min_h.shape[1], idx % lv.min_h.shape[1]]
        k, too_rough = _grid_choice(options, camera, err, d / eff, options.split * tsize / ground)
        ids = tile_id_array(z, x, y)
        can = z < zmax
        refine = can & ((px > options.split * tsize) | too_rough)
        if can and prev.size:
            was = _member(ids, prev) & ~refine
            if was.any():
                refine[was] = _children_hold(options, camera, tree, z, x[was], y[was], tsize)
        refined_ids.append(ids[refine])
        draw = ~refine
        if previous is not None:
            k = _keep_finer_grid(ids, k, previous.keys)
        magnified += int(((px > options.split * tsize) & draw).sum())
        kd = k[draw]
        errd = err[kd, np.nonzero(draw)[0]]
        drawn.append(
            (
                np.full(kd.size, z),
                x[draw],
                y[draw],
                kd,
                px[draw],
                errd * d / eff[draw],
                dn[draw],
                df[draw],
                errd.astype(np.float64),
            )
        )
        cx = (2 * x[refine][:, None] + np.array([0, 1, 0, 1])).ravel()
        cy = (2 * y[refine][:, None] + np.array([0, 0, 1, 1])).ravel()
        x, y = cx, cy

    cols = (
        [np.concatenate(c) if c else np.zeros(0) for c in zip(*drawn, strict=True)]
        if drawn
        else [np.zeros(0)] * 9
    )
    dz, dx, dy, dk, dpx, dsse, ddn, ddf, derr = cols
    dz, dx, dy, dk = (a.astype(np.int64) for a in (dz, dx, dy, dk))
    ids = tile_id_array(dz, dx, dy)
    keys = (ids << np.uint64(3)) | dk.astype(np.uint64)
    fallback = np.zeros(dz.size, dtype=np.int64)
    loads = _EMPTY_U
    if resident is not None:
        (dz, dx, dy, dk, dpx, dsse, ddn, ddf, derr, keys, fallback, loads) = _fall_back(
            camera, tree, resident, dz, dx, dy, dk, dpx, dsse, ddn, ddf, derr, keys
        )
    # a neighbour's edge may sit up to its own error away: at most max_sse pixels seen from
    # no farther than our far side, or a fallback tile's whole error
    worst = float(derr[fallback > 0].max()) if (fallback > 0).any() else 0.0
    skirt = derr + np.maximum(options.max_sse * ddf / d, worst)
    refined = np.unique(np.concatenate(refined_ids)) if refined_ids else _EMPTY_U
    return Selection(
        z=dz,
        x=dx,
        y=dy,
        grid=dk,
        keys=keys,
        screen_px=dpx,
        sse=dsse,
        dist_near=ddn,
        skirt=skirt,
        fallback=fallback,
        refined=refined,
        loads=loads,
        visited=visited,
        culled=culled,
        magnified=magnified,
        texture_size=tsize,
        grids=tuple(tree.grids),
    )


def _keep_finer_grid(
    ids: NDArray[np.uint64], k: NDArray[np.int64], prev_keys: NDArray[np.uint64]
) -> NDArray[np.int64]:
    """Grid hysteresis: a tile keeps last frame's grid while the one it needs is one step coarser
    (a finer grid only lowers the error), so a camera that hovers does not reload meshes."""
    if prev_keys.size == 0:
        return k
    order = np.argsort(prev_keys)
    pk = prev_keys[order]
    pid = pk >> np.uint64(3)
    pos = np.clip(np.searchsorted(pid, ids), 0, pid.size - 1)
    hit = pid[pos] == ids
    kprev = (pk[pos] & np.uint64(7)).astype(np.int64)
    return np.where(hit & (kprev == k + 1), kprev, k)


def _member(a: NDArray[np.uint64], sorted_b: NDArray[np.uint64]) -> NDArray[np.bool_]:
    """a ∈ b for a sorted b, vectorised."""
    if sorted_b.size == 0:
        return np.zeros(a.shape, dtype=bool)
    pos = np.clip(np.searchsorted(sorted_b, a), 0, sorted_b.size - 1)
    return sorted_b[pos] == a


def _children_hold(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    z: int,
    x: NDArray[np.int64],
    y: NDArray[np.int64],
    tsize: int,
) -> NDArray[np.bool_]:
    """For tiles split last frame: does every visible child still cover merge·T pixels?"""
    lv = tree.level(z + 1)
    cx = (2 * x[:, None] + np.array([0, 1, 0, 1])).ravel()
    cy = (2 * y[:, None] + np.array([0, 0, 1, 1])).ravel()
    ok, idx = lv.index(cx, cy)
    box = tile_boxes(camera, z + 1, cx, cy, lv.min_h.ravel()[idx], lv.max_h.ravel()[idx])
    px = box.ground * camera.scale / np.maximum(box.dist_near, camera.near or 0.0)
    # absent or culled children do not hold their parent back
    small = ok & box.inside & (px < options.merge * tsize)
    return ~small.reshape(-1, 4).any(axis=1)


def _fall_back(
    camera: Camera,
    tree: TreeLike,
    resident: NDArray[np.uint64],
    dz: NDArray[np.int64],
    dx: NDArray[np.int64],
    dy: NDArray[np.int64],
    dk: NDArray[np.int64],
    dpx: NDArray[np.float64],
    dsse: NDArray[np.float64],
    ddn: NDArray[np.float64],
    ddf: NDArray[np.float64],
    derr: NDArray[np.float64],
    keys: NDArray[np.uint64],
) -> tuple[NDArray[np.generic], ...]:
    """Draw each tile that is not resident from its nearest resident ancestor (no holes)."""
    present = _member(keys, resident)
    order = np.lexsort((ddn[~present], dz[~present]))
    loads = keys[~present][order]
    if present.all():
        return dz, dx, dy, dk, dpx, dsse, ddn, ddf, derr, keys, np.zeros(dz.size, np.int64), loads
    res_ids = np.unique(resident >> np.uint64(3))
    mz, mx, my = dz[~present], dx[~present], dy[~present]
    found = np.zeros(mz.size, dtype=bool)
    az, ax, ay = mz.copy(), mx.copy(), my.copy()
    up = np.zeros(mz.size, dtype=np.int64)
    for step in range(1, int(mz.max() - tree.zmin) + 1 if mz.size else 1):
        todo = ~found & (mz - step >= tree.zmin)
        if not todo.any():
            break
        pz, px_, py = mz[todo] - step, mx[todo] >> step, my[todo] >> step
        hit = _member(tile_id_array(pz, px_, py), res_ids)
        sel = np.nonzero(todo)[0][hit]
        az[sel], ax[sel], ay[sel], up[sel] = pz[hit], px_[hit], py[hit], step
        found[sel] = True
    fz, fx, fy, fup = az[found], ax[found], ay[found], up[found]
    fid = np.unique(tile_id_array(fz, fx, fy))
    # keep present tiles that no drawn ancestor already covers
    keep = present.copy()
    for step in range(1, int(dz.max() - tree.zmin) + 1 if dz.size else 1):
        anc = tile_id_array(dz - step, dx >> step, dy >> step)
        keep &= ~((dz - step >= tree.zmin) & _member(anc, fid))
    uz, ux, uy = (a.astype(np.int64) for a in _unpack(fid))
    # the fallback's resident key with the finest grid
    rk = resident[_member(resident >> np.uint64(3), fid)]
    rk = rk[np.argsort(rk)]
    rid = rk >> np.uint64(3)
    last = np.searchsorted(rid, fid, side="right") - 1
    fkeys = rk[last]
    fk = (fkeys & np.uint64(7)).astype(np.int64)
    fpx, fsse, fdn, fdf, ferr, fdepth = _metrics_many(camera, tree, uz, ux, uy, fk)
    # how many levels each fallback stands in for: the deepest of the tiles it replaces
    depth = np.zeros(fid.size, dtype=np.int64)
    np.maximum.at(depth, np.searchsorted(fid, tile_id_array(fz, fx, fy)), fup)
    del fdepth
    cat = np.concatenate
    return (
        cat([dz[keep], uz]),
        cat([dx[keep], ux]),
        cat([dy[keep], uy]),
        cat([dk[keep], fk]),
        cat([dpx[keep], fpx]),
        cat([dsse[keep], fsse]),
        cat([ddn[keep], fdn]),
        cat([ddf[keep], fdf]),
        cat([derr[keep], ferr]),
        cat([keys[keep], fkeys]),
        cat([np.zeros(int(keep.sum()), np.int64), depth]),
        loads,
    )


def _unpack(ids: NDArray[np.uint64]) -> tuple[NDArray[np.uint64], ...]:
    m = np.uint64(0x3FFFFFF)
    return ids >> np.uint64(52), ids & m, (ids >> np.uint64(26)) & m


def _metrics_many(
    camera: Camera,
    tree: TreeLike,
    z: NDArray[np.int64],
    x: NDArray[np.int64],
    y: NDArray[np.int64],
    k: NDArray[np.int64],
) -> tuple[NDArray[np.float64], ...]:
    """Screen metrics of tiles of mixed levels (the few fallback tiles), one numpy call a level."""
    n = z.size
    px, sse, dn, df, err = (np.zeros(n) for _ in range(5))
    near = camera.near or 0.0
    for lvl in np.unique(z):
        m = z == lvl
        lv = tree.level(int(lvl))
        _, idx = lv.index(x[m], y[m])
        box = tile_boxes(camera, int(lvl), x[m], y[m], lv.min_h.ravel()[idx], lv.max_h.ravel()[idx])
        eff = np.maximum(box.dist_near, near)
        e = lv.error[k[m], idx // lv.min_h.shape[1], idx % lv.min_h.shape[1]]
        px[m] = box.ground * camera.scale / eff
        sse[m] = e * camera.scale / eff
        dn[m], df[m], err[m] = box.dist_near, box.dist_far, e
    return px, sse, dn, df, err, np.zeros(n)
