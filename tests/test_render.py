"""The terrain pass on real OpenGL (headless EGL): pixels, view distance, precision far from the
origin, skirts, determinism and GL object hygiene."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from lodscape.geo.frames import enu_basis, geodetic_to_ecef
from lodscape.lod.camera import Camera
from lodscape.render import DrawItem, Renderer
from lodscape.terrain.mesh import TileMesh, ring_indices

pytestmark = pytest.mark.gl

MAGENTA = (1.0, 0.0, 1.0)
MAGENTA_U8 = (255, 0, 255)
LON, LAT, H = 7.0, 46.5, 800.0
# four quadrants, north-west first: the picture must keep north up and east right
QUADRANTS = {"nw": (220, 40, 40), "ne": (40, 200, 60), "sw": (40, 60, 220), "se": (230, 210, 30)}


def _quadrant_texture(size: int = 64) -> NDArray[np.uint8]:
    tex = np.empty((size, size, 3), np.uint8)
    half = size // 2
    tex[:half, :half] = QUADRANTS["nw"]
    tex[:half, half:] = QUADRANTS["ne"]
    tex[half:, :half] = QUADRANTS["sw"]
    tex[half:, half:] = QUADRANTS["se"]
    return tex


#: Tests upload each patch's texture under the patch's key plus this.
TEX = 1000


def _item(key: int, skirt: float = 0.0) -> DrawItem:
    return DrawItem(key, key + TEX, skirt)


def _put(r: Renderer, key: int, texture: NDArray[np.uint8], **kw: Any) -> TileMesh:
    """Upload a patch and its texture (under key + TEX); the mesh, for the test's geometry."""
    mesh = _patch(key, **kw)
    r.upload(mesh)
    r.upload_texture(key + TEX, texture)
    return mesh


def _patch(
    key: int,
    *,
    lon: float = LON,
    lat: float = LAT,
    h: float = H,
    size: float = 1000.0,
    segments: int = 8,
) -> TileMesh:
    """A flat square of ``size`` metres in the tangent plane at (lon, lat, h), row 0 north."""
    s = segments
    east = np.linspace(-size / 2, size / 2, s + 1)
    north = np.linspace(size / 2, -size / 2, s + 1)
    ee, nn = np.meshgrid(east, north)
    basis = enu_basis(lon, lat)
    local = np.column_stack([ee.ravel(), nn.ravel(), np.zeros(ee.size)])
    u, v = np.meshgrid(np.arange(s + 1) / s, np.arange(s + 1) / s)
    grid = np.column_stack([local @ basis, u.ravel(), v.ravel(), np.zeros(ee.size)])
    skirt = grid[ring_indices(s)].copy()
    skirt[:, 5] = 1.0
    vertices = np.concatenate([grid, skirt]).astype(np.float32)
    center = geodetic_to_ecef(lon, lat, h)
    return TileMesh(key, s, vertices, center, basis[2].astype(np.float32))


def _pixel(camera: Camera, point: NDArray[np.float64]) -> tuple[float, float]:
    """Where an ECEF point lands: (column, row from the top), in pixel units."""
    clip = camera.view_projection(point) @ np.array([0.0, 0.0, 0.0, 1.0])
    x, y = clip[:2] / clip[3]
    return (x + 1) / 2 * camera.width, (1 - y) / 2 * camera.height


def _plane_distance(camera: Camera, mesh: TileMesh) -> NDArray[np.float64]:
    """View-axis distance to the plane through ``mesh.center`` normal to ``mesh.up``, per pixel."""
    t = np.tan(np.radians(camera.fov_y) / 2)
    x = ((np.arange(camera.width) + 0.5) / camera.width * 2 - 1) * t * camera.aspect
    y = (1 - (np.arange(camera.height) + 0.5) / camera.height * 2) * t
    xx, yy = np.meshgrid(x, y)
    rays = np.stack([xx, yy, -np.ones_like(xx)], axis=-1) @ camera.rotation  # view z = -1
    up = mesh.up.astype(np.float64)
    result: NDArray[np.float64] = (up @ (mesh.center - camera.position)) / (rays @ up)
    return result


@pytest.fixture
def renderer(gl_ctx: Any) -> Any:
    # the tiles alone: no ellipsoid behind them
    with Renderer(64, 48, ctx=gl_ctx, ellipsoid=False) as r:
        yield r


