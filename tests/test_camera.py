"""The camera value: frames, the screen-space formulas, the frustum and validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from lodscape.errors import CameraError
from lodscape.geo.frames import ecef_to_geodetic, enu_basis, geodetic_to_ecef
from lodscape.lod.camera import Camera


@given(st.floats(-180, 180), st.floats(-89.9, 89.9), st.floats(-500, 9e6))
def test_ecef_round_trip(lon: float, lat: float, h: float) -> None:
    lon2, lat2, h2 = ecef_to_geodetic(geodetic_to_ecef(lon, lat, h))
    assert math.isclose(float(lat2), lat, abs_tol=1e-8)
    assert math.isclose((float(lon2) - lon + 180) % 360 - 180, 0.0, abs_tol=1e-8)
    assert math.isclose(float(h2), h, abs_tol=1e-3)


@given(st.floats(-180, 180), st.floats(-89.9, 89.9))
def test_enu_is_orthonormal_and_right_handed(lon: float, lat: float) -> None:
    b = enu_basis(lon, lat)
    assert np.allclose(b @ b.T, np.eye(3), atol=1e-12)
    assert np.allclose(np.cross(b[0], b[1]), b[2], atol=1e-12)


def test_scale_unit_is_paper_000s_d() -> None:
    cam = Camera(0, 0, 100, fov_y=60, width=1280, height=720)
    assert cam.scale == pytest.approx(720 / (2 * math.tan(math.radians(30))))
    # H = h·d/dist: a 100 m tile at 1000 m covers 100·d/1000 pixels
    assert float(cam.screen_size(100.0, 1000.0)) == pytest.approx(cam.scale / 10)
    assert float(cam.screen_error(2.0, 1000.0)) == pytest.approx(2 * cam.scale / 1000)


@pytest.mark.parametrize(("heading", "east", "north"), [(0, 0, 1), (90, 1, 0), (180, 0, -1)])
def test_heading_is_clockwise_from_north(heading: float, east: float, north: float) -> None:
    cam = Camera(10.0, 45.0, 1000.0, heading=heading, pitch=0.0)
    e, n, u = enu_basis(10.0, 45.0) @ cam.forward
    assert (e, n, u) == pytest.approx((east, north, 0.0), abs=1e-12)


def test_pitch_and_roll() -> None:
    down = Camera(10.0, 45.0, 1000.0, pitch=-90.0)
    assert enu_basis(10.0, 45.0) @ down.forward == pytest.approx([0, 0, -1], abs=1e-12)
    banked = Camera(10.0, 45.0, 1000.0, pitch=0.0, roll=30.0)
    right_enu = enu_basis(10.0, 45.0) @ banked.rotation[0]
    assert right_enu[2] == pytest.approx(-math.sin(math.radians(30)))


def test_with_clip_keeps_the_pose_and_a_move_does_not() -> None:
    """A clipped copy shares its camera's worked-out position and rotation (a frame fits its
    clip distances every time); a moved copy works out its own."""
    cam = Camera(-84.2, 36.6, 2000.0, heading=45, pitch=-20)
    pose = (cam.position, cam.rotation)
    clipped = cam.with_clip(1.0, 1e5)
    assert clipped.position is pose[0]
    assert clipped.rotation is pose[1]
    moved = clipped.moved(heading=46.0, alt=2100.0)
    fresh = Camera(-84.2, 36.6, 2100.0, heading=46, pitch=-20)
    assert np.array_equal(moved.rotation, fresh.rotation)
    assert np.array_equal(moved.position, fresh.position)
    assert not np.array_equal(moved.rotation, pose[1])
    # a camera clipped before its pose was asked for: the pose is worked out once for both
    first = Camera(-84.2, 36.6, 2000.0, heading=45, pitch=-20)
    late = first.with_clip(1.0, 1e5)
    assert late.rotation is first.rotation
    assert np.array_equal(late.rotation, pose[1])
    assert np.array_equal(late.position, pose[0])


def test_frustum_contains_what_is_ahead_only() -> None:
    cam = Camera(-84.2, 36.6, 2000.0, heading=45, pitch=-20).with_clip(1.0, 1e5)
    planes = cam.frustum_planes()
    ahead = 5000.0 * cam.forward
    behind = -5000.0 * cam.forward
    beyond = 2e5 * cam.forward
    side = 5000.0 * cam.rotation[0]
    inside = lambda p: bool(np.all(planes[:, :3] @ p + planes[:, 3] >= 0))  # noqa: E731
    assert inside(ahead)
    assert not inside(behind)
    assert not inside(beyond)
    assert not inside(side)
    # the frustum corners lie on the planes
    ty = math.tan(math.radians(30))
    corner = 100.0 * (cam.forward + ty * cam.aspect * cam.rotation[0] + ty * cam.rotation[1])
    assert np.min(planes[:, :3] @ corner + planes[:, 3]) == pytest.approx(0.0, abs=1e-9)


def test_view_projection_centres_the_target() -> None:
    cam = Camera(-84.2, 36.6, 2000.0, heading=45, pitch=-20).with_clip(1.0, 1e5)
    target = cam.position + 3000.0 * cam.forward
    clip = cam.view_projection(target) @ np.array([0, 0, 0, 1.0])
    assert clip[:2] / clip[3] == pytest.approx([0.0, 0.0], abs=1e-9)
    look = Camera.looking_at(-84.2, 36.6, 2000.0, (-84.1, 36.7, 300.0))
    e, n, _ = enu_basis(-84.2, 36.6) @ (geodetic_to_ecef(-84.1, 36.7, 300.0) - look.position)
    assert look.heading == pytest.approx(math.degrees(math.atan2(e, n)) % 360)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lat": float("nan")}, "lat must be a finite number"),
        ({"alt": float("inf")}, "alt must be a finite number"),
        ({"lat": 91.0}, "lat must be within"),
        ({"pitch": -95.0}, "pitch"),
        ({"fov_y": 0.0}, "fov"),
        ({"width": 0}, "width"),
        ({"near": -1.0}, "near"),
    ],
)
def test_invalid_cameras_are_named(kwargs: dict[str, float], message: str) -> None:
    base: dict[str, float] = {"lon": 0.0, "lat": 0.0, "alt": 100.0}
    with pytest.raises(CameraError, match=message):
        Camera(**{**base, **kwargs})  # type: ignore[arg-type]


def test_box_scales_bound_the_projection_everywhere_in_the_box() -> None:
    """A metre up (or along the ground, any direction) anywhere in a box that is on screen
    moves its image no more than ``box_scales`` says, measured by projecting both ends."""
    rng = np.random.default_rng(4)
    worst_v = worst_g = 0.0
    for _ in range(60):
        cam = Camera(
            -84.0, 36.5, float(rng.uniform(200, 5000)), heading=float(rng.uniform(0, 360)),
            pitch=float(rng.uniform(-90, -5)), width=640, height=360,
        ).with_clip(1.0, 1e6)  # fmt: skip
        # a box on the ground somewhere ahead
        ahead = cam.position + cam.forward * rng.uniform(300, 6000)
        lon, lat, _ = ecef_to_geodetic(ahead)
        basis = enu_basis(float(lon), float(lat))
        centre = geodetic_to_ecef(float(lon), float(lat), 0.0) - cam.position
        half = np.array([rng.uniform(20, 800), rng.uniform(20, 800), rng.uniform(1, 200)])
        pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)]) * 2 - 1
        corners = centre + (pick * half) @ basis
        v, g = cam.box_scales(
            corners[None], basis[2][None], basis[0][None], basis[1][None], [0.0], [0.0]
        )
        inner = centre + (rng.uniform(-1, 1, (400, 3)) * half) @ basis

        def image(p: np.ndarray, cam: Camera = cam) -> np.ndarray:
            q = p @ cam.rotation.T
            out: np.ndarray = cam.scale * q[:, :2] / -q[:, 2:3]
            return out

        q = inner @ cam.rotation.T
        ty = math.tan(math.radians(cam.fov_y) / 2)
        seen = (-q[:, 2] > 1.0) & (np.abs(q[:, 0] / -q[:, 2]) <= ty * cam.aspect)
        seen &= np.abs(q[:, 1] / -q[:, 2]) <= ty
        if not seen.any():
            continue
        p = inner[seen]
        step = 1e-3
        up = np.linalg.norm(image(p + step * basis[2]) - image(p), axis=1) / step
        turns = np.linspace(0, np.pi, 16)
        along = max(
            float(np.max(np.linalg.norm(image(p + step * d) - image(p), axis=1) / step))
            for d in np.cos(turns)[:, None] * basis[0] + np.sin(turns)[:, None] * basis[1]
        )
        assert up.max() <= v[0] * (1 + 1e-6)
        assert along <= g[0] * (1 + 1e-6)
        worst_v, worst_g = max(worst_v, up.max() / v[0]), max(worst_g, along / g[0])
    # and it is attained: some box comes close to its bound
    assert worst_v > 0.8
    assert worst_g > 0.8


@given(
    st.floats(-179.0, 179.0),
    st.floats(-80.0, 80.0),
    st.floats(10.0, 2e6),
    st.floats(0.0, 360.0),
    st.floats(-90.0, 0.0),
)
def test_view_projections_are_each_origins_view_projection(
    lon: float, lat: float, alt: float, heading: float, pitch: float
) -> None:
    """The tiles' matrices made at once (the terrain pass) are ``view_projection``'s, one by
    one, to a few ulps of float64: the same float32 matrices on the GPU."""
    cam = Camera(lon, lat, alt, heading=heading, pitch=pitch, width=640, height=360)
    cam = cam.with_clip(1.0, 1e7)
    rng = np.random.default_rng(int(alt))
    origins = cam.position + rng.normal(size=(7, 3)) * alt
    got = cam.view_projections(origins)
    assert got.shape == (7, 4, 4)
    for o, m in zip(origins, got, strict=True):
        want = cam.view_projection(o)
        np.testing.assert_allclose(m, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
    assert cam.view_projections(np.empty((0, 3))).shape == (0, 4, 4)


@given(
    st.floats(-180.0, 180.0),
    st.floats(-89.0, 89.0),
    st.floats(1.0, 8.0),
    st.floats(0.0, 360.0),
    st.floats(-90.0, 90.0),
    st.floats(20.0, 100.0),
)
def test_the_ellipsoid_box_holds_every_pixel_whose_ray_meets_it(
    lon: float, lat: float, log_alt: float, heading: float, pitch: float, fov: float
) -> None:
    """Every pixel centre of a 320×180 view whose ray meets the ellipsoid lies in
    ``ellipsoid_box`` (the terrain pass ray-casts only there), from 10 m up to 100,000 km, any
    way the camera looks; the box reaches at most its two lattice steps beyond what the rays
    of a finer lattice (the view's edges included, as the box's lattice) meet."""
    from lodscape.geo.frames import WGS84_A, WGS84_B

    w, h = 320, 180
    cam = Camera(lon, lat, 10.0**log_alt, heading=heading, pitch=pitch, fov_y=fov, width=w,
                 height=h)  # fmt: skip
    ax = np.array([WGS84_A, WGS84_A, WGS84_B])
    eye = cam.position / ax
    c = float(eye @ eye) - 1.0
    ty = math.tan(math.radians(fov) / 2.0)
    r = cam.rotation

    def meets(nx: np.ndarray, ny: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which rays of the grid nx × ny (NDC) meet the ellipsoid, and the grid."""
        x, y = np.meshgrid(nx * ty * cam.aspect, ny * ty)
        d = (x[..., None] * r[0] + y[..., None] * r[1] - r[2]) / ax
        b = d @ eye
        xs, ys = np.meshgrid(nx, ny)
        return (b < 0.0) & (b * b - (d * d).sum(axis=-1) * c >= 0.0), xs, ys

    hit, xs, ys = meets((np.arange(w) + 0.5) / w * 2.0 - 1.0, (np.arange(h) + 0.5) / h * 2.0 - 1.0)
    box = cam.ellipsoid_box()
    if box is None:  # nothing known: the whole view is ray-cast
        # only from inside, or where what is in view slips between the lattice's rays (a
        # convex region holding none of them covers at most a strip a lattice step wide)
        assert c <= 0.0 or hit.mean() <= 0.03
        return
    x0, y0, x1, y1 = box
    assert not (hit & ((xs < x0) | (xs > x1) | (ys < y0) | (ys > y1))).any()
    # a finer lattice holding the box's own (257 = 4·64 + 1 rays a side)
    fine, fx, fy = meets(np.linspace(-1.0, 1.0, 257), np.linspace(-1.0, 1.0, 257))
    assert fine.any()
    reach = 2.0 * 2.0 / 64 + 1e-9
    assert x0 >= fx[fine].min() - reach
    assert x1 <= fx[fine].max() + reach
    assert y0 >= fy[fine].min() - reach
    assert y1 <= fy[fine].max() + reach


def test_the_ellipsoid_box_is_unknown_from_inside_and_empty_of_the_sky() -> None:
    """No box from inside the ellipsoid; a camera on the ground looking up sees none of it
    (no ray meets it: unknown, the whole view is ray-cast and discards); one looking at the
    horizon has it below the middle of the view and none at the top."""
    assert Camera(10.0, 45.0, -50_000.0).ellipsoid_box() is None
    assert Camera(10.0, 45.0, 100.0, pitch=80.0, fov_y=40.0).ellipsoid_box() is None
    box = Camera(10.0, 45.0, 100.0, pitch=10.0, fov_y=40.0).ellipsoid_box()
    assert box is not None
    assert box[1] == -1.0
    assert box[3] < 0.0
