"""The OSM zoom/x/y quadtree in Web Mercator (EPSG:3857), aligned 1:1 with OSM imagery tiles.

Scalar functions take and return small immutable values (``Tile``); the ``*_array`` versions take
whole levels as numpy arrays in one call. Tile ``y`` grows southwards, as on OSM tile servers.
"""

from __future__ import annotations

import math
from typing import NamedTuple, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "EARTH_RADIUS",
    "MAX_ZOOM",
    "ORIGIN",
    "Bbox",
    "Tile",
    "bounds",
    "bounds_array",
    "children",
    "children_array",
    "lonlat_to_merc",
    "merc_to_lonlat",
    "neighbours",
    "parent",
    "parent_array",
    "quadkey",
    "quadkey_to_tile",
    "quadkeys_array",
    "tile",
    "tile_from_id",
    "tile_from_id_array",
    "tile_id",
    "tile_id_array",
    "tile_range",
    "tile_size",
    "tiles_array",
    "xy_bounds",
]

#: Web Mercator's sphere radius (metres), as EPSG:3857 defines it.
EARTH_RADIUS = 6378137.0
#: Half the width of the Web Mercator square, metres.
ORIGIN = math.pi * EARTH_RADIUS
#: Deepest level the packed tile ids hold (26 bits for x and y): tiles of about 0.6 m.
MAX_ZOOM = 26
#: Latitude where the Web Mercator square ends.
MAX_LAT = math.degrees(2.0 * math.atan(math.exp(math.pi)) - math.pi / 2.0)


class Tile(NamedTuple):
    """An OSM tile: column ``x``, row ``y`` (from the north), level ``z``."""

    x: int
    y: int
    z: int


class Bbox(NamedTuple):
    """A box (xmin, ymin, xmax, ymax): metres in EPSG:3857, or degrees for lon/lat bounds."""

    left: float
    bottom: float
    right: float
    top: float


def _check(t: Tile) -> None:
    if not 0 <= t.z <= MAX_ZOOM:
        raise ValueError(f"Expected zoom in 0..{MAX_ZOOM}, got {t.z}")
    n = 1 << t.z
    if not (0 <= t.x < n and 0 <= t.y < n):
        raise ValueError(f"Tile {tuple(t)} is outside level {t.z} (x and y must be in 0..{n - 1})")


def tile_size(z: int | NDArray[np.integer]) -> float | NDArray[np.float64]:
    """Width of a tile of level ``z`` in Web Mercator metres."""
    return 2.0 * ORIGIN / np.exp2(z) if isinstance(z, np.ndarray) else 2.0 * ORIGIN / (1 << z)


# --- projections --------------------------------------------------------------------------


