"""The city's materials (paper 001): each one colour, one repeating texture and the size in metres
its texture repeats over, packed as the layers of one texture array (an atlas without bleeding at
its tiles' edges, mipmapped as one).

Facade textures repeat once per storey (``LEVEL_HEIGHT``) up the wall and once per window bay
along it, so windows line up with the floors the tags give; walls carry texture coordinates in
metres (along the wall, above its base), roofs and street objects their plan coordinates. The
textures are drawn here from a few rules (window grids, courses, seams, plank and tile rows)
with a little seeded noise: generated materials, not photographs, and the same on every run.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.city.osm import LEVEL_HEIGHT

__all__ = ["MATERIALS", "TEXTURE_SIZE", "Material", "layers"]

#: Texels per side of each layer.
TEXTURE_SIZE = 128
_GLASS = (0.16, 0.20, 0.26)
_FRAME = (0.90, 0.90, 0.88)


@dataclass(frozen=True)
class Material:
    colour: tuple[float, float, float]
    #: The pattern drawn in the layer (see ``_PATTERNS``).
    pattern: str
    #: Metres one repeat of the texture covers: along the surface, up it.
    repeat: tuple[float, float] = (3.0, LEVEL_HEIGHT)


MATERIALS: dict[str, Material] = {
    "plaster": Material((0.86, 0.82, 0.74), "windows"),
    "brick": Material((0.64, 0.33, 0.25), "brick_windows"),
    "stone": Material((0.62, 0.60, 0.56), "stone_windows"),
    "concrete": Material((0.70, 0.70, 0.68), "panel_windows"),
    "glass": Material((0.45, 0.58, 0.66), "curtain_wall"),
    "metal": Material((0.55, 0.57, 0.60), "corrugated", (1.0, 1.0)),
    "wood": Material((0.55, 0.40, 0.26), "planks", (2.0, 1.5)),
    "copper": Material((0.35, 0.60, 0.50), "seams", (1.0, 1.0)),
    "tiles": Material((0.66, 0.30, 0.22), "roof_tiles", (1.2, 1.2)),
    "slate": Material((0.32, 0.34, 0.38), "roof_tiles", (0.8, 0.8)),
    "roofing": Material((0.38, 0.38, 0.40), "grain", (4.0, 4.0)),
    "bark": Material((0.36, 0.26, 0.18), "grain", (1.0, 1.0)),
    "foliage": Material((0.24, 0.45, 0.20), "grain", (2.0, 2.0)),
    "lamp": Material((1.00, 0.95, 0.75), "flat", (1.0, 1.0)),
}
#: A material lodscape does not know (a future tag value) is drawn as this one.
FALLBACK = "plaster"


def material(name: str) -> Material:
    return MATERIALS.get(name, MATERIALS[FALLBACK])


def layers(names: tuple[str, ...] | list[str], size: int = TEXTURE_SIZE) -> NDArray[np.uint8]:
    """(len(names), size, size, 4) RGBA texels, one layer per material, in ``names`` order."""
    out = np.empty((len(names), size, size, 4), np.uint8)
    for i, name in enumerate(names):
        out[i] = _layer(name, size)
    return out


def _layer(name: str, size: int) -> NDArray[np.uint8]:
    m = material(name)
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    # u along the surface, v up it, both 0..1 over one repeat; row 0 of the image is v = 0
    v, u = (np.mgrid[0:size, 0:size] + 0.5) / size
    base = np.asarray(m.colour, np.float64)
    rgb = np.broadcast_to(base, (size, size, 3)).copy()
    # noise, tileable: summed from whole-number frequencies
    noise = np.zeros((size, size))
    for f in (2, 4, 8, 16):
        ph = rng.uniform(0.0, 2.0 * np.pi, 2)
        noise += np.sin(2 * np.pi * f * u + ph[0]) * np.sin(2 * np.pi * f * v + ph[1]) / f
    rgb *= (1.0 + 0.08 * noise)[..., None]
    p = m.pattern

    def line(x: NDArray[np.float64], width: float) -> NDArray[np.bool_]:
        """Within ``width`` of a whole number (a line centred on the repeat's edge)."""
        return np.abs((x + 0.5) % 1.0 - 0.5) < width / 2

    def shade(mask: NDArray[np.bool_], factor: float) -> None:
        rgb[mask] *= factor

    def paint(mask: NDArray[np.bool_], colour: tuple[float, float, float]) -> None:
        rgb[mask] = colour

    if p == "brick_windows":
        rows = 24
        course = np.floor(v * rows)
        offset = (course % 2) * 0.5 / 6
        shade(line(v * rows, 0.16), 0.75)
        shade(line((u + offset) * 6, 0.04), 0.75)
    elif p == "stone_windows":
        shade(line(v * 6, 0.06), 0.8)
        shade(line((u + (np.floor(v * 6) % 2) * 0.25) * 3, 0.03), 0.8)
    elif p == "panel_windows":
        shade(line(u, 0.02) | line(v, 0.02), 0.8)  # the joints between panels
    elif p == "corrugated":
        rgb *= (0.9 + 0.1 * np.cos(2 * np.pi * 8 * u))[..., None]
    elif p == "planks":
        shade(line(v * 8, 0.08), 0.7)
    elif p == "seams":
        shade(line(u * 2, 0.04), 0.75)
    elif p == "roof_tiles":
        rows = 4
        frac = (v * rows) % 1.0
        rgb *= (0.8 + 0.2 * frac)[..., None]
        shade(line((u + (np.floor(v * rows) % 2) * 0.125) * 4, 0.05), 0.8)
    elif p == "curtain_wall":
        rgb[:] = np.asarray(_GLASS) * 1.4 * (1.0 + 0.1 * noise)[..., None]
        paint((v < 0.18), tuple(base * 0.9))  # spandrel at each floor
        paint(line(u * 2, 0.04) | line(v, 0.03), (0.75, 0.77, 0.80))  # mullions
    if p in ("windows", "brick_windows", "stone_windows", "panel_windows", "planks"):
        # one window per bay and storey: sill at 0.9 m, head at 2.2 m of the 3 m storey
        win = (np.abs(u - 0.5) < 0.22) & (v > 0.3) & (v < 0.75)
        frame = (np.abs(u - 0.5) < 0.25) & (v > 0.27) & (v < 0.78) & ~win
        paint(frame, _FRAME)
        glass = np.asarray(_GLASS) * (1.0 + 0.6 * (v - 0.3))[..., None]
        rgb[win] = glass[win]
        paint(win & (np.abs(u - 0.5) < 0.012), _FRAME)  # the mullion
    rgba = np.empty((size, size, 4), np.uint8)
    rgba[..., :3] = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
    rgba[..., 3] = 255
    return rgba
