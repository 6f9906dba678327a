"""Coordinate frames: WGS84 geodetic, Earth-centred Earth-fixed (ECEF) and local east-north-up.

All in float64; the GPU only ever sees positions relative to a tile's or the camera's centre.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "WGS84_A",
    "WGS84_B",
    "WGS84_E2",
    "ecef_to_geodetic",
    "enu_basis",
    "geodetic_to_ecef",
    "up_vector",
]

WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_B = WGS84_A * (1.0 - WGS84_F)
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lon: ArrayLike, lat: ArrayLike, h: ArrayLike) -> NDArray[np.float64]:
    """Degrees and metres above the ellipsoid to ECEF metres; the last axis holds x, y, z."""
    lon_r = np.radians(np.asarray(lon, dtype=np.float64))
    lat_r = np.radians(np.asarray(lat, dtype=np.float64))
    h = np.asarray(h, dtype=np.float64)
    sin_lat, cos_lat = np.sin(lat_r), np.cos(lat_r)
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    x = (n + h) * cos_lat * np.cos(lon_r)
    y = (n + h) * cos_lat * np.sin(lon_r)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(
    xyz: ArrayLike,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """ECEF metres to (lon°, lat°, height m); Bowring's method refined twice (sub-mm on Earth)."""
    p = np.asarray(xyz, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    lon = np.arctan2(y, x)
    r = np.hypot(x, y)
    ep2 = (WGS84_A**2 - WGS84_B**2) / WGS84_B**2
    theta = np.arctan2(z * WGS84_A, r * WGS84_B)
    lat = np.arctan2(
        z + ep2 * WGS84_B * np.sin(theta) ** 3, r - WGS84_E2 * WGS84_A * np.cos(theta) ** 3
    )
    for _ in range(2):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = np.where(
            np.abs(np.cos(lat)) > 1e-9,
            r / np.maximum(np.cos(lat), 1e-300) - n,
            np.abs(z) - WGS84_B,
        )
        lat = np.arctan2(z, r * (1.0 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    h = np.where(
        np.abs(np.cos(lat)) > 1e-9, r / np.maximum(np.cos(lat), 1e-300) - n, np.abs(z) - WGS84_B
    )
    return np.degrees(lon), np.degrees(lat), h


def up_vector(lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
    """The ellipsoid's outward normal (unit, ECEF) at the given geodetic positions."""
    lon_r = np.radians(np.asarray(lon, dtype=np.float64))
    lat_r = np.radians(np.asarray(lat, dtype=np.float64))
    return np.stack(
        np.broadcast_arrays(
            np.cos(lat_r) * np.cos(lon_r), np.cos(lat_r) * np.sin(lon_r), np.sin(lat_r)
        ),
        axis=-1,
    )


def enu_basis(lon: ArrayLike, lat: ArrayLike) -> NDArray[np.float64]:
    """Rows east, north, up (unit ECEF vectors) at each position: shape (..., 3, 3)."""
    lon_r = np.radians(np.asarray(lon, dtype=np.float64))
    lat_r = np.radians(np.asarray(lat, dtype=np.float64))
    sl, cl = np.sin(lon_r), np.cos(lon_r)
    sp, cp = np.sin(lat_r), np.cos(lat_r)
    zero = np.zeros_like(sl * sp)
    east = np.stack(np.broadcast_arrays(-sl, cl, zero), axis=-1)
    north = np.stack(np.broadcast_arrays(-sp * cl, -sp * sl, cp), axis=-1)
    up = np.stack(np.broadcast_arrays(cp * cl, cp * sl, sp), axis=-1)
    return np.stack([east, north, up], axis=-2)
