"""Terrain: height sources, the tile tree built over them, and tile meshes."""

from lodscape.terrain.source import ArraySource, HeightSource, RasterSource

__all__ = ["ArraySource", "HeightSource", "RasterSource"]
