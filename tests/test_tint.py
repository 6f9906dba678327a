"""Tint imagery: hypsometric colour × Horn hillshade, sampled at texel centres without seams."""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from lodscape.geo.tiles import Bbox, Tile, merc_to_lonlat, xy_bounds
from lodscape.imagery import TintImagery
from lodscape.imagery.tint import NODATA_GREY, hillshade, ramp, tint

tint_module = importlib.import_module("lodscape.imagery.tint")

Z, X, Y = 12, 2130, 1420  # a tile of about 6.4 km around 47° N
T = 32  # small textures keep the tests fast; the geometry does not depend on the size

Field = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]
Mask = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.bool_]]


def grid(bounds: Bbox, shape: tuple[int, int]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Vertex coordinates of the source protocol: row 0 north, both edges of ``bounds`` included."""
    rows, cols = shape
    xs = bounds.left + np.arange(cols) * (bounds.right - bounds.left) / (cols - 1)
    ys = bounds.top - np.arange(rows) * (bounds.top - bounds.bottom) / (rows - 1)
    return np.meshgrid(xs, ys)


class FakeSource:
    """Heights of an analytic field, optionally with a no-data region; records every read."""

    def __init__(self, field: Field, invalid: Mask | None = None) -> None:
        self.field = field
        self.invalid = invalid
        self.reads: list[tuple[Bbox, tuple[int, int]]] = []

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        self.reads.append((bounds, shape))
        x, y = grid(bounds, shape)
        h = self.field(x, y).astype(np.float32)
        valid = np.ones(shape, dtype=bool) if self.invalid is None else ~self.invalid(x, y)
        return h, valid

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        xb, yb = np.broadcast_arrays(xm, ym)
        return np.ones(xb.shape, dtype=bool) if self.invalid is None else ~self.invalid(xb, yb)


def centre() -> tuple[float, float]:
    b = xy_bounds(Tile(X, Y, Z))
    return 0.5 * (b.left + b.right), 0.5 * (b.bottom + b.top)


def plane(dx: float, dy: float, h0: float = 1000.0) -> Field:
    """h = h0 + dx·(x - cx) + dy·(y - cy) in metres per Web Mercator metre."""
    cx, cy = centre()
    return lambda x, y: h0 + dx * (x - cx) + dy * (y - cy)


def cone(peak: float = 2500.0, slope: float = 0.2) -> Field:
    cx, cy = centre()
    return lambda x, y: peak - slope * np.hypot(x - cx, y - cy)


def hill_on_seam() -> Field:
    """A smooth hill centred on the seam between tile X and X+1: its shade changes there."""
    b = xy_bounds(Tile(X, Y, Z))
    sx, sy = b.right, 0.5 * (b.bottom + b.top)
    return lambda x, y: 300.0 + 2000.0 * np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / 2500.0**2)


def saturation(rgb: NDArray[np.uint8]) -> NDArray[np.float64]:
    c = rgb.astype(np.float64)
    mx, mn = c.max(axis=-1), c.min(axis=-1)
    return np.where(mx > 0, (mx - mn) / np.maximum(mx, 1.0), 0.0)


# --- shapes and determinism ----------------------------------------------------------------


def test_texture_shape_dtype_and_default_size() -> None:
    src = FakeSource(cone())
    img = TintImagery(src, (0.0, 3000.0)).rgb(Z, X, Y)
    assert img.shape == (256, 256, 3)
    assert img.dtype == np.uint8
    assert src.reads[-1][1] == (258, 258)
    assert TintImagery.tile_size == 256


def test_tint_shape_and_dtype() -> None:
    h = np.zeros((7, 7), np.float32)
    out = tint(h, np.ones_like(h, dtype=bool), 10.0, (0.0, 1.0))
    assert out.shape == (5, 5, 3)
    assert out.dtype == np.uint8


def test_deterministic() -> None:
    imagery = TintImagery(FakeSource(cone()), (0.0, 3000.0), tile_size=T)
    a = imagery.rgb(Z, X, Y)
    b = imagery.rgb(Z, X, Y)
    assert a.tobytes() == b.tobytes()


# --- geometry ------------------------------------------------------------------------------


def test_reads_vertices_on_texel_centres_with_a_border() -> None:
    src = FakeSource(plane(0.0, 0.0))
    TintImagery(src, (0.0, 1.0), tile_size=T).rgb(Z, X, Y)
    bounds, shape = src.reads[-1]
    assert shape == (T + 2, T + 2)
    xs, ys = grid(bounds, shape)
    b = xy_bounds(Tile(X, Y, Z))
    w = (b.right - b.left) / T
    k = np.arange(-1, T + 1)  # texel index including the border ring
    np.testing.assert_allclose(xs[0], b.left + (k + 0.5) * w, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ys[:, 0], b.top - (k + 0.5) * w, rtol=0, atol=1e-6)


def test_each_texel_gets_the_height_of_its_centre(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: dict[str, Any] = {}

    def spy(heights: NDArray[np.float32], valid: NDArray[np.bool_], *a: Any, **kw: Any) -> Any:
        seen["h"] = heights
        return tint(heights, valid, *a, **kw)

    monkeypatch.setattr(tint_module, "tint", spy)
    b = xy_bounds(Tile(X, Y, Z))
    # heights linear in x and y with distinct rates; 1e-3 keeps float32 precise to millimetres
    src = FakeSource(lambda x, y: 1e-3 * (x - b.left) + 3e-3 * (b.top - y))
    TintImagery(src, (0.0, 100.0), tile_size=T).rgb(Z, X, Y)
    w = (b.right - b.left) / T
    j = np.arange(T)
    expect = 1e-3 * (j[None, :] + 0.5) * w + 3e-3 * (j[:, None] + 0.5) * w
    np.testing.assert_allclose(seen["h"][1:-1, 1:-1], expect, rtol=0, atol=1e-3)


def test_texel_size_is_web_mercator_scaled() -> None:
    imagery = TintImagery(FakeSource(cone()), (0.0, 1.0), tile_size=T)
    b = xy_bounds(Tile(X, Y, Z))
    _, lat = merc_to_lonlat(0.0, 0.5 * (b.top + b.bottom))
    expect = (b.right - b.left) / T * math.cos(math.radians(float(lat)))
    assert imagery.texel_size_m(Z, X, Y) == pytest.approx(expect)
    assert 0.6 < imagery.texel_size_m(Z, X, Y) / ((b.right - b.left) / T) < 0.75  # ~47° N


# --- shading -------------------------------------------------------------------------------


def test_flat_surface_is_uniform_with_shade_sin_altitude() -> None:
    h = np.full((10, 10), 500.0, np.float32)
    np.testing.assert_allclose(hillshade(h, 30.0), math.sin(math.radians(45.0)))
    np.testing.assert_allclose(hillshade(h, 30.0, altitude=30.0), 0.5)
    img = TintImagery(FakeSource(plane(0.0, 0.0)), (0.0, 3000.0), tile_size=T).rgb(Z, X, Y)
    assert (img == img[0, 0]).all()


def test_slope_facing_the_sun_is_brighter() -> None:
    # rising to the south-east, so the face looks north-west, towards the default sun (315°)
    nw = TintImagery(FakeSource(plane(0.3, -0.3)), (0.0, 3000.0), tile_size=T).rgb(Z, X, Y)
    se = TintImagery(FakeSource(plane(-0.3, 0.3)), (0.0, 3000.0), tile_size=T).rgb(Z, X, Y)
    # the planes share their centre height, so compare the centre texels' colour
    c = T // 2
    assert nw[c, c].astype(int).sum() > se[c, c].astype(int).sum() + 60


def test_hillshade_matches_horn_on_a_plane() -> None:
    # a plane rising east with gradient 1 faces west, tilted 45°: a sun due west at 45° lights it
    # head-on (shade 1); a sun due east at 45° grazes it exactly (shade 0)
    s = 10.0
    x = np.arange(6) * s
    h = np.broadcast_to(x, (6, 6)).astype(np.float32)
    np.testing.assert_allclose(hillshade(h, s, azimuth=270.0), 1.0, atol=1e-7)
    np.testing.assert_allclose(hillshade(h, s, azimuth=90.0), 0.0, atol=1e-7)
    # the z factor exaggerates: sun from the north sees a plane rising east dim as it steepens
    assert hillshade(h, s, azimuth=0.0, z_factor=2.0)[0, 0] < hillshade(h, s, azimuth=0.0)[0, 0]


def test_cone_is_lit_on_its_north_west_flank() -> None:
    img = TintImagery(FakeSource(cone()), (0.0, 3000.0), tile_size=T).rgb(Z, X, Y)
    lum = img.astype(int).sum(axis=-1)
    q = T // 4
    assert lum[q, q] > lum[T - 1 - q, T - 1 - q] + 60  # north-west quarter vs south-east


# --- colour and no-data --------------------------------------------------------------------


def test_invalid_texels_are_grey_valid_keep_ramp_colour() -> None:
    cx, _ = centre()
    # height at 15 % of the range: the saturated light-green stop; no data west of the centre
    src = FakeSource(plane(0.0, 0.0, 150.0), invalid=lambda x, y: x < cx)
    img = TintImagery(src, (0.0, 1000.0), tile_size=T).rgb(Z, X, Y)
    sat = saturation(img)
    west, east = sat[:, : T // 2 - 1], sat[:, T // 2 + 1 :]
    assert west.max() < 0.03
    assert east.min() > 0.3
    light = 0.35 + 0.65 * math.sin(math.radians(45.0))
    np.testing.assert_allclose(img[0, 0], round(NODATA_GREY * light), atol=1)
    np.testing.assert_allclose(img[0, -1], np.rint(ramp(0.15) * light), atol=1)


def test_equal_range_does_not_divide_by_zero() -> None:
    with np.errstate(all="raise"):
        img = TintImagery(FakeSource(cone()), (700.0, 700.0), tile_size=T).rgb(Z, X, Y)
    assert img.shape == (T, T, 3)
    flat = tint(np.full((5, 5), 700.0, np.float32), np.ones((5, 5), bool), 10.0, (700.0, 700.0))
    assert (flat == flat[0, 0]).all()


@pytest.mark.parametrize(("h", "t"), [(-500.0, 0.0), (5000.0, 1.0)])
def test_out_of_range_heights_are_clamped(h: float, t: float) -> None:
    ones = np.ones((5, 5), bool)
    out = tint(np.full((5, 5), h, np.float32), ones, 10.0, (0.0, 3000.0))
    edge = tint(np.full((5, 5), 3000.0 * t, np.float32), ones, 10.0, (0.0, 3000.0))
    np.testing.assert_array_equal(out, edge)


def test_ramp_is_continuous_and_ordered_from_green_to_white() -> None:
    t = np.linspace(0.0, 1.0, 1001)
    c = ramp(t)
    assert np.abs(np.diff(c, axis=0)).max() < 2.0  # no jumps between close heights
    lo, hi = ramp(0.0), ramp(1.0)
    assert lo[1] > lo[0]  # green at the foot
    assert lo[1] > lo[2]
    assert hi.min() > 240  # near-white at the top


def test_rejects_bad_inputs() -> None:
    h = np.zeros((6, 6), np.float32)
    ok = np.ones((6, 6), bool)
    with pytest.raises(ValueError, match="shape"):
        tint(np.zeros((6, 5), np.float32), np.ones((6, 5), bool), 1.0, (0.0, 1.0))
    with pytest.raises(ValueError, match="valid"):
        tint(h, ok[:5], 1.0, (0.0, 1.0))
    with pytest.raises(ValueError, match="texel size"):
        tint(h, ok, 0.0, (0.0, 1.0))
    with pytest.raises(ValueError, match="height range"):
        tint(h, ok, 1.0, (2.0, 1.0))
    with pytest.raises(ValueError, match="tile size"):
        TintImagery(FakeSource(cone()), (0.0, 1.0), tile_size=0)


def test_non_finite_heights_become_no_data() -> None:
    h = np.full((6, 6), 100.0, np.float32)
    h[3, 3] = np.nan
    out = tint(h, np.ones((6, 6), bool), 10.0, (0.0, 1000.0))
    assert saturation(out)[2, 2] < 0.03  # texel (2, 2) is grid (3, 3)
    assert saturation(out)[0, 0] > 0.3


# --- seams ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field",
    [
        pytest.param(plane(0.05, 0.02, 400.0), id="plane"),
        pytest.param(hill_on_seam(), id="hill"),
    ],
)
def test_adjacent_tiles_have_no_seam(field: Field) -> None:
    imagery = TintImagery(FakeSource(field), (0.0, 2500.0), tile_size=T)
    west = imagery.rgb(Z, X, Y).astype(int)
    east = imagery.rgb(Z, X + 1, Y).astype(int)
    both = np.concatenate([west, east], axis=1)
    steps = np.abs(np.diff(both, axis=1)).max(axis=(0, 2))
    seam = steps[T - 1]  # between the west tile's last column and the east tile's first
    inside = np.delete(steps, T - 1)
    assert seam <= inside.max() + 1


def test_alpha_marks_where_the_source_covers_the_tile() -> None:
    cx, _ = centre()
    src = FakeSource(lambda x, y: 0.0 * x + 100.0, invalid=lambda x, y: x > cx)
    img = TintImagery(src, (0.0, 1000.0), tile_size=T).texture(Z, X, Y)
    assert img.shape == (T, T, 4)
    assert np.all(img[:, : T // 2, 3] == 255)
    assert np.all(img[:, T // 2 :, 3] == 0)
    assert np.array_equal(img[..., :3], TintImagery(src, (0.0, 1000.0), tile_size=T).rgb(Z, X, Y))
