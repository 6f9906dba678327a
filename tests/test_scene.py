"""End to end on real GeoTIFFs and real OpenGL (headless EGL): cracks, the pixel rule, depth,
determinism and GL hygiene."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, magenta_cracks, spine_views, write_dem
from lodscape import Camera, SceneOptions
from lodscape.errors import CameraError

pytestmark = pytest.mark.gl

MAGENTA = (1.0, 0.0, 1.0)
# UTM 17N, around 36.6N 84.2W: 1025 samples at 10 m (10 km of rough relief)
EAST, NORTH = 700000.0, 4060000.0


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("dem") / "utm.tif"
    return write_dem(
        str(path), fbm_heights(1025), crs="EPSG:32617", west=EAST, north=NORTH, res=10.0
    )


@pytest.fixture(scope="module")
def scene(dem: str) -> lodscape.Scene:
    with lodscape.open(dem, SceneOptions(background=MAGENTA, ellipsoid=False)) as s:
        yield s


def _centre(scene: lodscape.Scene) -> tuple[float, float]:
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.source.bounds_merc
    lon, lat = merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
    return float(lon), float(lat)


def _views(scene: lodscape.Scene) -> dict[str, Camera]:
    return spine_views(scene, 640, 360)


_cracks = magenta_cracks


def test_no_cracks_across_levels(scene: lodscape.Scene) -> None:
    depths = set()
    for name, cam in _views(scene).items():
        rgb, _ = scene.render(cam)
        assert scene.last is not None
        sel = scene.last.selection
        depths.add(sel["max_depth"])
        assert (~np.all(rgb == (255, 0, 255), axis=2)).mean() > 0.3, name
        assert _cracks(rgb) == 0, name
    # the views really mix levels
    lv = {int(z) for z in scene.select(_views(scene)["low"]).z}
    assert len(lv) >= 3


def test_cracks_would_show_without_skirts(scene: lodscape.Scene) -> None:
    """The crack detector is not vacuous: with skirts forced to zero, gaps appear."""
    from lodscape.lod.view import draw_items

    cam = scene.prepare(_views(scene)["low"])
    scene.render(cam)
    sel = scene.view.previous
    assert sel is not None
    renderer = scene.renderer
    assert renderer is not None
    items = [replace(item, skirt=0.0) for item in draw_items(sel)]
    # on the scene's GL thread, where its renderer lives
    rgb, _ = scene.on_gl(renderer.draw, cam, items, background=MAGENTA)
    assert _cracks(rgb) > 0


def test_pixel_rule_and_sse_on_a_real_raster(scene: lodscape.Scene) -> None:
    tree = scene.tree
    for name, cam in _views(scene).items():
        c = scene.prepare(cam)
        sel = scene.select(cam)
        ratio = sel.px_per_texel
        tex_z = sel.z - sel.texture_up
        assert c.near is not None
        # above the band only with the data's finest texture, or where the near plane cuts in
        high = ratio > 1.5
        assert np.all((tex_z[high] == tree.texture_zmax) | (sel.dist_near[high] < c.near)), name
        # below it only with a root's texture: the whole data is small on screen
        low = ratio < 0.5
        assert np.all(tex_z[low] == tree.zmin), name
        assert sel.max_sse <= 2.0, name


def test_depth_is_distance_along_the_view(scene: lodscape.Scene) -> None:
    lon, lat = _centre(scene)
    g = scene.ground_height(lon, lat)
    assert g is not None
    cam = Camera(lon, lat, g + 1000.0, pitch=-90, width=320, height=240)
    rgb, depth = scene.render(cam)
    assert rgb.shape == (240, 320, 3)
    assert depth.shape == (240, 320)
    assert depth[120, 160] == pytest.approx(1000.0, rel=0.02)
    sky = scene.render(Camera(lon, lat, g + 1000.0, pitch=10, width=320, height=240))[1]
    assert np.isinf(sky[0]).all()


def test_same_inputs_same_picture(dem: str) -> None:
    cam = Camera(-84.0, 36.6, 3000.0, pitch=-40, width=320, height=200)
    images = []
    for _ in range(2):
        with lodscape.open(dem) as s:
            c = s.overview_camera(320, 200)
            images.append(s.render(c)[0].tobytes())
    assert images[0] == images[1]
    del cam


def test_a_picture_is_the_same_whatever_was_rendered_before_it(dem: str) -> None:
    """Hysteresis is for the frames of one motion: a camera unrelated to the last (here a
    close-up of the same ground first) is selected and drawn as in a fresh scene."""
    with lodscape.open(dem) as fresh:
        views = _views(fresh)
        want = {name: fresh.render(cam)[0] for name, cam in views.items()}
        tris = {}
        for name, cam in views.items():
            fresh.view.previous = None
            fresh.render(cam)
            tris[name] = fresh.frame_stats()["triangles"]
    with lodscape.open(dem) as s:
        for name, cam in views.items():
            ground = s.ground_height(cam.lon, cam.lat)
            assert ground is not None
            close = cam.moved(alt=ground + 0.3 * (cam.alt - ground), pitch=max(cam.pitch, -60.0))
            s.render(close)
            got, _ = s.render(cam)
            assert s.frame_stats()["triangles"] == tris[name], name
            assert np.array_equal(got, want[name]), name


def test_a_low_flight_keeps_its_hysteresis_frame_to_frame(dem: str) -> None:
    """The frames of a flight 60 m over rough ground, 10 m apart, follow one another (the
    scale of a move is the eye's height above the ground, not the nearest tile's box, which a
    low eye in a valley stands inside); a jump of a kilometre does not."""
    with lodscape.open(dem) as s:
        lon, lat = _centre(s)
        followed = []
        for i in range(8):
            at = lat + i * 10.0 / 111_000.0
            ground = s.ground_height(lon, at)
            assert ground is not None
            cam = Camera(lon, at, ground + 60.0, pitch=-10.0, width=320, height=180)
            followed.append(s.view.history(s.prepare(cam)) is not None)
            s.render(cam)
        assert followed == [False] + [True] * 7
        away = cam.moved(lat=cam.lat + 1000.0 / 111_000.0)
        ground = s.ground_height(away.lon, away.lat)
        assert ground is not None
        assert s.view.history(s.prepare(away.moved(alt=ground + 60.0))) is None


def test_the_first_picture_waits_for_nothing_it_does_not_need(dem: str, tmp_path: Path) -> None:
    """On the way to a DEM's first picture: SciPy is imported only where the DEM has voids or
    a sea to find (its import was a fifth of the sample's first picture), numba not at all
    (the picture's TINs are NumPy's: numba and its kernels took 0.8 s to load), and the Blue
    Marble's decoding starts as the scene opens, on a thread of its own, not in the render."""
    script = f"""
import sys, threading, lodscape
scene = lodscape.open({dem!r})
assert any(t.name == "lodscape-earth" for t in threading.enumerate()) or (
    __import__("lodscape.render.passes").render.passes._EARTH.done()
)
rgb, _ = scene.render(scene.overview_camera(64, 36))
scene.close()
assert rgb.shape == (36, 64, 3)
from lodscape.terrain.tin_tiles import ErrorLadder
assert isinstance(scene.tree, ErrorLadder)
print(sorted(m for m in sys.modules if m.startswith(("scipy.ndimage", "numba"))))
"""
    env = {**os.environ, "LODSCAPE_CACHE": str(tmp_path)}
    got = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120
    )
    assert got.returncode == 0, got.stderr
    assert got.stdout.strip().splitlines()[-1] == "[]"


