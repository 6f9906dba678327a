"""The visible region (paper 003's quadrangle made conservative): it never drops a tile that holds
a visible point, and the selection with it equals the selection without it, while it spares
the bounds of tiles out of view."""

from __future__ import annotations

import math

import numpy as np
import pytest

import lodscape
from _synthetic import AnalyticSource
from lodscape.geo.frames import ecef_to_geodetic
from lodscape.geo.tiles import lonlat_to_merc, tiles_array
from lodscape.lod import select as select_module
from lodscape.lod.camera import Camera
from lodscape.lod.region import MIN_LEVEL, visible_region
from lodscape.lod.select import SelectOptions, select
from lodscape.terrain.mesh import cell_corners


def _random_camera(rng: np.random.Generator) -> Camera:
    alt = float(np.exp(rng.uniform(np.log(30.0), np.log(60_000.0))))
    cam = Camera(
        float(rng.uniform(-180, 180)),
        float(rng.uniform(-84, 84)),
        alt,
        heading=float(rng.uniform(0, 360)),
        pitch=float(rng.uniform(-90, 30)),
        roll=float(rng.uniform(-40, 40)),
        fov_y=float(rng.uniform(20, 100)),
        width=int(rng.integers(64, 1920)),
        height=int(rng.integers(64, 1080)),
    )
    return cam.with_clip(max(alt * 0.01, 0.5), float(np.exp(rng.uniform(np.log(2e3), np.log(1e6)))))


