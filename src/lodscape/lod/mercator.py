"""Imagery tiles (OSM z/x/y, Web Mercator) for a camera over the whole Earth: paper 000's rule
on the globe. Pure numpy.

``select_tiles`` walks the quadtree from the world tile level by level: a tile is split while it
covers more than ``band`` pixels on screen (H = w·d/dist, w its ground width where the Earth is
widest inside it, dist the nearest it comes to the camera) and the imagery has finer levels;
tiles wholly beyond the horizon or outside the frustum are dropped at the first level that proves
it. ``patches`` gives each tile's surface as a grid of (lon, lat) points for drawing, and
``resident_ancestors`` the nearest level of each tile that has its image (no holes: a tile
whose image has not come is drawn from its nearest ancestor's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import WGS84_A, WGS84_B, geodetic_to_ecef
from lodscape.geo.keys import texture_key_array
from lodscape.geo.tiles import (
    ORIGIN,
    bounds_array,
    children_array,
    lonlat_to_merc,
    merc_to_lonlat,
    tile_id_array,
)
from lodscape.lod.camera import Camera

__all__ = ["TileSelection", "patches", "resident_ancestors", "select_tiles"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class TileSelection:
    """Tiles to draw, coarsest first, with how near each comes to the camera (metres) and the
    pixels it covers."""

    z: I64
    x: I64
    y: I64
    distance: F64
    pixels: F64

    def __len__(self) -> int:
        return int(self.z.size)


def _samples(z: I64, x: I64, y: I64, camera_merc: tuple[float, float]) -> tuple[F64, F64]:
    """Per tile, (lon, lat) of ten points: a 3×3 grid over the tile and the point of the tile
    nearest the camera's ground point (in Mercator), which keeps a tile beside the camera from
    looking far away when its grid points are."""
    left, bottom, right, top = bounds_array(z, x, y)
    f = np.array([0.0, 0.5, 1.0])
    mx = left[:, None, None] + (right - left)[:, None, None] * f[None, None, :]
    my = bottom[:, None, None] + (top - bottom)[:, None, None] * f[None, :, None]
    mx, my = np.broadcast_arrays(mx, my)
    cx = np.clip(camera_merc[0], left, right)
    cy = np.clip(camera_merc[1], bottom, top)
    mx = np.concatenate([mx.reshape(len(z), 9), cx[:, None]], axis=1)
    my = np.concatenate([my.reshape(len(z), 9), cy[:, None]], axis=1)
    lon, lat = merc_to_lonlat(mx, my)
    return lon, lat


def _hidden(p: F64, eye: F64, relief: float) -> NDArray[np.bool_]:
    """Points (…, 3) hidden from ``eye`` by the Earth: the segment to them passes through the
    ellipsoid shrunk by ``relief`` metres (so ground that high beyond the horizon counts as
    seen). Tested in the ellipsoid's scaled space, where it is the unit sphere."""
    scale = np.array([1.0 / WGS84_A, 1.0 / WGS84_A, 1.0 / WGS84_B])
    p, eye = p * scale, eye * scale
    r = 1.0 - relief / WGS84_A
    d = p - eye
    dd = np.einsum("...k,...k->...", d, d)
    t = np.clip(-np.einsum("...k,k->...", d, eye) / np.maximum(dd, 1e-30), 0.0, 1.0)
    closest = eye + t[..., None] * d
    out: NDArray[np.bool_] = (np.einsum("...k,...k->...", closest, closest) < r * r) & (
        t < 1.0 - 1e-12
    )
    return out


