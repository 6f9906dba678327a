"""Resource keys: one integer names each thing a tile streams (a mesh at one of its grids, its
texture), so caches, the GPU stage and the selection share one key space.

A key is ``tile_id << 3 | slot``: slots ``0 .. len(grids) - 1`` are the tile's mesh grids
(coarsest first), slot 7 (``TEXTURE``) its texture. The GPU terrain mode's height texture is
made from a mesh and lives under that mesh's key. Scalar functions take and return ``int``; the
``*_array`` versions take and return numpy arrays of ``uint64``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.geo.tiles import Tile, tile_from_id, tile_id, tile_id_array

__all__ = [
    "MAX_GRIDS",
    "TEXTURE",
    "grid_of",
    "grid_of_array",
    "is_texture",
    "is_texture_array",
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

#: The slot of a tile's texture; slots below it are the tile's mesh grids.
TEXTURE = 7
#: How many mesh grids a tile can have (the slots below ``TEXTURE``).
MAX_GRIDS = TEXTURE
_BITS = 3
_SHIFT = np.uint64(_BITS)
_SLOT = np.uint64(TEXTURE)


def mesh_key(tid: int, grid: int) -> int:
    """The key of tile ``tid``'s mesh at grid index ``grid``."""
    if not 0 <= grid < MAX_GRIDS:
        raise ValueError(f"Expected a grid index in 0..{MAX_GRIDS - 1}, got {grid}")
    return (tid << _BITS) | grid


def texture_key(tid: int) -> int:
    """The key of tile ``tid``'s texture."""
    return (tid << _BITS) | TEXTURE


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
    return key & TEXTURE


def mesh_key_array(ids: ArrayLike, grids: ArrayLike) -> NDArray[np.uint64]:
    return (np.asarray(ids, dtype=np.uint64) << _SHIFT) | np.asarray(grids).astype(np.uint64)


def texture_key_array(ids: ArrayLike) -> NDArray[np.uint64]:
    return (np.asarray(ids, dtype=np.uint64) << _SHIFT) | _SLOT


def tile_id_of_array(keys: ArrayLike) -> NDArray[np.uint64]:
    return np.asarray(keys, dtype=np.uint64) >> _SHIFT


def is_texture_array(keys: ArrayLike) -> NDArray[np.bool_]:
    out: NDArray[np.bool_] = (np.asarray(keys, dtype=np.uint64) & _SLOT) == _SLOT
    return out


def grid_of_array(keys: ArrayLike) -> NDArray[np.int64]:
    """Slots of mesh keys (7 for texture keys: mask them with ``is_texture_array``)."""
    return (np.asarray(keys, dtype=np.uint64) & _SLOT).astype(np.int64)


def tile_mesh_key(t: Tile, grid: int) -> int:
    """The key of tile ``t``'s mesh at grid index ``grid``."""
    return mesh_key(tile_id(t), grid)


def tile_texture_key(t: Tile) -> int:
    """The key of tile ``t``'s texture."""
    return texture_key(tile_id(t))


def texture_keys_zxy(z: ArrayLike, x: ArrayLike, y: ArrayLike) -> NDArray[np.uint64]:
    """Texture keys of tiles (z, x, y)."""
    return texture_key_array(tile_id_array(z, x, y))


def mesh_keys_zxy(z: ArrayLike, x: ArrayLike, y: ArrayLike, grids: ArrayLike) -> NDArray[np.uint64]:
    """Mesh keys of tiles (z, x, y) at grid indices ``grids``."""
    return mesh_key_array(tile_id_array(z, x, y), grids)
