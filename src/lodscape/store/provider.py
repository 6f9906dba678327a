"""Providers: what a Scene streams from. A raster meshed on the fly and a prebuilt tileset sit
behind the same small protocol (ARCHITECTURE: one provider protocol for both).

Every method but ``close`` is safe to call from worker threads; none touches the GPU.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from typing import Any, Protocol, cast

import numpy as np
from numpy.typing import NDArray

from lodscape._lru import ByteLRU
from lodscape.geo.keys import MAX_LAYERS, grid_of, is_texture, layer_of, tile_id_of, tile_of
from lodscape.geo.tiles import ORIGIN, Bbox, lonlat_to_merc, merc_to_lonlat, tile_size
from lodscape.imagery import TintImagery
from lodscape.imagery.sources import ImageryError
from lodscape.terrain.fractal import MAX_LEVEL
from lodscape.terrain.lazy import open_tree
from lodscape.terrain.mesh import TileMesh, build_mesh, grid_coordinates
from lodscape.terrain.pyramid import RefinedTree, TileTree
from lodscape.terrain.source import Fill, HeightSource
from lodscape.terrain.tin_tiles import ErrorLadder, SplitBeforeFinest, TinTile

__all__ = [
    "FractalProvider",
    "LandcoverProvider",
    "LayeredProvider",
    "Provider",
    "RasterProvider",
    "RefinedProvider",
]


class Provider(Protocol):
    """A terrain a Scene can draw: its tile tree, and each tile's mesh and texture on demand."""

    #: For messages: the path, or "array".
    name: str
    tree: TileTree
    #: Footprint of the data in EPSG:3857 metres.
    bounds_merc: Bbox
    #: What texture keys decode to: "imagery" (RGBA pixels) or "landcover" (class masks).
    textures: str
    #: Imagery layers over the terrain's own texture (``imagery.layers.ImageryLayer``), bottom
    #: to top; their tiles are texture keys of layers 1.. (``geo.keys``).
    layers: tuple[Any, ...]
    #: Every key comes over the network (a terrain server): the streamer fetches them on its
    #: network threads, so a slow server never holds the meshing workers.
    network: bool

    @property
    def texture_levels(self) -> tuple[int, ...]:
        """The finest level of the terrain's own texture, then of each imagery layer."""
        ...

    def ground_height(self, lon: float, lat: float) -> float | None:
        """Terrain height at a point, or None outside the data."""
        ...

    def heights_at(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        """Terrain heights at many points (degrees), NaN outside the data."""
        ...

    @property
    def resolution_merc(self) -> float | None:
        """The data's cell size in EPSG:3857 metres (None: not known)."""
        ...

    def city(self) -> Any:
        """The cities the source stores (a tileset's ``lodscape city add``) as one
        ``city.osm.City``, or None."""
        ...

    def fetch(self, key: int) -> bytes:
        """The stored form of one resource key (``geo.keys``): what the disk or the
        network gives, what the streamer's cache stage holds."""
        ...

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        """The fetched bytes made ready to upload: a mesh, or a (T, T, 4) RGBA texture (alpha
        0 where there is no data)."""
        ...

    def mesh(self, key: int) -> TileMesh:
        """fetch and decode of a mesh key."""
        ...

    def texture(self, key: int) -> NDArray[np.uint8]:
        """fetch and decode of a texture key."""
        ...

    def close(self) -> None: ...


def _same_blocks(a: NDArray[np.float64] | None, b: NDArray[np.float64] | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return bool(np.array_equal(a, b))


def mesh_of(provider: Provider, key: int) -> TileMesh:
    """fetch then decode a mesh key (the one-shot path, off the streamer)."""
    made = provider.decode(key, provider.fetch(key))
    if not isinstance(made, TileMesh):
        raise TypeError(f"key {key} is not a mesh key")
    return made


def texture_of(provider: Provider, key: int) -> NDArray[np.uint8]:
    """fetch then decode a texture key."""
    if not is_texture(key):
        raise TypeError(f"key {key} is not a texture key")
    made = provider.decode(key, provider.fetch(key))
    if isinstance(made, TileMesh):
        raise TypeError(f"key {key} is not a texture key")
    return made


def fill_of(source: Any) -> Fill:
    """The fill a (wrapped) height source was opened with; none if it does not say."""
    for _ in range(8):  # wrappers keep the source they wrap as ``source``
        fill = getattr(source, "fill", None)
        if isinstance(fill, Fill):
            return fill
        source = getattr(source, "source", None)
        if source is None:
            break
    return Fill("none")


#: Bytes of the tiles' uncut RTINs (``TinTile``: heights and errors, 51 KB a 65² tile, 200 KB
#: a 129² one) a raster meshed by error keeps, the most recently meshed: a tile cut at another
#: rung (the camera moved) is a cut alone, not heights read and errors measured again. Sized
#: for a frame's tiles on the 2049² fBm's views (300-400, a share of them 129²).
TIN_CACHE_BYTES = 64 << 20


class RasterProvider:
    """A height source meshed on the fly: regular grids per tile, or RTINs cut by error
    (``mesh_by_error``); tint + hillshade imagery."""

    textures = "imagery"
    layers: tuple[Any, ...] = ()
    network = False

    def __init__(
        self, source: HeightSource, tree: Any = None, *, sea_level: float | None = 0.0
    ) -> None:
        self.source = source
        self.name = source.name
        # a large raster's tree is made as the selection reaches it: opening costs what the
        # view needs, not what the file holds
        self.tree: Any = tree if tree is not None else open_tree(source)
        self.bounds_merc = source.bounds_merc
        # where there is no data the terrain is cut (fill none), or the fill stands in: over
        # the raster (nearest), or everywhere the tiles reach (a level or the ellipsoid)
        kind = fill_of(source).kind
        alpha = {"none": "valid", "nearest": "covers"}.get(kind, "all")
        self.imagery = TintImagery(
            source,
            self.tree.height_range,
            tile_size=self.tree.tile_size,
            alpha=alpha,
            sea_level=sea_level,
        )
        # the RTINs of the tiles meshed by error lately, by tile id (fetch and decode run on
        # the loader's workers)
        self._tins: ByteLRU[int, TinTile] = ByteLRU()
        self._tins_lock = threading.Lock()

    def ground_height(self, lon: float, lat: float) -> float | None:
        xm, ym = lonlat_to_merc([lon], [lat])
        h, valid = self.source.sample(xm, ym, self.source.resolution_merc)
        return float(h[0]) if bool(valid[0]) else None

    def heights_at(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        xm, ym = lonlat_to_merc(lon, lat)
        h, ok = self.source.sample(xm, ym, self.source.resolution_merc)
        return np.where(ok, np.asarray(h, np.float64), np.nan)

    def city(self) -> Any:
        return None

    @property
    def resolution_merc(self) -> float | None:
        return float(self.source.resolution_merc)

    @property
    def texture_levels(self) -> tuple[int, ...]:
        z = self.tree.texture_zmax
        return (int(self.tree.zmax if z is None else z),)

    def fetch(self, key: int) -> bytes:
        """A mesh key's sampled heights (float32), or a texture key's RGBA pixels."""
        t = tile_of(key)
        if is_texture(key):
            return self.imagery.texture(t.z, t.x, t.y).tobytes()
        if isinstance(self.tree, ErrorLadder):
            # every ladder slot meshes the same grid: a tile met before has its heights
            with self._tins_lock:
                kept = self._tins.get(tile_id_of(key))
            if kept is not None:
                return kept.data
            segments = self.tree.segments(t.z)
        else:
            segments = self.tree.grids[grid_of(key)]
        xs, ys = grid_coordinates(t.z, t.x, t.y, segments)
        spacing = float(tile_size(t.z)) / segments
        # the protocol's grid sampling projects a lattice and the edges, not every point; a
        # source of the user's own may have ``sample`` alone
        grid = getattr(self.source, "sample_grid", None)
        if grid is not None:
            heights, _ = grid(xs, ys, spacing)
        else:
            heights, _ = self.source.sample(*np.meshgrid(xs, ys), spacing)
        return np.asarray(heights, np.float32).tobytes()

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        t = tile_of(key)
        if is_texture(key):
            n = self.imagery.tile_size
            return np.frombuffer(data, dtype=np.uint8).reshape(n, n, 4)
        if isinstance(self.tree, ErrorLadder):
            bound, blocks = self.tree.cut(t.z, t.x, t.y, grid_of(key))
            tin = self._tin(key, data, blocks)
            made = tin.mesh(key, bound)
            # heights not all finite: the regular grid they were sampled on
            return build_mesh(key, t.z, t.x, t.y, tin.heights) if made is None else made
        s = self.tree.grids[grid_of(key)] + 1
        heights = np.frombuffer(data, dtype=np.float32).reshape(s, s)
        return build_mesh(key, t.z, t.x, t.y, heights)

    def _tin(self, key: int, data: bytes, blocks: NDArray[np.float64] | None) -> TinTile:
        """Tile ``key``'s uncut RTIN of its heights ``data`` and the grid's error ``blocks``
        (``ErrorLadder.cut``): the one kept where it has the same (a rung change), else made
        and kept."""
        tid = tile_id_of(key)
        with self._tins_lock:
            kept = self._tins.get(tid)
        if kept is not None and kept.data == data and _same_blocks(kept.blocks, blocks):
            return kept
        t = tile_of(key)
        data = bytes(data)
        s = self.tree.segments(t.z) + 1
        heights = np.frombuffer(data, dtype=np.float32).reshape(s, s)
        made = TinTile(t.z, t.x, t.y, heights, data, blocks)
        with self._tins_lock:
            self._tins.put(tid, made, made.nbytes)
            self._tins.shrink(TIN_CACHE_BYTES)
        return made

    def mesh_by_error(self) -> None:
        """Mesh tiles as RTINs cut at the error each frame allows (``terrain.tin_tiles``)
        instead of regular grids: the tree's grids become the error ladder's slots. Call
        before anything selects over the tree."""
        if not isinstance(self.tree, ErrorLadder):
            self.tree = ErrorLadder(self.tree)

    def split_before_finest(self) -> None:
        """Draw a tile that can split no finer than its next-to-finest grid: where it needs
        more it splits (``terrain.tin_tiles.SplitBeforeFinest``). Call before anything selects
        over the tree; not with ``mesh_by_error``."""
        if not isinstance(self.tree, ErrorLadder | SplitBeforeFinest):
            self.tree = SplitBeforeFinest(self.tree)

    def mesh(self, key: int) -> TileMesh:
        return mesh_of(self, key)

    def texture(self, key: int) -> NDArray[np.uint8]:
        t = tile_of(key)
        return self.imagery.texture(t.z, t.x, t.y)

    def close(self) -> None:
        closing = getattr(self.tree, "close", None)
        if closing is not None:
            closing()
        self.source.close()


class FractalProvider(RasterProvider):
    """A raster with fractal detail below its resolution, or the procedural planet: meshes of
    exact lattice heights, split along their lowest diagonals below the data (paper 003)."""

    def __init__(self, heights: Any, tree: Any, *, sea_level: float | None = 0.0) -> None:
        super().__init__(heights, tree, sea_level=sea_level)
        self.heights: Any = heights
        self.detail_tree: Any = tree

    def ground_height(self, lon: float, lat: float) -> float | None:
        xm, ym = lonlat_to_merc([lon], [lat])
        finest = 2.0 * ORIGIN / float(1 << MAX_LEVEL)
        h, valid = self.source.sample(xm, ym, finest)
        return float(h[0]) if bool(valid[0]) else None

    def fetch(self, key: int) -> bytes:
        t = tile_of(key)
        if is_texture(key):
            return self.imagery.texture(t.z, t.x, t.y).tobytes()
        segments = self.tree.grids[grid_of(key)]
        return bytes(self.heights.tile(t.z, t.x, t.y, segments).tobytes())

    def mesh_by_error(self) -> None:
        """Keeps its grids: meshes of exact lattice heights split along their lowest
        diagonals (paper 003)."""

    def split_before_finest(self) -> None:
        """Keeps its grids as its detail tree gives them."""

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        t = tile_of(key)
        if is_texture(key):
            return super().decode(key, data)
        g = self.tree.grids[grid_of(key)]
        heights = np.frombuffer(data, dtype=np.float32).reshape(g + 1, g + 1)
        return build_mesh(key, t.z, t.x, t.y, heights, adaptive=self.detail_tree.adaptive(t.z, g))


class _Retextured:
    """A provider over another whose textures it changes: heights, cities and the tree are the
    base's."""

    def __init__(self, base: Provider) -> None:
        self.base = base
        self.name = base.name
        self.tree = base.tree
        self.bounds_merc = base.bounds_merc
        self.layers: tuple[Any, ...] = tuple(base.layers)
        self.network = base.network

    @property
    def texture_levels(self) -> tuple[int, ...]:
        return self.base.texture_levels

    def ground_height(self, lon: float, lat: float) -> float | None:
        return self.base.ground_height(lon, lat)

    def heights_at(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.base.heights_at(lon, lat)

    def city(self) -> Any:
        return self.base.city()

    @property
    def resolution_merc(self) -> float | None:
        return self.base.resolution_merc

    def mesh(self, key: int) -> TileMesh:
        return self.base.mesh(key)


class RefinedProvider(_Retextured):
    """A terrain carried on below its finest level (``terrain.pyramid.RefinedTree``), for
    imagery finer than it: a mesh below the finest level samples the finest stored surface
    (``heights_at``) on its grid. No heights are made up; the data's surface is only cut
    finer, so the imagery can be drawn at its own level."""

    def __init__(self, base: Provider, zmax: int) -> None:
        super().__init__(base)
        self.textures = base.textures
        self._refined = RefinedTree(base.tree, max(int(zmax), int(base.tree.zmax)))
        self.tree = cast(Any, self._refined)

    def fetch(self, key: int) -> bytes:
        t = tile_of(key)
        if is_texture(key) or self._refined.stored(t.z, t.x, t.y):
            return self.base.fetch(key)
        xs, ys = grid_coordinates(t.z, t.x, t.y, self.tree.grids[grid_of(key)])
        xx, yy = np.meshgrid(xs, ys)
        lon, lat = merc_to_lonlat(xx, yy)
        h = self.base.heights_at(lon, lat)
        if np.isnan(h).all():
            h = np.full(h.shape, self.tree.height_range[0])
        else:
            # past the data's edge a skirt-like flat fill at the nearest known height
            h = np.where(np.isnan(h), np.nanmin(h), h)
        return np.asarray(h, np.float32).tobytes()

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        t = tile_of(key)
        if is_texture(key) or self._refined.stored(t.z, t.x, t.y):
            return self.base.decode(key, data)
        s = self.tree.grids[grid_of(key)] + 1
        return build_mesh(key, t.z, t.x, t.y, np.frombuffer(data, np.float32).reshape(s, s))

    def mesh(self, key: int) -> TileMesh:
        return mesh_of(self, key)

    def texture(self, key: int) -> NDArray[np.uint8]:
        return self.base.texture(key)

    def close(self) -> None:
        self.base.close()


class LayeredProvider(_Retextured):
    """A provider with imagery layers over the terrain's own texture: the user's tile servers,
    MBTiles, folders and orthophotos (``imagery.layers.ImageryLayer``), bottom to top, each
    keyed apart (``geo.keys`` layers 1..) and fetched at its own levels, not the terrain's.

    The terrain's texture (layer 0) stays underneath: its alpha says where the terrain has data,
    and it shows wherever the layers above are transparent or failed. A layer tile that cannot
    be had raises (counted and said once by its layer); the frame draws an ancestor's or nothing
    of that layer there.
    """

    textures = "imagery"

    def __init__(
        self, base: Provider, layers: Sequence[Any], *, own_zmax: int | None = None
    ) -> None:
        super().__init__(base)
        if not layers:
            raise ValueError("LayeredProvider needs at least one imagery layer")
        if len(layers) > MAX_LAYERS:
            raise ImageryError(f"at most {MAX_LAYERS} imagery layers, got {len(layers)}")
        self.layers: tuple[Any, ...] = tuple(layers)
        self._own = own_zmax

    @property
    def texture_levels(self) -> tuple[int, ...]:
        own = self._own if self._own is not None else self.base.texture_levels[0]
        return (int(own), *(int(layer.max_zoom) for layer in self.layers))

    def mesh_by_error(self) -> None:
        """The base's meshes by error, if it makes them (its ``decode`` cuts them): the
        imagery over a raster changes its textures, not its meshes."""
        self._base_meshes("mesh_by_error")

    def split_before_finest(self) -> None:
        """The base's grids split before their finest, if it makes them."""
        self._base_meshes("split_before_finest")

    def _base_meshes(self, name: str) -> None:
        call = getattr(self.base, name, None)
        if call is not None:
            call()
            self.tree = self.base.tree

    def fetch(self, key: int) -> bytes:
        if not is_texture(key) or layer_of(key) == 0:
            return self.base.fetch(key)
        t = tile_of(key)
        return bytes(self.layers[layer_of(key) - 1].fetch(t.z, t.x, t.y))

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        if not is_texture(key) or layer_of(key) == 0:
            return self.base.decode(key, data)
        out: NDArray[np.uint8] = self.layers[layer_of(key) - 1].decode(data, self.tree.tile_size)
        return out

    def texture(self, key: int) -> NDArray[np.uint8]:
        return self.base.texture(key) if layer_of(key) == 0 else texture_of(self, key)

    def close(self) -> None:
        try:
            for layer in self.layers:
                layer.close()
        finally:
            self.base.close()


class LandcoverProvider(_Retextured):
    """A provider whose textures are land-cover masks (``imagery.landcover``): per tile one byte
    per texel, the class to paint, and ``NODATA`` where the terrain has no data. The renderer's
    land-cover ground turns them into colour."""

    textures = "landcover"

    def __init__(self, base: Provider, landcover: Any) -> None:
        super().__init__(base)
        self.landcover = landcover

    def fetch(self, key: int) -> bytes:
        if not is_texture(key):
            return self.base.fetch(key)
        from lodscape.imagery.landcover import NODATA

        t = tile_of(key)
        coverage = self.base.texture(key)[..., 3]
        mask = self.landcover.mask(t.z, t.x, t.y, coverage.shape[0])
        mask[coverage < 128] = NODATA
        return bytes(mask.tobytes())

    def decode(self, key: int, data: bytes) -> TileMesh | NDArray[np.uint8]:
        if not is_texture(key):
            return self.base.decode(key, data)
        n = math.isqrt(len(data))
        return np.frombuffer(data, dtype=np.uint8).reshape(n, n, 1).copy()

    def texture(self, key: int) -> NDArray[np.uint8]:
        return texture_of(self, key)

    def close(self) -> None:
        self.base.close()
