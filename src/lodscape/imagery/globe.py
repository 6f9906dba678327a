"""A generated global image (equirectangular, no data shipped): land and sea from smooth noise on
the sphere (so it has no seam at the antimeridian and no pinch at the poles), coloured by a
latitude ramp with ice towards the poles. Not a map of the Earth: a stand-in where no global
imagery is at hand, the same on every run."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["global_image"]


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
