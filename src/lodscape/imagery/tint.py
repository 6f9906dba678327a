"""The offline default imagery: a hypsometric tint with hillshade, one RGB texture per OSM tile.

Heights are sampled at texel centres with a one-texel border, so Horn's 3×3 gradient is defined for
every texel of the tile and uses the same neighbours as the adjacent tile does: no seams.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.geo.tiles import Bbox, Tile, merc_to_lonlat, xy_bounds

__all__ = [
    "AMBIENT",
    "NODATA_GREY",
    "RAMP",
    "WATER",
    "HeightSourceLike",
    "TintImagery",
    "hillshade",
    "ramp",
    "tint",
]

#: Share of the light that reaches every texel whatever its slope, so shadowed sides keep colour.
AMBIENT = 0.35
#: Colour of texels without data before shading: neutral (zero saturation) so it reads as "none".
NODATA_GREY = 170.0

#: Hypsometric ramp: (normalised height, R, G, B) stops, lowest first.
RAMP: NDArray[np.float64] = np.array(
    [
        [0.00, 46.0, 106.0, 58.0],  # deep green
        [0.15, 104.0, 158.0, 82.0],  # light green
        [0.35, 204.0, 196.0, 128.0],  # yellow-tan
        [0.55, 168.0, 124.0, 78.0],  # brown
        [0.75, 146.0, 136.0, 130.0],  # grey
        [1.00, 248.0, 248.0, 250.0],  # near-white
    ]
)

#: Water below sea level, by depth over the data's deepest: (normalised depth, R, G, B).
WATER: NDArray[np.float64] = np.array(
    [
        [0.00, 150.0, 196.0, 226.0],  # shallows
        [0.25, 80.0, 140.0, 200.0],
        [1.00, 18.0, 44.0, 112.0],  # the deep
    ]
)


class HeightSourceLike(Protocol):
    """Anything that samples heights on a regular vertex grid spanning a Web Mercator box."""

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]: ...


def ramp(t: ArrayLike) -> NDArray[np.float64]:
    """RGB (0..255 floats, shape ``t.shape + (3,)``) of normalised heights ``t`` (clamped)."""
    t = np.clip(np.asarray(t, dtype=np.float64), 0.0, 1.0)
    # piecewise linear per channel: continuous, so neighbouring heights never jump in colour
    return np.stack([np.interp(t, RAMP[:, 0], RAMP[:, k]) for k in (1, 2, 3)], axis=-1)


def hillshade(
    heights: ArrayLike,
    texel_size_m: float,
    *,
    azimuth: float = 315.0,
    altitude: float = 45.0,
    z_factor: float = 1.0,
) -> NDArray[np.float64]:
    """Horn's hillshade (0..1) of the interior of a bordered (T+2, T+2) height grid, row 0 north."""
    h = np.asarray(heights, dtype=np.float64)
    a, b, c = h[:-2, :-2], h[:-2, 1:-1], h[:-2, 2:]
    d, f = h[1:-1, :-2], h[1:-1, 2:]
    g, k, i = h[2:, :-2], h[2:, 1:-1], h[2:, 2:]
    scale = z_factor / (8.0 * texel_size_m)
    # dz/d(east) and dz/d(north); rows grow southwards, hence north = top row minus bottom row
    p = ((c + 2.0 * f + i) - (a + 2.0 * d + g)) * scale
    q = ((a + 2.0 * b + c) - (g + 2.0 * k + i)) * scale
    az, alt = math.radians(azimuth), math.radians(altitude)
    # unit normal (-p, -q, 1)/|.| dotted with the unit vector towards the sun (east, north, up)
    sun_e, sun_n, sun_u = math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt)
    shade = (sun_u - p * sun_e - q * sun_n) / np.sqrt(1.0 + p * p + q * q)
    return np.clip(shade, 0.0, 1.0)


def tint(
    heights: NDArray[np.float32],
    valid: NDArray[np.bool_],
    texel_size_m: float,
    height_range: tuple[float, float],
    *,
    azimuth: float = 315.0,
    altitude: float = 45.0,
    z_factor: float = 1.0,
    sea_level: float | None = 0.0,
    wet: NDArray[np.bool_] | None = None,
) -> NDArray[np.uint8]:
    """(T, T, 3) RGB of a bordered (T+2, T+2) height grid: hypsometric colour × hillshade.

    Heights below ``sea_level`` (when the range reaches below it) are water, shaded by depth
    over the range's deepest, and the land ramp runs from sea level up; None: no sea. ``wet``
    (T+2, T+2) marks more water: the sea a DEM stores at exactly the sea level."""
    h = np.asarray(heights)
    ok = np.asarray(valid, dtype=bool)
    if h.ndim != 2 or h.shape[0] != h.shape[1] or h.shape[0] < 3:
        raise ValueError(f"Expected heights of shape (T+2, T+2) with T >= 1, got {h.shape}")
    if ok.shape != h.shape:
        raise ValueError(f"Expected valid of shape {h.shape}, got {ok.shape}")
    if not (math.isfinite(texel_size_m) and texel_size_m > 0.0):
        raise ValueError(f"Expected a positive texel size in metres, got {texel_size_m}")
    lo, hi = float(height_range[0]), float(height_range[1])
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
        raise ValueError(f"Expected a finite height range lo <= hi, got {height_range}")

    # non-finite heights would poison the shade of all 8 neighbours: flatten them, mark as no data
    finite = np.isfinite(h)
    h64 = np.where(finite, h, lo).astype(np.float64)
    ok = ok & finite

    light = AMBIENT + (1.0 - AMBIENT) * hillshade(
        h64, texel_size_m, azimuth=azimuth, altitude=altitude, z_factor=z_factor
    )
    inner = h64[1:-1, 1:-1]
    sea = sea_level is not None and math.isfinite(sea_level) and lo < sea_level
    land = max(lo, float(sea_level)) if sea and sea_level is not None else lo
    # a single-height dataset (lo == hi) maps to the ramp's foot rather than dividing by zero
    span = hi - land if hi > land else 1.0
    base = ramp((inner - land) / span)
    if sea:
        below = inner < land
        depth = (land - inner[below]) / (land - lo)
        base[below] = np.stack(
            [np.interp(depth, WATER[:, 0], WATER[:, k]) for k in (1, 2, 3)], axis=-1
        )
    if wet is not None and sea_level is not None:
        level = np.asarray(wet, bool)[1:-1, 1:-1]
        base[level] = WATER[0, 1:4]
    base[~ok[1:-1, 1:-1]] = NODATA_GREY
    rgb = base * light[..., None]
    return np.rint(np.clip(rgb, 0.0, 255.0)).astype(np.uint8)


