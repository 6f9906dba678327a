"""The GPU terrain mode (paper 001): height textures tessellated in hardware. Its pieces (error
tables, patches, tile frames) against brute force, and its pictures against the CPU mode's at
the spine's test views: no cracks, the same terrain."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, magenta_cracks, run_cli, spine_views, write_dem
from lodscape import Camera, SceneOptions, SelectOptions
from lodscape.geo.frames import geodetic_to_ecef
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.terrain.heightmap import (
    LEVELS,
    error_table,
    patch_layout,
    tile_frame,
    tile_origin,
)
from lodscape.terrain.mesh import grid_coordinates

MAGENTA = (1.0, 0.0, 1.0)
EAST, NORTH = 700000.0, 4060000.0


def test_error_table_against_brute_force() -> None:
    rng = np.random.default_rng(4)
    h = np.cumsum(np.cumsum(rng.normal(size=(65, 65)), 0), 1)
    table = error_table(h)
    p, c = patch_layout(64)
    assert (p, c) == (4, 16)
    assert table.shape == (p * p + 2 * p * (p + 1), LEVELS + 2)
    # the finest level is the grid itself; coarser levels never stray less than finer ones
    assert np.all(table[:, LEVELS - 1] == 0.0)
    assert np.all(np.diff(table[:, :LEVELS], axis=1) <= 0.0)
    # patch (row 1, column 2) at 2 segments a side: vertices every 8 cells, by hand
    r0, c0, k = 16, 32, 8
    worst = 0.0
    for i in range(17):
        for j in range(17):
            y0, x0 = r0 + (i // k) * k, c0 + (j // k) * k
            y1, x1 = min(y0 + k, 64), min(x0 + k, 64)
            fy, fx = (i % k) / k, (j % k) / k
            v = (h[y0, x0] * (1 - fx) + h[y0, x1] * fx) * (1 - fy) + (
                h[y1, x0] * (1 - fx) + h[y1, x1] * fx
            ) * fy
            if i < 16 and j < 16:
                worst = max(worst, abs(v - h[r0 + i, c0 + j]))
    q = h[r0 : r0 + 17 : k, c0 : c0 + 17 : k]
    twist = np.abs(q[:-1, :-1] + q[1:, 1:] - q[:-1, 1:] - q[1:, :-1]).max() / 2.0
    assert table[1 * p + 2, 1] >= worst + twist - 1e-3
    # heights: the patch's lowest and highest samples
    block = h[r0 : r0 + 17, c0 : c0 + 17]
    assert table[1 * p + 2, LEVELS] == pytest.approx(block.min(), abs=1e-3)
    assert table[1 * p + 2, LEVELS + 1] == pytest.approx(block.max(), abs=1e-3)
    # a plane is drawn exactly at every level
    yy, xx = np.mgrid[0:65, 0:65]
    assert np.abs(error_table(3.0 * xx - 2.0 * yy + 7.0)[:, :LEVELS]).max() < 1e-3


@pytest.mark.parametrize(("z", "x", "y"), [(9, 137, 201), (14, 4410, 6480), (3, 7, 1)])
def test_tile_frame_puts_grid_points_at_their_geodetic_place(z: int, x: int, y: int) -> None:
    s = 64
    grid, _, _ = tile_frame(z, y, s)
    origin, basis = tile_origin(z, x, y, s)
    xs, ys = grid_coordinates(z, x, y, s)
    lon, lat = merc_to_lonlat(xs[None, :], ys[:, None])
    lon, lat = np.broadcast_arrays(lon, lat)
    h = np.random.default_rng(z).uniform(-400, 8000, lon.shape)
    want = (geodetic_to_ecef(lon, lat, h) - origin) @ basis.T
    got = grid[..., :3] + h[..., None] * grid[..., 4:7]
    # float32 positions a tile across: centimetres even for the coarse tile
    tol = 1e-6 * float(np.abs(want).max()) + 0.01
    assert np.abs(got - want).max() < tol


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("dem") / "utm.tif"
    return write_dem(
        str(path), fbm_heights(1025), crs="EPSG:32617", west=EAST, north=NORTH, res=10.0
    )


def _views(scene: lodscape.Scene) -> dict[str, Camera]:
    return spine_views(scene, 480, 270)


_cracks = magenta_cracks


@pytest.mark.gl
def test_gpu_mode_draws_the_cpu_terrain_without_cracks(dem: str) -> None:
    pictures = {}
    for mode in ("cpu", "gpu"):
        with lodscape.open(
            # grids in both: the cpu mode's TINs are a coarser surface within the same bound
            dem,
            SceneOptions(background=MAGENTA, terrain_mode=mode, ellipsoid=False, meshes="grid"),
        ) as scene:
            for name, cam in _views(scene).items():
                rgb, depth = scene.render(cam)
                assert scene.last is not None
                assert scene.terrain_mode == mode
                assert scene.last.terrain_mode == mode
                assert _cracks(rgb) == 0, (mode, name)
                assert scene.last.selection["max_sse_px"] <= 2.0
                assert scene.last.triangles > 0
                pictures[mode, name] = (rgb, depth)
            if mode == "gpu":
                # the crack test is not vacuous here either: without skirts, gaps show
                from lodscape.lod.view import draw_items

                cam = scene.prepare(_views(scene)["low"])
                scene.render(cam)
                assert scene.view.previous is not None
                assert scene.renderer is not None
                items = [replace(i, skirt=0.0) for i in draw_items(scene.view.previous)]
                rgb, _ = scene.on_gl(scene.renderer.draw, cam, items, background=MAGENTA)
                assert _cracks(rgb) > 0
    # the same terrain: distances within a fraction of a percent, colours within a few levels
    for name in ("down", "oblique", "low", "steep-near"):
        (a, da), (b, db) = pictures["cpu", name], pictures["gpu", name]
        both = np.isfinite(da) & np.isfinite(db)
        assert both.mean() > 0.3
        rel = np.abs(da[both] - db[both]) / da[both]
        assert np.median(rel) < 1e-4, name
        assert np.percentile(rel, 99) < 0.01, name
        assert np.abs(a.astype(np.int16) - b.astype(np.int16)).mean() < 3.0, name


@pytest.mark.gl
def test_the_pixel_rule_thins_the_tessellation(dem: str) -> None:
    tris = {}
    for px in (4.0, 24.0):
        opts = SceneOptions(
            select=SelectOptions(max_sse=6.0),
            background=MAGENTA,
            terrain_mode="gpu",
            tess_px=px,
            ellipsoid=False,
        )
        with lodscape.open(dem, opts) as scene:
            rgb, _ = scene.render(_views(scene)["oblique"])
            assert scene.last is not None
            assert _cracks(rgb) == 0, px
            tris[px] = scene.last.triangles
    assert tris[24.0] < tris[4.0], tris


@pytest.mark.gl
def test_without_tessellation_it_says_so_and_draws_on_the_cpu(
    dem: str, monkeypatch: pytest.MonkeyPatch, tmp_path: object, capsys: pytest.CaptureFixture[str]
) -> None:
    from lodscape.render import terrain_pass
    from lodscape.render.tess_pass import TessellationUnavailable

    def refuse(*args: object, **kwargs: object) -> None:
        raise TessellationUnavailable("the GPU terrain mode needs OpenGL 4.0 tessellation")

    monkeypatch.setattr(terrain_pass, "TessTerrain", refuse)
    with lodscape.open(dem, SceneOptions(terrain_mode="gpu")) as scene:
        scene.render(_views(scene)["down"])
        assert scene.terrain_mode == "cpu"
        assert scene.terrain_mode_note is not None
        assert "OpenGL 4.0" in scene.terrain_mode_note
    out = f"{tmp_path}/v.png"
    code, _, err = run_cli(
        ["render", dem, "--terrain-mode", "gpu", "--size", "160x100", "-o", out, "-q"], capsys
    )
    assert code == 0
    assert "notice:" in err
    assert "CPU terrain mode" in err
    code, _, err = run_cli(["render", dem, "--terrain-mode", "tpu", "-o", out], capsys)
    assert code == 2
    assert "terrain_mode" in err