def test_flat_patch_from_above_fills_its_pixels_with_the_texture(renderer: Renderer) -> None:
    _put(renderer, 1, _quadrant_texture())
    height = 2000.0
    cam = Camera(LON, LAT, H + height, pitch=-90, width=320, height=240).with_clip(1.0, 1e4)
    rgb, depth = renderer.draw(cam, [_item(1, 0.0)], background=MAGENTA)
    assert rgb.shape == (240, 320, 3)
    assert rgb.dtype == np.uint8
    assert depth.shape == (240, 320)
    assert depth.dtype == np.float32

    half = 500.0 * cam.scale / height  # the patch's half width in pixels
    cols = np.arange(320) + 0.5 - 160.0
    rows = np.arange(240) + 0.5 - 120.0
    dx, dy = np.meshgrid(cols, rows)
    inside = (np.abs(dx) < half - 1.5) & (np.abs(dy) < half - 1.5)
    outside = (np.abs(dx) > half + 1.5) | (np.abs(dy) > half + 1.5)
    assert not np.all(rgb[inside] == MAGENTA_U8, axis=1).any()
    assert np.all(rgb[outside] == MAGENTA_U8)
    # quadrant centres, far from any edge where filtering blends colours
    q = half / 2
    for name, (x, y) in {"nw": (-q, -q), "ne": (q, -q), "sw": (-q, q), "se": (q, q)}.items():
        core = (np.abs(dx - x) < q - 3) & (np.abs(dy - y) < q - 3)
        assert np.all(rgb[core] == QUADRANTS[name]), name

    # a plane square to the view axis lies at one distance: the camera's height above it
    np.testing.assert_allclose(depth[inside], height, rtol=5e-3)
    assert np.all(np.isinf(depth[outside]))
    stats = renderer.last_stats
    assert (stats.draw_calls, stats.triangles) == (1, 2 * 8 * 8 + 8 * 8)
    assert stats.submit_ms > 0.0


def test_patch_far_from_the_origin_does_not_jitter(renderer: Renderer) -> None:
    rng = np.random.default_rng(7)
    noise = rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)
    lon, lat = 10.0, 30.0
    mesh = _put(renderer, 2, noise, lon=lon, lat=lat, h=0.0, segments=16)
    assert np.linalg.norm(mesh.center) > 6.0e6
    base = Camera(lon, lat - 0.0005, 100.0, pitch=-50, width=320, height=240).with_clip(1.0, 5e3)

    def frame(cam: Camera) -> NDArray[np.float64]:
        return renderer.draw(cam, [_item(2, 0.0)], background=MAGENTA)[0].astype(np.float64)

    still = frame(base)
    assert not np.all(still == MAGENTA_U8, axis=2).any()  # the patch fills the view
    # every pixel's view distance matches a float64 ray cast to within a centimetre per 100 m,
    # where float32 ECEF would be off by up to half a metre
    depth = renderer.draw(base, [_item(2, 0.0)])[1]
    np.testing.assert_allclose(depth, _plane_distance(base, mesh), rtol=1e-4)
    nudged = frame(base.moved(alt=100.001))  # 1 mm: far below a pixel
    moved = frame(base.moved(alt=100.5))  # 0.5 m: a few pixels
    # float32 ECEF would snap vertices to half a metre here; the relative transform keeps 1 mm
    # to rounding noise, while half a metre visibly moves the picture
    assert np.abs(nudged - still).mean() < 0.1
    assert np.mean(np.abs(nudged - still).max(axis=2) > 8) < 1e-3
    assert np.abs(moved - still).mean() > 1.0


