"""Providers: what a Scene streams from. A raster meshed on the fly and a prebuilt tileset sit
behind the same small protocol (ARCHITECTURE: one provider protocol for both).

Every method but ``close`` is safe to call from worker threads; none touches the GPU.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.tiles import Bbox, lonlat_to_merc, tile_from_id, tile_size
from lodscape.imagery import TintImagery
from lodscape.terrain.mesh import TileMesh, build_mesh, grid_coordinates
from lodscape.terrain.pyramid import TileTree, build_tree
from lodscape.terrain.source import HeightSource

__all__ = ["Provider", "RasterProvider"]


class Provider(Protocol):
    """A terrain a Scene can draw: its tile tree, and each tile's mesh and texture on demand."""

    #: For messages: the path, or "array".
    name: str
    tree: TileTree
    #: Footprint of the data in EPSG:3857 metres.
    bounds_merc: Bbox

    def ground_height(self, lon: float, lat: float) -> float | None:
        """Terrain height at a point, or None outside the data."""
        ...

    def mesh(self, key: int) -> TileMesh:
        """The mesh of one resource key (tile id << 3 | grid index)."""
        ...

    def texture(self, key: int) -> NDArray[np.uint8]:
        """The (T, T, 4) RGBA texture of one texture key; alpha 0 where there is no data."""
        ...

    def close(self) -> None: ...


class RasterProvider:
    """A height source meshed on the fly: regular grids per tile, tint + hillshade imagery."""

    def __init__(self, source: HeightSource, tree: TileTree | None = None) -> None:
        self.source = source
        self.name = source.name
        self.tree = tree if tree is not None else build_tree(source)
        self.bounds_merc = source.bounds_merc
        self.imagery = TintImagery(source, self.tree.height_range, tile_size=self.tree.tile_size)

    def ground_height(self, lon: float, lat: float) -> float | None:
        xm, ym = lonlat_to_merc([lon], [lat])
        h, valid = self.source.sample(xm, ym, self.source.resolution_merc)
        return float(h[0]) if bool(valid[0]) else None

    def mesh(self, key: int) -> TileMesh:
        t = tile_from_id(key >> 3)
        segments = self.tree.grids[key & 7]
        xs, ys = grid_coordinates(t.z, t.x, t.y, segments)
        xx, yy = np.meshgrid(xs, ys)
        heights, _ = self.source.sample(xx, yy, float(tile_size(t.z)) / segments)
        return build_mesh(key, t.z, t.x, t.y, heights)

    def texture(self, key: int) -> NDArray[np.uint8]:
        t = tile_from_id(key >> 3)
        return self.imagery.texture(t.z, t.x, t.y)

    def close(self) -> None:
        self.source.close()
