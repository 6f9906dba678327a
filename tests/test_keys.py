"""The resource key scheme: scalar and array functions agree, and keys round-trip."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lodscape.geo import keys
from lodscape.geo.tiles import MAX_ZOOM, Tile, tile_id


@st.composite
def tiles(draw: st.DrawFn) -> Tile:
    z = draw(st.integers(0, MAX_ZOOM))
    n = (1 << z) - 1
    return Tile(draw(st.integers(0, n)), draw(st.integers(0, n)), z)


@given(tiles(), st.integers(0, keys.MAX_GRIDS - 1))
def test_mesh_keys_round_trip(t: Tile, grid: int) -> None:
    k = keys.tile_mesh_key(t, grid)
    assert keys.tile_of(k) == t
    assert keys.grid_of(k) == grid
    assert not keys.is_texture(k)
    arr = keys.mesh_key_array([tile_id(t)], [grid])
    assert int(arr[0]) == k
    assert int(keys.grid_of_array(arr)[0]) == grid
    assert not keys.is_texture_array(arr)[0]
    assert int(keys.mesh_keys_zxy([t.z], [t.x], [t.y], [grid])[0]) == k


@given(tiles())
def test_texture_keys_round_trip(t: Tile) -> None:
    k = keys.tile_texture_key(t)
    assert keys.tile_of(k) == t
    assert keys.is_texture(k)
    assert keys.tile_id_of(k) == tile_id(t)
    assert int(keys.texture_keys_zxy([t.z], [t.x], [t.y])[0]) == k
    assert bool(keys.is_texture_array(np.array([k], np.uint64))[0])
    # a tile's texture and its meshes never share a key
    assert k not in {keys.tile_mesh_key(t, g) for g in range(keys.MAX_GRIDS)}


def test_bad_grid_and_texture_as_mesh_are_refused() -> None:
    with pytest.raises(ValueError, match="grid index"):
        keys.mesh_key(5, keys.MAX_GRIDS)
    with pytest.raises(ValueError, match="texture key"):
        keys.grid_of(keys.texture_key(5))


@given(tiles(), st.integers(0, keys.MAX_LAYERS))
def test_layer_keys_round_trip(t: Tile, layer: int) -> None:
    k = keys.tile_texture_key(t, layer)
    assert keys.is_texture(k)
    assert keys.layer_of(k) == layer
    assert keys.tile_of(k) == t
    arr = keys.texture_keys_zxy([t.z], [t.x], [t.y], layer)
    assert int(arr[0]) == k
    assert int(keys.layer_of_array(arr)[0]) == layer
    # layers never share keys with each other nor with meshes
    others = {keys.tile_texture_key(t, j) for j in range(keys.MAX_LAYERS + 1) if j != layer}
    assert k not in others | {keys.tile_mesh_key(t, g) for g in range(keys.MAX_GRIDS)}


def test_bad_layers_are_refused() -> None:
    with pytest.raises(ValueError, match="layer"):
        keys.texture_key(5, keys.MAX_LAYERS + 1)
    with pytest.raises(ValueError, match="mesh key"):
        keys.layer_of(keys.mesh_key(5, 0))