def test_skirts_hang_below_the_edge_only_when_asked(renderer: Renderer) -> None:
    _put(renderer, 3, np.full((16, 16, 3), (200, 120, 40), np.uint8))
    south = LAT - 2000.0 / 111_200.0  # about 2 km south of the patch centre
    cam = Camera.looking_at(LON, south, H + 200.0, (LON, LAT, H), width=320, height=240)
    cam = cam.with_clip(1.0, 1e4)
    flat, flat_depth = renderer.draw(cam, [_item(3, 0.0)], background=MAGENTA)
    hung, hung_depth = renderer.draw(cam, [_item(3, 100.0)], background=MAGENTA)

    col = 160
    covered = ~np.all(flat[:, col] == MAGENTA_U8, axis=1)
    with_skirt = ~np.all(hung[:, col] == MAGENTA_U8, axis=1)
    # the south edge and the bottom of its 100 m skirt, projected on the CPU
    basis = enu_basis(LON, LAT)
    edge = geodetic_to_ecef(LON, LAT, H) - 500.0 * basis[1]
    _, edge_row = _pixel(cam, edge)
    _, foot_row = _pixel(cam, edge - 100.0 * basis[2])
    assert foot_row - edge_row > 10  # a skirt worth seeing
    assert abs(np.flatnonzero(covered).max() + 0.5 - edge_row) < 1.5
    assert abs(np.flatnonzero(with_skirt).max() + 0.5 - foot_row) < 1.5
    band = slice(int(edge_row) + 2, int(foot_row) - 1)
    assert np.all(flat[band, col] == MAGENTA_U8)
    assert np.all(np.isinf(flat_depth[band, col]))
    assert np.all(hung[band, col] == (200, 120, 40))
    # the skirt is a wall square to the ground, at the edge's distance along the view axis
    edge_dist = float(-(cam.rotation @ (edge - cam.position))[2])
    np.testing.assert_allclose(hung_depth[band, col], edge_dist, rtol=0.05)
    # above the edge nothing changes: the skirt hangs below the surface, never over it
    assert np.array_equal(flat[: int(edge_row) - 1], hung[: int(edge_row) - 1])


def test_same_inputs_give_byte_identical_frames(renderer: Renderer, gl_ctx: Any) -> None:
    for k in range(3):
        _put(renderer, k, _quadrant_texture(), lon=LON + 0.01 * k)
    items = [_item(k, 20.0 * k) for k in range(3)]
    cam = Camera.looking_at(LON, LAT - 0.02, H + 600, (LON + 0.01, LAT, H), width=160, height=120)
    cam = cam.with_clip(1.0, 2e4)
    first = renderer.draw(cam, items)
    renderer.draw(cam.moved(heading=cam.heading + 30), items[::-1], background=MAGENTA)
    again = renderer.draw(cam, items)
    with Renderer(160, 120, ctx=gl_ctx, ellipsoid=False) as other:
        for k in range(3):
            _put(other, k, _quadrant_texture(), lon=LON + 0.01 * k)
        fresh = other.draw(cam, items)
    for a, b in ((first, again), (first, fresh)):
        assert a[0].tobytes() == b[0].tobytes()
        assert a[1].tobytes() == b[1].tobytes()