def _points_in_view(cam: Camera, rng: np.random.Generator, n: int) -> np.ndarray:
    """Random points inside the camera's frustum, as (lon, lat, h)."""
    assert cam.near is not None
    assert cam.far is not None
    right, up, back = cam.rotation
    ty = math.tan(math.radians(cam.fov_y) / 2.0)
    tx = ty * cam.aspect
    sx, sy = rng.uniform(-1, 1, n), rng.uniform(-1, 1, n)
    # half of them on the frustum's sides, where the region's edges are
    side = rng.integers(0, 4, n // 2)
    sx[: n // 2] = np.where(side == 0, -1.0, np.where(side == 1, 1.0, sx[: n // 2]))
    sy[: n // 2] = np.where(side == 2, -1.0, np.where(side == 3, 1.0, sy[: n // 2]))
    d = cam.near + (cam.far - cam.near) * rng.uniform(0, 1, n) ** 2
    v = d[:, None] * (-back + (sx * tx)[:, None] * right + (sy * ty)[:, None] * up)
    lon, lat, h = ecef_to_geodetic(cam.position + v)
    return np.stack([lon, lat, h], axis=1)


def test_every_visible_ground_point_lies_in_a_tile_the_region_keeps() -> None:
    rng = np.random.default_rng(5)
    checked = 0
    for _ in range(300):
        cam = _random_camera(rng)
        lo, hi = sorted(rng.uniform(-500.0, 6000.0, 2))
        region = visible_region(cam, lo, hi)
        if region is None:
            continue
        p = _points_in_view(cam, rng, 400)
        p = p[(p[:, 2] >= lo) & (p[:, 2] <= hi) & (np.abs(p[:, 1]) < 85.0)]
        if not len(p):
            continue
        assert not region.empty
        xm, ym = lonlat_to_merc(p[:, 0], p[:, 1])
        for z in range(MIN_LEVEL, 20):
            x, y = tiles_array(xm, ym, z)
            assert region.hits(z, x, y).all(), (cam, lo, hi, z)
        checked += len(p)
    assert checked > 5000


def test_region_is_bounded_and_drops_what_is_out_of_view() -> None:
    cam = Camera(7.0, 46.0, 1500.0, heading=30, pitch=-20).with_clip(5.0, 60_000.0)
    region = visible_region(cam, 200.0, 2500.0)
    assert region is not None
    assert not region.empty
    # bounded by the far plane's corners, and much smaller than the disc they span
    ty = math.tan(math.radians(cam.fov_y) / 2.0)
    reach = 60_000.0 * math.sqrt(1.0 + ty * ty * (1.0 + cam.aspect**2))
    assert np.linalg.norm(region.polygon, axis=1).max() <= reach
    assert region.area < 0.25 * math.pi * reach**2
    # the tile under the camera's back is out of view; the one ahead is in it
    ahead = lonlat_to_merc(7.0 + 0.1 * math.sin(math.radians(30)), 46.0 + 0.1)
    behind = lonlat_to_merc(7.0 - 0.2, 46.0 - 0.2)
    for (xm, ym), want in ((ahead, True), (behind, False)):
        x, y = tiles_array(np.array([xm]), np.array([ym]), 12)
        assert bool(region.hits(12, x, y)[0]) is want


def test_looking_at_the_sky_sees_no_ground() -> None:
    cam = Camera(7.0, 46.0, 3000.0, pitch=60.0, fov_y=40).with_clip(1.0, 20_000.0)
    region = visible_region(cam, 0.0, 2000.0)
    assert region is not None
    assert region.empty
    assert not region.hits(10, np.array([533]), np.array([360])).any()


def test_no_region_for_a_far_plane_at_planet_scale() -> None:
    cam = Camera(0.0, 0.0, 2e6, pitch=-90).with_clip(1e5, 5e6)
    assert visible_region(cam, 0.0, 1000.0) is None


def _out_of_view(cam: Camera, provider: object, key: int) -> bool:
    """Whether no cell of the tile's real mesh can be seen: each has its four corners outside
    one frustum plane (so both of its triangles lie outside it, whatever the diagonal)."""
    mesh = provider.mesh(key)  # type: ignore[attr-defined]
    s = mesh.segments
    p = mesh.vertices[: (s + 1) ** 2, :3].astype(np.float64) + (mesh.center - cam.position)
    planes = cam.frustum_planes()
    out = (p @ planes[:, :3].T + planes[:, 3]) < 0.0
    nw = cell_corners(s)
    corners = np.stack([nw, nw + 1, nw + s + 1, nw + s + 2], axis=1)
    one_plane = out[corners].all(axis=1).any(axis=1)
    # or beyond the far plane's corners, the frustum's farthest reach
    ty = math.tan(math.radians(cam.fov_y) / 2.0)
    reach = cam.far * math.sqrt(1.0 + ty * ty * (1.0 + cam.aspect**2))  # type: ignore[operator]
    dist = np.linalg.norm(p, axis=1)[corners]
    size = np.linalg.norm(p[corners[:, 3]] - p[corners[:, 0]], axis=1)
    too_far = dist.min(axis=1) - size > reach
    return bool((one_plane | too_far).all())


SOURCES = {"dem": AnalyticSource, "procedural": lambda: "procedural:seed=3"}


@pytest.mark.parametrize("name", SOURCES)
def test_the_region_drops_only_tiles_out_of_view(
    name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With the region the selection draws the same tiles, less only some whose real mesh cannot
    be seen (tiles the looser box test let through)."""
    monkeypatch.setattr(select_module, "_REGION_MIN", 1)
    provider = lodscape.open(SOURCES[name]()).provider
    tree = provider.tree
    rng = np.random.default_rng(11)
    on, off = SelectOptions(region=True), SelectOptions()
    spared = 0
    if name == "dem":
        lon0, lat0 = -84.3, 36.5
        cams = [
            Camera(
                lon0 + rng.uniform(-0.3, 0.3),
                lat0 + rng.uniform(-0.3, 0.3),
                float(rng.uniform(300, 20_000)),
                heading=float(rng.uniform(0, 360)),
                pitch=float(rng.uniform(-90, 20)),
            )
            for _ in range(12)
        ]
    else:
        cams = [
            Camera(
                float(rng.uniform(-180, 180)),
                float(rng.uniform(-70, 70)),
                float(rng.uniform(3_000, 20_000)),
                heading=float(rng.uniform(0, 360)),
                pitch=float(rng.uniform(-90, 0)),
            )
            for _ in range(6)
        ]
    for cam in cams:
        cam = cam.with_clip(max(cam.alt * 0.02, 1.0), min(40.0 * cam.alt + 50_000.0, 1e6))
        a, b = select(on, cam, tree), select(off, cam, tree)
        assert b.outside == 0
        assert a.visited <= b.visited
        extra = set(a.keys.tolist()) - set(b.keys.tolist())
        assert not extra
        for key in set(b.keys.tolist()) - set(a.keys.tolist()):
            assert _out_of_view(cam, provider, key), (cam, key)
        spared += a.outside
    assert spared > 0
