"""The semantic classes a dataset's label pass writes (``Renderer.draw_labels``), one byte a
pixel: what is drawn there, from the land cover (ground) and the city (objects)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["LABELS", "ground_labels", "object_label"]

SKY = 0
TERRAIN = 1
WATER = 2
BUILDING = 3
ROAD = 4
VEGETATION = 5
STREET_FURNITURE = 6
#: The ellipsoid drawn where the terrain has no data: not ground anyone measured.
NO_DATA = 255

#: Label value → name (the legend written with every dataset).
LABELS: dict[int, str] = {
    SKY: "sky",
    TERRAIN: "terrain",
    WATER: "water",
    BUILDING: "building",
    ROAD: "road",
    VEGETATION: "vegetation",
    STREET_FURNITURE: "street_furniture",
    NO_DATA: "no_data",
}

#: Land-cover classes (``imagery.landcover.CLASSES``) that are not plain terrain.
_GROUND = {
    "farmland": VEGETATION,
    "grass": VEGETATION,
    "forest": VEGETATION,
    "wetland": VEGETATION,
    "water": WATER,
    "paved": ROAD,
    "road": ROAD,
}
#: Street-object kinds (``city.osm``) that are not furniture.
_OBJECTS = {"tree": VEGETATION}


def ground_labels(classes: tuple[str, ...] | None) -> NDArray[np.float32]:
    """The label of each land-cover class value (16 slots; None: imagery, all terrain)."""
    out = np.full(16, TERRAIN, np.float32)
    for i, name in enumerate(classes or ()):
        out[i] = _GROUND.get(name, TERRAIN)
    return out


def object_label(kind: str | None) -> int:
    """A city object's label: None for a building, else its street-object kind."""
    return BUILDING if kind is None else _OBJECTS.get(kind, STREET_FURNITURE)