def test_a_thousand_draws_leak_no_gl_objects(gl_ctx: Any) -> None:
    textures = [np.full((32, 32, 3), 60 * k, np.uint8) for k in range(4)]
    meshes = [_patch(k, lon=LON + 0.005 * k, segments=(8, 16)[k % 2]) for k in range(4)]
    r = Renderer(64, 48, ctx=gl_ctx)
    counts = []
    for i in range(1000):
        # a cycle of four: one mesh in, another out, a new camera, and the viewport size flips
        r.upload(meshes[i % 4])
        r.upload_texture(i % 4 + TEX, textures[i % 4])
        r.release(meshes[(i + 2) % 4].key)
        r.release((i + 2) % 4 + TEX)
        size = (64, 48) if (i // 4) % 2 == 0 else (48, 64)
        cam = Camera(
            LON + 0.0005 * (i % 7),
            LAT - 0.01,
            H + 300.0 + i,
            heading=(7.0 * i) % 360,
            pitch=-35,
            width=size[0],
            height=size[1],
        ).with_clip(1.0, 2e4)
        r.draw(cam, [_item(k, 5.0) for k in sorted(r.resident()) if k < TEX])
        if i % 4 == 3:
            counts.append(r.live_objects())
    assert gl_ctx.error == "GL_NO_ERROR"
    # program + the clear layer texture + the ellipsoid's program and VAO + two index buffers +
    # two tiles x (VBO, VAO, texture) + FBO with three attachments; the textures have nothing
    # to cut, so the variant without a discard too: its program and a VAO per tile
    assert counts == [1 + 1 + 2 + 2 + 2 * 3 + 4 + 1 + 2] * 250
    r.close()
    assert r.live_objects() == 0
    r.close()  # idempotent
    assert r.live_objects() == 0


def test_drawing_a_key_never_uploaded_is_a_key_error(renderer: Renderer) -> None:
    _put(renderer, 5, _quadrant_texture())
    cam = Camera(LON, LAT, H + 500, pitch=-90, width=32, height=32).with_clip(1.0, 1e4)
    with pytest.raises(KeyError, match="mesh 99 is not uploaded"):
        renderer.draw(cam, [_item(5, 0.0), _item(99, 0.0)])
    with pytest.raises(KeyError, match="texture 7 is not uploaded"):
        renderer.draw(cam, [DrawItem(5, 7)])
    renderer.release(99)  # releasing an unknown key is harmless


def test_uploads_are_idempotent_and_share_index_buffers(renderer: Renderer) -> None:
    base = renderer.live_objects()
    a, b = _patch(10), _patch(11, lon=LON + 0.01)
    tex = _quadrant_texture()
    renderer.upload(a)
    renderer.upload(a)
    renderer.upload(b)
    renderer.upload_texture(12, tex)
    renderer.upload_texture(12, tex)
    # one index buffer for both meshes (same S), a VBO and a VAO each, one texture
    assert renderer.live_objects() == base + 1 + 2 * 2 + 1
    assert renderer.resident() == {10: a.nbytes, 11: b.nbytes, 12: tex.nbytes * 4 // 3}
    for key in (10, 11, 12):
        renderer.release(key)
    assert renderer.live_objects() == base
    assert renderer.resident() == {}


def test_an_owned_context_is_created_and_released(gl_ctx: Any) -> None:
    with Renderer(40, 30, background=MAGENTA, ellipsoid=False) as r:
        assert r.ctx is not gl_ctx
        _put(r, 1, _quadrant_texture())
        cam = Camera(LON, LAT, H + 3000, pitch=-90, width=40, height=30).with_clip(1.0, 1e4)
        rgb, depth = r.draw(cam, [_item(1, 0.0)])
        # the background given at construction applies when a draw names none
        assert tuple(rgb[0, 0]) == MAGENTA_U8
        assert np.isinf(depth[0, 0])
        assert r.ctx.error == "GL_NO_ERROR"
    assert r.live_objects() == 0
    with pytest.raises(RuntimeError, match="closed"):
        _put(r, 2, _quadrant_texture())


def test_a_texture_window_stretches_one_quadrant_over_the_tile(renderer: Renderer) -> None:
    """A tile textured from its parent shows only its quarter of the parent's image."""
    _put(renderer, 6, _quadrant_texture())
    cam = Camera(LON, LAT, H + 2000, pitch=-90, width=64, height=64).with_clip(1.0, 1e4)
    # the north-east quarter: u from 0.5, v from 0 (row 0 is north), half the image
    rgb, _ = renderer.draw(cam, [DrawItem(6, 6 + TEX, 0.0, (0.5, 0.0, 0.5))], background=MAGENTA)
    half = int(500.0 * cam.scale / 2000)  # the patch's half width in pixels
    core = rgb[32 - half + 2 : 32 + half - 2, 32 - half + 2 : 32 + half - 2]
    assert np.all(core == QUADRANTS["ne"])


def test_a_window_frame_is_the_picture_read_back_bottom_row_first(gl_ctx: Any) -> None:
    """A frame read back is drawn upside down in clip space, so its rows come top first with
    no flip; a window's frame (``read_back`` off) keeps the GL's orientation. Both are the same
    picture: the tile, its texture's quadrants and the ellipsoid's ray-cast behind it (drawn
    from window coordinates) alike."""
    import moderngl

    # 2 km south of the tile, looking north-north-east over it: the sky in the top rows
    cam = Camera(LON, LAT - 0.018, H + 800, heading=30.0, pitch=-15, width=96, height=64)
    cam = cam.with_clip(1.0, 1e7)
    with Renderer(96, 64, ctx=gl_ctx, background=MAGENTA) as r:
        _put(r, 9, _quadrant_texture())
        rgb, dist = r.draw(cam, [_item(9, 20.0)])
        assert r.target.flipped
        r.read_back = False
        got, _ = r.draw(cam, [_item(9, 20.0)])
        assert got.size == 0
        assert not r.target.flipped
        fbo = r.target.framebuffer
        assert isinstance(fbo, moderngl.Framebuffer)
        window = np.frombuffer(fbo.read(components=3, alignment=1), np.uint8).reshape(64, 96, 3)
        wdist = np.frombuffer(fbo.read(components=1, attachment=1, dtype="f4"), np.float32)
    # the sky (the clear colour) above, the ground below, in the picture read back
    assert np.all(rgb[0] == MAGENTA_U8)
    assert not np.any(np.all(rgb[-1] == MAGENTA_U8, axis=1))
    assert np.isinf(dist[0]).all()
    assert np.isfinite(dist[-1]).all()
    window, wdist = window[::-1], wdist.reshape(64, 96)[::-1]
    # the rasteriser's fill rule turns with the picture: pixels on an edge may go to the other
    # triangle, nothing more
    same = np.all(window == rgb, axis=2)
    assert same.mean() > 0.98, same.mean()
    both = np.isfinite(dist) & np.isfinite(wdist)
    assert (np.isfinite(dist) == np.isfinite(wdist)).mean() > 0.99
    close = np.abs(dist[both] - wdist[both]) <= 1e-4 * dist[both]
    assert close.mean() > 0.98, close.mean()


def _pixel_rays(camera: Camera) -> NDArray[np.float64]:
    """Per pixel (row 0 at the top) the world direction of its ray, scaled so its parameter is
    the view depth (z = -1 in view space), in float64."""
    t = np.tan(np.radians(camera.fov_y) / 2)
    x = ((np.arange(camera.width) + 0.5) / camera.width * 2 - 1) * t * camera.aspect
    y = (1 - (np.arange(camera.height) + 0.5) / camera.height * 2) * t
    xx, yy = np.meshgrid(x, y)
    rays: NDArray[np.float64] = np.stack([xx, yy, -np.ones_like(xx)], axis=-1) @ camera.rotation
    return rays


def _ellipsoid_depth(camera: Camera) -> NDArray[np.float64]:
    """View depth of the WGS84 ellipsoid per pixel (inf where the ray misses), in float64."""
    from lodscape.geo.frames import WGS84_A, WGS84_B

    axes = np.array([WGS84_A, WGS84_A, WGS84_B])
    d = _pixel_rays(camera) / axes
    o = camera.position / axes
    a, b, c = (d * d).sum(-1), d @ o, o @ o - 1.0
    disc = b * b - a * c
    hit = (disc >= 0) & (b < 0)
    out = np.full(d.shape[:2], np.inf)
    out[hit] = c / (-b[hit] + np.sqrt(disc[hit]))
    return out


@pytest.mark.parametrize(
    ("alt", "pitch"),
    # the last three see it in part of the view (the Earth whole and small, its limb, the
    # horizon from the ground): it is ray-cast inside its box only, the rows turned with the
    # picture read back top row first
    [(1000.0, -90.0), (1000.0, -5.0), (3e6, -60.0), (3e7, -80.0), (4e5, -5.0), (1000.0, 8.0)],
)
def test_the_ellipsoid_stands_behind_the_terrain(gl_ctx: Any, alt: float, pitch: float) -> None:
    cam = Camera(LON, LAT, alt, heading=30.0, pitch=pitch, width=64, height=48).with_clip(1.0, 1e8)
    if alt > 1e7 or pitch > 0.0:
        box = cam.ellipsoid_box()
        assert box is not None
        assert (box[2] - box[0]) * (box[3] - box[1]) < 3.0
    want = _ellipsoid_depth(cam)
    with Renderer(64, 48, ctx=gl_ctx, background=MAGENTA) as r:
        rgb, depth = r.draw(cam, [])
        hit = np.isfinite(want)
        assert hit.any()
        # where a ray meets it the ellipsoid is there, at its distance; elsewhere the sky
        np.testing.assert_array_equal(np.isfinite(depth), hit)
        np.testing.assert_allclose(depth[hit], want[hit], rtol=2e-4, atol=0.05)
        assert (np.abs(rgb[hit].astype(int) - MAGENTA_U8).sum(-1) > 0).all()
        assert (rgb[~hit] == MAGENTA_U8).all()
        # grey: the no-data colour, lit
        assert np.ptp(rgb[hit].astype(int), axis=-1).max() <= 1
        if alt < 2000.0:
            # any terrain drawn wins over it, even below height 0 (no depth written for it)
            _put(r, 1, _quadrant_texture(), h=-300.0)
            r.ellipsoid = True
            look = Camera(LON, LAT, 500.0, pitch=-90, width=32, height=32).with_clip(1.0, 1e4)
            _, d2 = r.draw(look, [_item(1, 0.0)])
            assert float(np.median(d2)) == pytest.approx(800.0, abs=2.0)


def _earth_reference(camera: Camera, image: NDArray[np.uint8]) -> NDArray[np.float64]:
    """What the ellipsoid shows of an equirectangular ``image`` per pixel, in float64: the
    ray's hit, its geodetic latitude and longitude, the image sampled bilinearly there (the
    base level: the cameras below magnify it), lit as the shader lights it."""
    from lodscape.geo.frames import WGS84_A, WGS84_B
    from lodscape.render.terrain_pass import _sun_world

    t = _ellipsoid_depth(camera)
    assert np.isfinite(t).all()
    axes = np.array([WGS84_A, WGS84_A, WGS84_B])
    n = (camera.position + t[..., None] * _pixel_rays(camera)) / axes**2
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    lat, lon = np.arcsin(n[..., 2]), np.arctan2(n[..., 1], n[..., 0])
    rows, cols = image.shape[:2]
    fx = (lon / (2 * np.pi) + 0.5) * cols - 0.5
    fy = (0.5 - lat / np.pi) * rows - 0.5
    x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    ax, ay = (fx - x0)[..., None], (fy - y0)[..., None]

    def texel(r: NDArray[np.int64], c: NDArray[np.int64]) -> NDArray[np.float64]:
        return image[np.clip(r, 0, rows - 1), c % cols].astype(np.float64)

    colour = (
        texel(y0, x0) * (1 - ax) * (1 - ay) + texel(y0, x0 + 1) * ax * (1 - ay)
        + texel(y0 + 1, x0) * (1 - ax) * ay + texel(y0 + 1, x0 + 1) * ax * ay
    )  # fmt: skip
    light = 0.35 + 0.65 * np.maximum(n @ _sun_world(camera), 0.0)
    out: NDArray[np.float64] = colour * light[..., None]
    return out


@pytest.mark.parametrize("lat", [0.0, 30.0, 60.0, 74.0, 84.0])
def test_the_earths_image_lies_where_its_latitude_says(gl_ctx: Any, lat: float) -> None:
    """The Earth's image on the ellipsoid is sampled at each pixel's own latitude and
    longitude (a random texture: any texel off shows). With asin for the latitude llvmpipe put
    it off by a fraction of a texel row (here a median of 2.6-6.1 of 255 and up to 24 from 30
    to 84 degrees); with the atan the shader takes: a median of 0.3 and at most 1.5."""
    rng = np.random.default_rng(7)
    image = rng.integers(0, 256, (1024, 2048, 3), dtype=np.uint8)
    with Renderer(64, 48, ctx=gl_ctx, background=MAGENTA) as r:
        r.set_earth(image)
        cam = Camera(20.0, lat, 60000.0, heading=30.0, pitch=-90, width=64, height=48)
        rgb, _ = r.draw(cam.with_clip(1.0, 1e8), [])
    diff = np.abs(rgb.astype(np.float64) - _earth_reference(cam, image))
    assert np.median(diff) < 1.0
    assert diff.max() <= 3.0


def test_tiles_with_nothing_to_cut_draw_the_same_without_the_discard(gl_ctx: Any) -> None:
    """A texture with alpha everywhere is drawn by the variant without a discard (the depth
    test may run first): the picture and distance are those of the cutting program."""
    r = Renderer(96, 64, ctx=gl_ctx)
    try:
        textures = [np.full((32, 32, 3), 50 + 60 * k, np.uint8) for k in range(3)]
        for k in range(3):
            r.upload(_patch(k, lon=LON + 0.004 * k, segments=16))
            r.upload_texture(k + TEX, textures[k])
        cam = Camera(LON + 0.004, LAT - 0.01, H + 600.0, pitch=-35, width=96, height=64)
        cam = cam.with_clip(1.0, 2e4)
        items = [_item(k, 5.0) for k in range(3)]
        assert r._whole == {TEX, TEX + 1, TEX + 2}
        rgb_whole, d_whole = r.draw(cam, items)
        r.no_discard = False  # every tile by the cutting program
        rgb_cut, d_cut = r.draw(cam, items)
        np.testing.assert_array_equal(rgb_whole, rgb_cut)
        np.testing.assert_array_equal(d_whole, d_cut)
        assert np.isfinite(d_whole).mean() > 0.3
    finally:
        r.close()


@pytest.mark.parametrize("clockwise", [False, True])
def test_an_irregular_mesh_shows_its_top_from_above_and_its_underside_from_below(
    renderer: Renderer, clockwise: bool
) -> None:
    """The surface's underside is told by the rasteriser's facing: a mesh wound either way
    (RTIN clockwise, quantized-mesh counter-clockwise) is turned to face up when uploaded."""
    from lodscape.render.terrain_pass import wound_up
    from lodscape.terrain.mesh import grid_indices

    grid = _patch(7)
    s = grid.segments
    tris = grid_indices(s).reshape(-1, 3)[: 2 * s * s].astype(np.uint32)  # no skirts
    if clockwise:
        tris = tris[:, [0, 2, 1]]
    verts = grid.vertices[: (s + 1) ** 2]
    mesh = TileMesh(7, 0, verts, grid.center, grid.up, indices=tris)
    fixed = wound_up(verts, tris, grid.up.astype(np.float64))
    p = verts[:, :3].astype(np.float64)
    normals = np.cross(p[fixed[:, 1]] - p[fixed[:, 0]], p[fixed[:, 2]] - p[fixed[:, 0]])
    assert (normals @ grid.up > 0).all()
    renderer.upload(mesh)
    renderer.upload_texture(7 + TEX, np.full((8, 8, 3), 200, np.uint8))
    dark = (round(0.16 * 255), round(0.16 * 255), round(0.18 * 255))  # the underside
    for alt, pitch in ((H + 1500.0, -90.0), (H - 1500.0, 90.0)):
        cam = Camera(LON, LAT, alt, pitch=pitch, width=64, height=48).with_clip(1.0, 1e4)
        rgb, _ = renderer.draw(cam, [_item(7)], background=MAGENTA)
        centre = rgb[20:28, 28:36].reshape(-1, 3)
        want = np.array((200, 200, 200) if alt > H else dark)
        assert np.abs(centre.astype(int) - want).max() <= 2, (alt, centre[0])


def test_a_renderer_holds_the_code_of_as_many_layers_as_asked(gl_ctx: Any) -> None:
    with Renderer(32, 24, ctx=gl_ctx, ellipsoid=False, layers=0) as r:
        _put(r, 1, _quadrant_texture())
        cam = Camera(LON, LAT, H + 2000.0, pitch=-90, width=32, height=24).with_clip(1.0, 1e4)
        r.draw(cam, [_item(1)])
        layered = DrawItem(1, 1 + TEX, 0.0, layers=((1 + TEX, (0.0, 0.0, 1.0)),))
        with pytest.raises(ValueError, match="at most 0 imagery layers"):
            r.draw(cam, [layered])
    with pytest.raises(ValueError, match="at most 4"):
        Renderer(32, 24, ctx=gl_ctx, layers=5)


def test_no_underside_speckles_on_the_ground() -> None:
    """The underside's colour on the ground itself (its depth continuous with its neighbours'):
    a sliver triangle seen edge-on whose facing rounding flipped. None, over cameras at random
    above the sample DEM (a fixed seed) and its overview."""
    import lodscape
    from lodscape.data import sample_dem_path
    from lodscape.geo.tiles import merc_to_lonlat

    rng = np.random.default_rng(0)
    with lodscape.open(sample_dem_path()) as scene:
        b = scene.provider.bounds_merc
        cams = [scene.overview_camera(480, 270)]
        while len(cams) < 9:
            lon, lat = merc_to_lonlat(rng.uniform(b.left, b.right), rng.uniform(b.bottom, b.top))
            ground = scene.ground_height(float(lon), float(lat))
            if ground is None:
                continue
            cams.append(
                Camera(float(lon), float(lat), ground + rng.uniform(100.0, 2000.0),
                       heading=rng.uniform(0.0, 360.0), pitch=rng.uniform(-60.0, -5.0),
                       width=480, height=270)
            )  # fmt: skip
        for cam in cams:
            rgb, depth = scene.render(cam)
            dark = np.all(rgb == (41, 41, 46), axis=2)
            d = np.where(np.isfinite(depth), depth, 1e30).astype(np.float64)  # sky: far away
            pad = np.pad(d, 1, mode="edge")
            near = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
            ground_here = (d < 1e29) & (np.abs(near - d).max(axis=0) < 0.02 * d)
            assert int((dark & ground_here).sum()) == 0, cam