def select_tiles(
    camera: Camera,
    max_zoom: int,
    *,
    min_zoom: int = 0,
    band: float = 384.0,
    max_tiles: int = 4096,
    relief: float = 2000.0,
) -> TileSelection:
    """The imagery tiles ``camera`` needs: split while a tile covers more than ``band`` pixels
    (1.5× a 256-pixel tile, paper 000's band) and ``max_zoom`` allows, and always down to
    ``min_zoom``; ``max_tiles`` bounds the walk (the coarser tiles are kept when it is hit);
    ``relief``: the highest ground (metres) that may rise into view from beyond the horizon."""
    eye = camera.position
    camera_merc = tuple(float(v) for v in lonlat_to_merc(camera.lon, camera.lat))
    planes = camera.frustum_planes() if camera.near is not None else None
    z = np.zeros(1, np.int64)
    x = np.zeros(1, np.int64)
    y = np.zeros(1, np.int64)
    out: list[tuple[I64, I64, I64, F64, F64]] = []
    count = 0
    for level in range(max_zoom + 1):
        if z.size == 0:
            break
        lon, lat = _samples(z, x, y, (camera_merc[0], camera_merc[1]))  # (T, 10)
        p = geodetic_to_ecef(lon, lat, 0.0)
        # the widest the tile's ground is: at its latitude nearest the equator
        south, north = lat.min(axis=1), lat.max(axis=1)
        nearest_eq = np.where(
            (south <= 0.0) & (north >= 0.0), 0.0, np.minimum(abs(south), abs(north))
        )
        width = 2.0 * math.pi * WGS84_A * np.cos(np.radians(nearest_eq)) / float(1 << level)
        # how far the tile's surface bulges above its sample points' hull, and its relief
        sag = (width * 0.5) ** 2 / (2.0 * WGS84_B) + max(relief, 0.0)
        keep = np.ones(z.size, bool)
        if level >= 2:
            keep &= ~_hidden(p, eye, relief).all(axis=1)
            if planes is not None:
                rel = p - eye
                side = np.einsum("tsk,pk->tsp", rel, planes[:, :3]) + planes[None, None, :, 3]
                keep &= ~(side < -sag[:, None, None]).all(axis=1).any(axis=1)
        dist = np.linalg.norm(p - eye, axis=2).min(axis=1)
        dist = np.maximum(dist, max(camera.alt, 1.0) * 0.5)
        pixels = camera.screen_size(width, dist)
        z, x, y, dist, pixels = z[keep], x[keep], y[keep], dist[keep], pixels[keep]
        split = ((pixels > band) | (level < min_zoom)) & (level < max_zoom)
        if count + int((~split).sum()) + 4 * int(split.sum()) > max_tiles:
            split[:] = False  # the walk's bound: these tiles are drawn as they are
        leaf = ~split
        out.append((z[leaf], x[leaf], y[leaf], dist[leaf], pixels[leaf]))
        count += int(leaf.sum())
        z, x, y = children_array(z[split], x[split], y[split])
    if not out:
        empty = np.zeros(0, np.int64)
        return TileSelection(empty, empty, empty, np.zeros(0), np.zeros(0))
    cols = [np.concatenate([o[i] for o in out]) for i in range(5)]
    return TileSelection(cols[0], cols[1], cols[2], cols[3], cols[4])


def resident_ancestors(z: I64, x: I64, y: I64, layer: int, resident: NDArray[np.uint64]) -> I64:
    """Per tile, how many levels up its nearest ancestor with a resident image (``resident``:
    sorted texture keys) is: 0 for the tile's own, -1 where no ancestor has one."""
    up = np.full(z.size, -1, np.int64)
    if resident.size == 0:
        return up
    for k in range(int(z.max(initial=-1)) + 1):
        todo = (up < 0) & (z >= k)
        if not todo.any():
            break
        keys = texture_key_array(tile_id_array(z[todo] - k, x[todo] >> k, y[todo] >> k), layer)
        i = np.searchsorted(resident, keys)
        hit = (i < resident.size) & (resident[np.minimum(i, resident.size - 1)] == keys)
        idx = np.nonzero(todo)[0]
        up[idx[hit]] = k
    return up


def patches(z: I64, x: I64, y: I64, n: int, *, grow: float = 0.0) -> tuple[F64, F64, F64, F64]:
    """Each tile's surface as an (n+1)² grid: lon, lat (T, n+1, n+1), and its Web Mercator
    coordinates; ``grow`` widens each tile by that share of its size on every side (so that
    neighbouring patches overlap and cover every pixel between them), within the square."""
    left, _bottom, right, top = bounds_array(z, x, y)
    size = (right - left)[:, None, None]
    f = np.linspace(-grow, 1.0 + grow, n + 1)
    mx = left[:, None, None] + size * f[None, None, :]
    my = top[:, None, None] - size * f[None, :, None]
    mx, my = np.broadcast_arrays(mx, my)
    my = np.clip(my, -ORIGIN, ORIGIN)
    lon, lat = merc_to_lonlat(mx, my)
    return lon, lat, np.ascontiguousarray(mx), np.ascontiguousarray(my)
