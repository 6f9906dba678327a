"""Tile math: round trips (hypothesis), a reference implementation (mercantile), array = scalar."""

from __future__ import annotations

import math

import mercantile
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lodscape.geo import tiles as T
from lodscape.geo.tiles import Tile


@st.composite
def tiles(draw: st.DrawFn, max_z: int = T.MAX_ZOOM) -> Tile:
    z = draw(st.integers(0, max_z))
    n = 1 << z
    return Tile(draw(st.integers(0, n - 1)), draw(st.integers(0, n - 1)), z)


lons = st.floats(-180.0, 179.999999, allow_nan=False)
lats = st.floats(-85.0, 85.0, allow_nan=False)


@given(tiles())
def test_quadkey_round_trip(t: Tile) -> None:
    qk = T.quadkey(t)
    assert len(qk) == t.z
    assert T.quadkey_to_tile(qk) == t
    assert qk == mercantile.quadkey(*t)


@given(tiles())
def test_id_round_trip(t: Tile) -> None:
    assert T.tile_from_id(T.tile_id(t)) == t
    z, x, y = T.tile_from_id_array(T.tile_id_array([t.z], [t.x], [t.y]))
    assert (int(z[0]), int(x[0]), int(y[0])) == (t.z, t.x, t.y)


@given(tiles(max_z=T.MAX_ZOOM - 1))
def test_parent_of_children(t: Tile) -> None:
    kids = T.children(t)
    assert len(set(kids)) == 4
    assert all(T.parent(k) == t for k in kids)
    # children tile their parent exactly
    b = T.xy_bounds(t)
    kb = [T.xy_bounds(k) for k in kids]
    assert min(k.left for k in kb) == b.left
    assert max(k.right for k in kb) == b.right
    assert min(k.bottom for k in kb) == b.bottom
    assert max(k.top for k in kb) == b.top
    assert math.isclose(
        sum((k.right - k.left) * (k.top - k.bottom) for k in kb),
        (b.right - b.left) * (b.top - b.bottom),
        rel_tol=1e-12,
    )


@given(lons, lats, st.integers(0, 24))
def test_point_in_its_tile(lon: float, lat: float, z: int) -> None:
    t = T.tile(lon, lat, z)
    assert t == Tile(*mercantile.tile(lon, lat, z)) or _on_edge(lon, lat, t)
    b = T.bounds(t)
    eps = 1e-9
    assert b.left - eps <= lon <= b.right + eps
    assert b.bottom - eps <= lat <= b.top + eps


def _on_edge(lon: float, lat: float, t: Tile) -> bool:
    b = T.bounds(t)
    return min(abs(lon - b.left), abs(lon - b.right), abs(lat - b.bottom), abs(lat - b.top)) < 1e-9


@given(tiles(max_z=28 - 2))
def test_bounds_match_mercantile(t: Tile) -> None:
    ours = T.xy_bounds(t)
    ref = mercantile.xy_bounds(*t)
    assert np.allclose(ours, ref, rtol=0, atol=1e-6)


@given(lons, lats)
def test_merc_round_trip(lon: float, lat: float) -> None:
    x, y = T.lonlat_to_merc(lon, lat)
    lon2, lat2 = T.merc_to_lonlat(x, y)
    assert math.isclose(float(lon2), lon, abs_tol=1e-9)
    assert math.isclose(float(lat2), lat, abs_tol=1e-9)
    rx, ry = mercantile.xy(lon, lat)
    assert math.isclose(float(x), rx, abs_tol=1e-6)
    assert math.isclose(float(y), ry, abs_tol=1e-6)


@given(tiles(max_z=20))
def test_neighbours_are_mutual(t: Tile) -> None:
    for nb in T.neighbours(t):
        assert t in T.neighbours(nb)
        assert nb.z == t.z
        assert nb != t


def test_array_versions_equal_scalar_over_a_whole_level() -> None:
    z = 5
    n = 1 << z
    y, x = np.mgrid[0:n, 0:n]
    x, y = x.ravel(), y.ravel()
    left, bottom, right, top = T.bounds_array(z, x, y)
    qks = T.quadkeys_array(z, x, y)
    for i in range(0, n * n, 37):
        t = Tile(int(x[i]), int(y[i]), z)
        assert (left[i], bottom[i], right[i], top[i]) == tuple(T.xy_bounds(t))
        assert qks[i] == T.quadkey(t)
    cz, cx, cy = T.children_array(np.full(x.size, z), x, y)
    pz, px, py = T.parent_array(cz, cx, cy)
    assert np.array_equal(px, np.repeat(x, 4))
    assert np.array_equal(py, np.repeat(y, 4))
    assert np.all(pz == z)
    tx, ty = T.tiles_array((left + right) / 2, (bottom + top) / 2, z)
    assert np.array_equal(tx, x)
    assert np.array_equal(ty, y)


@pytest.mark.parametrize(
    ("bad", "message"),
    [(Tile(0, 0, -1), "zoom"), (Tile(2, 0, 1), "outside level 1"), (Tile(0, -1, 3), "outside")],
)
def test_bad_tiles_are_named(bad: Tile, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        T.xy_bounds(bad)


def test_bad_quadkey() -> None:
    with pytest.raises(ValueError, match="quadkey"):
        T.quadkey_to_tile("0124")
    with pytest.raises(ValueError, match="no parent"):
        T.parent(Tile(0, 0, 0))
