"""Resource keys: one integer names each thing a tile streams (a mesh at one of its grids, its
texture, an imagery layer's tile), so caches, the GPU stage and the selection share one key
space.

A key is ``tile_id << 5 | slot``: slots ``0 .. len(grids) - 1`` are the tile's mesh grids
(coarsest first; twenty-four at most, the bounds of ``terrain.tin_tiles``' ladder), slot 24
(``TEXTURE``) the terrain's own texture (its tint, or a tileset's stored imagery) and slots
25..31 the tiles of imagery layers 1..7 (``texture_key(tid, layer)``), which come from the
user's imagery at the imagery's own levels. A tile id takes 57 bits (``geo.tiles.tile_id``),
a key 62: keys are in-memory names only, nothing stores them. The GPU terrain mode's height
texture is made from a mesh and lives under that mesh's key. Scalar functions take and return
``int``; the ``*_array`` versions take and return numpy arrays of ``uint64``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.geo.tiles import Tile, tile_from_id, tile_id, tile_id_array

__all__ = [
    "MAX_GRIDS",
    "MAX_LAYERS",
    "TEXTURE",
    "grid_of",
    "grid_of_array",
    "is_overlay",
    "is_texture",
    "is_texture_array",
    "layer_of",
    "layer_of_array",
    "mesh_key",
    "mesh_key_array",
    "mesh_keys_zxy",
    "texture_key",
    "texture_key_array",
    "texture_keys_zxy",
    "tile_id_of",
    "tile_id_of_array",
    "tile_mesh_key",
    "tile_of",
    "tile_texture_key",
]

#: The slot of a tile's own texture (layer 0); slots below it are the tile's mesh grids, the
#: slots above it imagery layers 1..``MAX_LAYERS``.
TEXTURE = 24
#: How many mesh grids a tile can have (the slots below ``TEXTURE``).
MAX_GRIDS = TEXTURE
#: How many imagery layers keys can name above the terrain's own texture.
MAX_LAYERS = 7
_BITS = 5
_SHIFT = np.uint64(_BITS)
_MASK = np.uint64((1 << _BITS) - 1)
_TEX = np.uint64(TEXTURE)


def mesh_key(tid: int, grid: int) -> int:
    """The key of tile ``tid``'s mesh at grid index ``grid``."""
    if not 0 <= grid < MAX_GRIDS:
        raise ValueError(f"Expected a grid index in 0..{MAX_GRIDS - 1}, got {grid}")
    return (tid << _BITS) | grid


def texture_key(tid: int, layer: int = 0) -> int:
    """The key of tile ``tid``'s texture: the terrain's own (layer 0) or imagery layer
    ``layer``'s tile (1..``MAX_LAYERS``)."""
    if not 0 <= layer <= MAX_LAYERS:
        raise ValueError(f"Expected a layer in 0..{MAX_LAYERS}, got {layer}")
    return (tid << _BITS) | (TEXTURE + layer)


def is_overlay(key: int) -> bool:
    """Whether a key is an imagery layer's tile (layer 1 or above)."""
    return key & int(_MASK) > TEXTURE


def layer_of(key: int) -> int:
    """A texture key's layer (0: the terrain's own texture)."""
    if not is_texture(key):
        raise ValueError(f"key {key} is a mesh key, not a texture key")
    return (key & int(_MASK)) - TEXTURE


def tile_id_of(key: int) -> int:
    """The tile id a key belongs to."""
    return key >> _BITS


def tile_of(key: int) -> Tile:
    """The tile a key belongs to."""
    return tile_from_id(key >> _BITS)


def is_texture(key: int) -> bool:
    return key & TEXTURE == TEXTURE


def grid_of(key: int) -> int:
    """A mesh key's grid index."""
    if is_texture(key):
        raise ValueError(f"key {key} is a texture key, not a mesh key")
    return key & int(_MASK)


def mesh_key_array(ids: ArrayLike, grids: ArrayLike) -> NDArray[np.uint64]:
    return (np.asarray(ids, dtype=np.uint64) << _SHIFT) | np.asarray(grids).astype(np.uint64)


def texture_key_array(ids: ArrayLike, layer: int = 0) -> NDArray[np.uint64]:
    if not 0 <= layer <= MAX_LAYERS:
        raise ValueError(f"Expected a layer in 0..{MAX_LAYERS}, got {layer}")
    return (np.asarray(ids, dtype=np.uint64) << _SHIFT) | np.uint64(TEXTURE + layer)


def tile_id_of_array(keys: ArrayLike) -> NDArray[np.uint64]:
    return np.asarray(keys, dtype=np.uint64) >> _SHIFT


def is_texture_array(keys: ArrayLike) -> NDArray[np.bool_]:
    out: NDArray[np.bool_] = (np.asarray(keys, dtype=np.uint64) & _TEX) == _TEX
    return out


def layer_of_array(keys: ArrayLike) -> NDArray[np.int64]:
    """Layers of texture keys (negative for mesh keys: mask them with ``is_texture_array``)."""
    return (np.asarray(keys, dtype=np.uint64) & _MASK).astype(np.int64) - TEXTURE


def grid_of_array(keys: ArrayLike) -> NDArray[np.int64]:
    """Slots of mesh keys (8 or more for texture keys: mask them with ``is_texture_array``)."""
    return (np.asarray(keys, dtype=np.uint64) & _MASK).astype(np.int64)


def tile_mesh_key(t: Tile, grid: int) -> int:
    """The key of tile ``t``'s mesh at grid index ``grid``."""
    return mesh_key(tile_id(t), grid)


def tile_texture_key(t: Tile, layer: int = 0) -> int:
    """The key of tile ``t``'s texture in ``layer``."""
    return texture_key(tile_id(t), layer)


def texture_keys_zxy(
    z: ArrayLike, x: ArrayLike, y: ArrayLike, layer: int = 0
) -> NDArray[np.uint64]:
    """Texture keys of tiles (z, x, y) in ``layer``."""
    return texture_key_array(tile_id_array(z, x, y), layer)


def mesh_keys_zxy(z: ArrayLike, x: ArrayLike, y: ArrayLike, grids: ArrayLike) -> NDArray[np.uint64]:
    """Mesh keys of tiles (z, x, y) at grid indices ``grids``."""
    return mesh_key_array(tile_id_array(z, x, y), grids)