class TintImagery:
    """Imagery source: a tinted, hillshaded texture per OSM tile, computed from a height source."""

    tile_size: int = 256

    def __init__(
        self,
        heights: HeightSourceLike,
        height_range: tuple[float, float],
        tile_size: int = 256,
        *,
        azimuth: float = 315.0,
        altitude: float = 45.0,
        z_factor: float = 1.0,
        alpha: str = "covers",
        sea_level: float | None = 0.0,
    ) -> None:
        """``alpha`` says where the terrain is drawn: ``valid`` where there is data (holes
        and the margins cut out), ``covers`` inside the raster's footprint, ``all`` everywhere
        (a fill stands in); ``sea_level`` as ``tint``'s."""
        if alpha not in ("valid", "covers", "all"):
            raise ValueError(f"Expected alpha valid, covers or all, got {alpha!r}")
        if tile_size < 1:
            raise ValueError(f"Expected a tile size of at least 1 texel, got {tile_size}")
        lo, hi = float(height_range[0]), float(height_range[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
            raise ValueError(f"Expected a finite height range lo <= hi, got {height_range}")
        self.heights = heights
        self.height_range = (lo, hi)
        self.tile_size = tile_size
        self.azimuth = azimuth
        self.altitude = altitude
        self.z_factor = z_factor
        self.alpha = alpha
        self.sea_level = sea_level

    def sample_bounds(self, z: int, x: int, y: int) -> Bbox:
        """The box whose (T+2)² vertex grid lands on the tile's texel centres plus a border ring."""
        b = xy_bounds(Tile(x, y, z))
        # T+2 vertices over the tile expanded by half a texel each side are w/T apart, the first
        # at left - w/(2T): exactly the centres of texel columns -1..T
        half = 0.5 * (b.right - b.left) / self.tile_size
        return Bbox(b.left - half, b.bottom - half, b.right + half, b.top + half)

    def texel_size_m(self, z: int, x: int, y: int) -> float:
        """Ground size of one texel at the tile centre (Web Mercator scales by 1/cos(latitude))."""
        b = xy_bounds(Tile(x, y, z))
        _, lat = merc_to_lonlat(0.0, 0.5 * (b.bottom + b.top))
        return (b.right - b.left) / self.tile_size * math.cos(math.radians(float(lat)))

    def texture(self, z: int, x: int, y: int) -> NDArray[np.uint8]:
        """The (tile_size, tile_size, 4) RGBA texture of tile z/x/y; alpha 0 where the terrain
        is not drawn (``alpha``: where there is no data, or outside the raster)."""
        rgb, valid = self._rgb(z, x, y)
        n = self.tile_size
        if self.alpha == "valid":
            inside = valid[1:-1, 1:-1]
        elif self.alpha == "covers":
            b = self.sample_bounds(z, x, y)
            step = (b.right - b.left) / (n + 1)
            # texel centres: the inner samples of the bordered grid
            xs = b.left + step * np.arange(1, n + 1, dtype=np.float64)
            ys = b.top - step * np.arange(1, n + 1, dtype=np.float64)
            inside = self.heights.covers(xs[None, :], ys[:, None])
        else:
            inside = np.ones((n, n), bool)
        alpha = np.where(inside, 255, 0).astype(np.uint8)
        return np.dstack([rgb, np.broadcast_to(alpha, (n, n))])

    def rgb(self, z: int, x: int, y: int) -> NDArray[np.uint8]:
        """The (tile_size, tile_size, 3) RGB tint of tile z/x/y."""
        return self._rgb(z, x, y)[0]

    def _rgb(self, z: int, x: int, y: int) -> tuple[NDArray[np.uint8], NDArray[np.bool_]]:
        n = self.tile_size + 2
        b = self.sample_bounds(z, x, y)
        heights, valid = self.heights.read(b, (n, n))
        wet = None
        sea_at = getattr(self.heights, "sea_at", None)  # a raster's sea stored as its level
        level = self.sea_level
        if sea_at is not None and level is not None and bool((heights == level).any()):
            xs = np.linspace(b.left, b.right, n)
            ys = np.linspace(b.top, b.bottom, n)
            wet = (heights == level) & valid & sea_at(xs[None, :], ys[:, None], level)
        return tint(
            heights,
            valid,
            self.texel_size_m(z, x, y),
            self.height_range,
            azimuth=self.azimuth,
            altitude=self.altitude,
            z_factor=self.z_factor,
            sea_level=self.sea_level,
            wet=wet,
        ), valid
