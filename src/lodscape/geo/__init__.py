"""Tile ids and bounds (OSM z/x/y, quadkeys) and coordinate frames. No IO, no GL."""

from lodscape.geo import frames, tiles
from lodscape.geo.tiles import Bbox, Tile

__all__ = ["Bbox", "Tile", "frames", "tiles"]