def lonlat_to_merc(
    lon: ArrayLike, lat: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Degrees to Web Mercator metres; latitudes are clamped to the square's ±85.0511°."""
    lon = np.asarray(lon, dtype=np.float64)
    lat = np.clip(np.asarray(lat, dtype=np.float64), -MAX_LAT, MAX_LAT)
    x = EARTH_RADIUS * np.radians(lon)
    y = EARTH_RADIUS * np.log(np.tan(np.pi / 4.0 + np.radians(lat) / 2.0))
    return x, y


def merc_to_lonlat(x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Web Mercator metres to degrees."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    lon = np.degrees(x / EARTH_RADIUS)
    lat = np.degrees(2.0 * np.arctan(np.exp(y / EARTH_RADIUS)) - np.pi / 2.0)
    return lon, lat


# --- scalar API ---------------------------------------------------------------------------


def xy_bounds(t: Tile) -> Bbox:
    """The tile's box in Web Mercator metres."""
    _check(t)
    size = 2.0 * ORIGIN / (1 << t.z)
    # each edge from its own integer index, so a parent's and its children's edges are bit-equal
    return Bbox(
        -ORIGIN + t.x * size,
        ORIGIN - (t.y + 1) * size,
        -ORIGIN + (t.x + 1) * size,
        ORIGIN - t.y * size,
    )


def bounds(t: Tile) -> Bbox:
    """The tile's box in longitude/latitude degrees."""
    b = xy_bounds(t)
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    return Bbox(float(w), float(s), float(e), float(n))


def tile(lon: float, lat: float, z: int) -> Tile:
    """The tile of level ``z`` that holds the point (edges belong to the tile east/south)."""
    x, y = lonlat_to_merc(lon, lat)
    tx, ty = tiles_array(x, y, z)
    return Tile(int(tx), int(ty), z)


def parent(t: Tile) -> Tile:
    _check(t)
    if t.z == 0:
        raise ValueError("Tile (0, 0, 0) has no parent")
    return Tile(t.x >> 1, t.y >> 1, t.z - 1)


def children(t: Tile) -> list[Tile]:
    """The four children in quadkey order (NW, NE, SW, SE)."""
    _check(t)
    x, y, z = 2 * t.x, 2 * t.y, t.z + 1
    return [Tile(x, y, z), Tile(x + 1, y, z), Tile(x, y + 1, z), Tile(x + 1, y + 1, z)]


def neighbours(t: Tile) -> list[Tile]:
    """The up to eight tiles of the same level around ``t``; x wraps at the antimeridian."""
    _check(t)
    n = 1 << t.z
    out = []
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            y = t.y + dy
            if (dx, dy) == (0, 0) or not 0 <= y < n:
                continue
            nb = Tile((t.x + dx) % n, y, t.z)
            if nb != t and nb not in out:
                out.append(nb)
    return out


def quadkey(t: Tile) -> str:
    """Bing-style quadkey: one digit 0-3 per level (paper 000, fig. 6b). The root is ''."""
    _check(t)
    digits = []
    for i in range(t.z, 0, -1):
        mask = 1 << (i - 1)
        digits.append(str((1 if t.x & mask else 0) + (2 if t.y & mask else 0)))
    return "".join(digits)


def quadkey_to_tile(qk: str) -> Tile:
    if len(qk) > MAX_ZOOM or any(c not in "0123" for c in qk):
        raise ValueError(f"Expected a quadkey of digits 0-3 (at most {MAX_ZOOM}), got {qk!r}")
    x = y = 0
    for c in qk:
        d = int(c)
        x = (x << 1) | (d & 1)
        y = (y << 1) | (d >> 1)
    return Tile(x, y, len(qk))


def tile_id(t: Tile) -> int:
    """A unique integer for the tile: z in bits 52+, y in bits 26-51, x in bits 0-25."""
    _check(t)
    return (t.z << 52) | (t.y << 26) | t.x


def tile_from_id(i: int) -> Tile:
    return Tile(i & 0x3FFFFFF, (i >> 26) & 0x3FFFFFF, i >> 52)


# --- array API ----------------------------------------------------------------------------

_U = np.uint64


def tile_id_array(z: ArrayLike, x: ArrayLike, y: ArrayLike) -> NDArray[np.uint64]:
    ids = (
        (np.asarray(z, dtype=_U) << _U(52))
        | (np.asarray(y, dtype=_U) << _U(26))
        | np.asarray(x, dtype=_U)
    )
    return cast("NDArray[np.uint64]", ids)


def tile_from_id_array(
    ids: ArrayLike,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """(z, x, y) arrays from packed ids."""
    ids = np.asarray(ids, dtype=_U)
    mask = _U(0x3FFFFFF)
    x = (ids & mask).astype(np.int64)
    y = ((ids >> _U(26)) & mask).astype(np.int64)
    z = (ids >> _U(52)).astype(np.int64)
    return z, x, y


def bounds_array(
    z: ArrayLike, x: ArrayLike, y: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(left, bottom, right, top) arrays in Web Mercator metres for many tiles at once."""
    size = 2.0 * ORIGIN / np.exp2(np.asarray(z, dtype=np.float64))
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    return -ORIGIN + x * size, ORIGIN - (y + 1) * size, -ORIGIN + (x + 1) * size, ORIGIN - y * size


def tiles_array(
    xm: ArrayLike, ym: ArrayLike, z: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Column and row of level ``z`` holding each Web Mercator point (clamped to the square)."""
    n = 1 << z
    size = 2.0 * ORIGIN / n
    # floor of the position in tile units; the clamp keeps the east/south edges of the square in
    tx = np.floor((np.asarray(xm, dtype=np.float64) + ORIGIN) / size).astype(np.int64)
    ty = np.floor((ORIGIN - np.asarray(ym, dtype=np.float64)) / size).astype(np.int64)
    return np.clip(tx, 0, n - 1), np.clip(ty, 0, n - 1)


def tile_range(box: Bbox, z: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """The first and last column, and first and last row (OSM), of level ``z`` that the Web
    Mercator box touches (clamped to the square)."""
    tx, ty = tiles_array([box.left, box.right], [box.top, box.bottom], z)
    return (int(tx[0]), int(tx[1])), (int(ty[0]), int(ty[1]))


def parent_array(
    z: NDArray[np.int64], x: NDArray[np.int64], y: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    return z - 1, x >> 1, y >> 1


def children_array(
    z: NDArray[np.int64], x: NDArray[np.int64], y: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The children of N tiles as arrays of 4N, grouped per parent in quadkey order."""
    cx = (2 * np.asarray(x)[:, None] + np.array([0, 1, 0, 1])).ravel()
    cy = (2 * np.asarray(y)[:, None] + np.array([0, 0, 1, 1])).ravel()
    cz = np.repeat(np.asarray(z) + 1, 4)
    return cz, cx, cy


def quadkeys_array(z: int, x: ArrayLike, y: ArrayLike) -> NDArray[np.str_]:
    """Quadkeys of many tiles of one level."""
    x = np.asarray(x, dtype=np.int64)
    y = np.asarray(y, dtype=np.int64)
    if z == 0:
        return np.full(x.shape, "", dtype="<U1")
    shifts = np.arange(z - 1, -1, -1)
    digits = ((x[..., None] >> shifts) & 1) + 2 * ((y[..., None] >> shifts) & 1)
    chars = (digits + ord("0")).astype(np.uint8)
    return chars.view(f"S{z}").squeeze(-1).astype(f"<U{z}")