def test_a_window_scene_keeps_its_frames_in_the_target(dem: str, gl_ctx: Any) -> None:
    """A scene drawing in a window's context (``use_context``) reads nothing back, from its
    first frame: the target holds the picture as the GL draws it (bottom row first), the same
    picture a headless render returns (top row first)."""
    opts = SceneOptions(background=MAGENTA, ellipsoid=False)
    with lodscape.open(dem, opts) as headless:
        cam = headless.overview_camera(160, 90)
        want, _ = headless.render(cam)
    s = lodscape.open(dem, opts)
    try:
        s.use_context(gl_ctx)
        got, dist = s.render(cam)
        assert got.size == 0
        assert dist.size == 0
        renderer = s.renderer
        assert renderer is not None
        assert not renderer.target.flipped
        fbo = renderer.colour_framebuffer
        assert fbo is not None
        window = np.frombuffer(fbo.read(components=3, alignment=1), np.uint8)
        same = np.all(window.reshape(90, 160, 3)[::-1] == want, axis=2)
        assert same.mean() > 0.98, same.mean()
    finally:
        s.close()


def test_camera_under_the_ground_is_refused(scene: lodscape.Scene) -> None:
    lon, lat = _centre(scene)
    g = scene.ground_height(lon, lat)
    assert g is not None
    with pytest.raises(CameraError, match="under the ground"):
        scene.render(Camera(lon, lat, g - 5.0))


@pytest.mark.slow
def test_no_gl_object_leaks_over_1000_renders(dem: str) -> None:
    # a budget the first lap fills (a picture's TINs are small: 4 MiB took three laps)
    opts = SceneOptions(gpu_budget_mb=2.0)
    s = lodscape.open(dem, opts)
    lon, lat = _centre(s)
    hi = s.tree.height_range[1]
    counts, held = [], []
    for i in range(1000):
        a = 2 * np.pi * i / 250
        cam = Camera(
            lon + 0.03 * np.cos(a),
            lat + 0.02 * np.sin(a),
            hi + 400 + 300 * np.sin(a / 3),
            heading=float(np.degrees(a)) % 360,
            pitch=-25,
            width=64,
            height=48,
        )
        s.render(cam)
        renderer = s.renderer
        assert renderer is not None
        counts.append(renderer.live_objects())
        held.append(sum(renderer.resident().values()))
        assert s.on_gl(lambda r=renderer: r.ctx.error) == "GL_NO_ERROR"
    # bounded by the budget: what a lap holds, the next lap holds too
    assert max(held[:250]) > 0.9 * 2.0 * 2**20, "the test's premise: the first lap fills it"
    assert max(counts[750:]) <= max(counts[:500]) + 8
    renderer = s.renderer
    s.close()
    assert renderer.live_objects() == 0


@pytest.mark.gl
def test_a_scene_and_its_pictures_show_themselves_in_a_notebook() -> None:
    """``show`` renders a ``Picture`` (the overview by default); it and the scene give a
    notebook PNG bytes (``_repr_png_``) that decode to what was rendered."""
    import io

    from PIL import Image

    import lodscape
    from lodscape.data import sample_dem_path

    with lodscape.open(sample_dem_path()) as scene:
        cam = scene.overview_camera(96, 64)
        pic = scene.show(cam)
        assert isinstance(pic, lodscape.Picture)
        assert pic.camera == cam
        rgb, depth = scene.render(cam)
        assert np.array_equal(pic.rgb, rgb)
        assert np.array_equal(pic.depth, depth)
        back = np.asarray(Image.open(io.BytesIO(pic._repr_png_())))
        assert np.array_equal(back, rgb)
        default = np.asarray(Image.open(io.BytesIO(scene._repr_png_())))
        assert default.shape == (400, 640, 3)
        assert default.std() > 5  # terrain, not a blank frame
