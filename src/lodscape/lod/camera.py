"""The camera: a frozen value owning the screen-space formulas (paper 000, cesium-native ViewState).

Position is geodetic (lon°, lat°, metres above sea level, taken as the ellipsoid: lodscape ignores
the geoid, so terrain heights and camera altitudes share one datum). Orientation is heading
(degrees clockwise from north), pitch (degrees, negative looking down) and roll (degrees, positive
banks right), in the local east-north-up frame at the camera. Everything is float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property
from typing import TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.errors import CameraError
from lodscape.geo.frames import WGS84_A, WGS84_B, ecef_to_geodetic, enu_basis, geodetic_to_ecef

__all__ = ["EARTH_MIN_RADIUS", "MIN_DISTANCE", "Camera"]

#: Metres: the closest distance a screen-space formula sees (below it, a point is on the eye).
MIN_DISTANCE = 1e-3
#: Metres: the ellipsoid's smallest radius of curvature (WGS84's meridian radius at the equator,
#: rounded down): over a ground distance s its normal turns by at most s / this.
EARTH_MIN_RADIUS = 6.3e6


_Posed = TypeVar("_Posed", bound="Camera")


@dataclass(frozen=True)
class Camera:
    """Where the viewer is, where it looks, and the viewport it draws into."""

    lon: float
    lat: float
    alt: float
    heading: float = 0.0
    pitch: float = -30.0
    roll: float = 0.0
    fov_y: float = 60.0
    width: int = 1280
    height: int = 720
    #: Clip distances in metres; None lets the scene choose them from the terrain under the camera.
    near: float | None = None
    far: float | None = None

    def __post_init__(self) -> None:
        for name in ("lon", "lat", "alt", "heading", "pitch", "roll", "fov_y"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not math.isfinite(value):
                raise CameraError(f"camera {name} must be a finite number, got {value!r}")
        if not -90.0 <= self.lat <= 90.0:
            raise CameraError(f"camera lat must be within -90..90 degrees, got {self.lat}")
        if not -90.0 <= self.pitch <= 90.0:
            raise CameraError(f"camera pitch must be within -90..90 degrees, got {self.pitch}")
        if not 0.0 < self.fov_y < 180.0:
            raise CameraError(f"camera fov must be within 0..180 degrees, got {self.fov_y}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= 16384:
                raise CameraError(
                    f"camera {name} must be a whole number of pixels 1..16384, got {value!r}"
                )
        for name in ("near", "far"):
            value = getattr(self, name)
            if value is not None and (not math.isfinite(value) or value <= 0.0):
                raise CameraError(f"camera {name} must be a positive distance, got {value!r}")
        if self.near is not None and self.far is not None and self.far <= self.near:
            raise CameraError(f"camera far ({self.far}) must exceed near ({self.near})")

    # --- construction ------------------------------------------------------------------

    def with_clip(self, near: float, far: float) -> Camera:
        return self.posed_as(replace(self, near=near, far=far))

    def posed_as(self, other: _Posed) -> _Posed:
        """``other`` (a copy of this camera's pose: other clip distances, another projection)
        with this camera's position and rotation, worked out once for both: a frame fits its
        camera's clip distances and draws it upside down every time."""
        other.__dict__["position"] = self.position
        other.__dict__["rotation"] = self.rotation
        return other

    def moved(self, **changes: float) -> Camera:
        """A copy with some fields changed (e.g. ``cam.moved(alt=500)``)."""
        return replace(self, **changes)  # type: ignore[arg-type]

    @classmethod
    def looking_at(
        cls,
        lon: float,
        lat: float,
        alt: float,
        target: tuple[float, float, float],
        **kwargs: float | int,
    ) -> Camera:
        """A camera at (lon, lat, alt) whose view axis passes through ``target`` (lon, lat, h)."""
        eye = geodetic_to_ecef(lon, lat, alt)
        to = geodetic_to_ecef(*target) - eye
        e, n, u = enu_basis(lon, lat) @ to
        heading = math.degrees(math.atan2(e, n)) % 360.0
        pitch = math.degrees(math.atan2(u, math.hypot(e, n)))
        return cls(lon, lat, alt, heading=heading, pitch=pitch, **kwargs)  # type: ignore[arg-type]

    # --- frames ------------------------------------------------------------------------

    @cached_property
    def position(self) -> NDArray[np.float64]:
        """ECEF position, metres."""
        return geodetic_to_ecef(self.lon, self.lat, self.alt)

    @cached_property
    def rotation(self) -> NDArray[np.float64]:
        """World (ECEF) to view rotation: rows right, up, back (the view looks down -Z as in GL)."""
        h, p, r = (math.radians(a) for a in (self.heading, self.pitch, self.roll))
        fwd = np.array([math.sin(h) * math.cos(p), math.cos(h) * math.cos(p), math.sin(p)])
        right = np.array([math.cos(h), -math.sin(h), 0.0])
        up = np.cross(right, fwd)
        # positive roll banks right: the right vector dips towards the ground
        right, up = math.cos(r) * right - math.sin(r) * up, math.sin(r) * right + math.cos(r) * up
        basis = enu_basis(self.lon, self.lat)
        return np.stack([right @ basis, up @ basis, -(fwd @ basis)])

    @property
    def forward(self) -> NDArray[np.float64]:
        fwd: NDArray[np.float64] = -self.rotation[2]
        return fwd

    @property
    def scale(self) -> float:
        """Paper 000's unit of scale d = viewport_height / (2·tan(fovy/2)), in pixels."""
        return self.height / (2.0 * math.tan(math.radians(self.fov_y) / 2.0))

    @property
    def aspect(self) -> float:
        return self.width / self.height

    # --- screen-space formulas ----------------------------------------------------------

    def pixels_per_metre(self, distance: ArrayLike) -> NDArray[np.float64]:
        """d/dist: pixels a metre covers at ``distance``, the one place a distance is clamped
        (to the near plane, and never under a millimetre: nothing is seen closer)."""
        floor = max(self.near or 0.0, MIN_DISTANCE)
        return self.scale / np.maximum(np.asarray(distance, np.float64), floor)

    def screen_size(self, size: ArrayLike, distance: ArrayLike) -> NDArray[np.float64]:
        """Paper 000's H = h·d/dist: pixels covered by ``size`` metres at ``distance``."""
        return np.asarray(size, np.float64) * self.pixels_per_metre(distance)

    def screen_error(self, error: ArrayLike, distance: ArrayLike) -> NDArray[np.float64]:
        """Screen-space error in pixels of a geometric error (metres) seen at ``distance``, in
        any direction: the globe and the city refine by it (the quadtree by ``box_scales``,
        the projection's own measure over a tile's box)."""
        return self.screen_size(error, distance)

    def box_scales(
        self,
        corners: ArrayLike,
        up: ArrayLike,
        east: ArrayLike,
        north: ArrayLike,
        spread: ArrayLike,
        nearest: ArrayLike,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The most pixels a metre covers anywhere in N boxes, as the projection draws it: along
        the vertical (a height error) and along the ground (a texel's side).

        ``corners`` (N, 8, 3) are each box's corners relative to the camera (ECEF metres),
        ``up``/``east``/``north`` (N, 3) the frame at each box's centre, ``spread`` (N) radians
        the normal turns by within a box, ``nearest`` (N) the distance from the eye to each
        box. A displacement v at a point of depth Z whose image is d·(a, b) = d·(X/Z, Y/Z)
        moves it d/Z·(v_x − a·v_z, v_y − b·v_z) pixels (first order, v_z along the view axis):
        a vertical error seen along the line of sight does not show, one across it shows whole,
        and off the axis the image stretches. The bound takes the smallest depth of the box's
        visible part (its corners' where all are in front; never nearer than the near plane,
        nor than its distance times the cosine of the viewport's corner angle, since a visible
        point is within that angle of the axis) and the worst of (a, b) over the box's image
        clipped to the viewport (a linear-fractional map: its extremes are at corners), so it
        holds at every point of the box that is on screen.
        """
        pts = np.asarray(corners, np.float64)
        rot = self.rotation
        cam = pts @ rot.T
        depth = -cam[..., 2]
        floor = max(self.near or 0.0, MIN_DISTANCE)
        zmin = depth.min(axis=-1)
        crosses = zmin < floor
        ty = math.tan(math.radians(self.fov_y) / 2.0)
        tx = ty * self.aspect
        zs = np.maximum(depth, floor)
        a, b = cam[..., 0] / zs, cam[..., 1] / zs
        # a box reaching behind the near plane may cover the whole viewport
        a0 = np.where(crosses, -tx, np.clip(a.min(axis=-1), -tx, tx))
        a1 = np.where(crosses, tx, np.clip(a.max(axis=-1), -tx, tx))
        b0 = np.where(crosses, -ty, np.clip(b.min(axis=-1), -ty, ty))
        b1 = np.where(crosses, ty, np.clip(b.max(axis=-1), -ty, ty))
        u, e, n = (np.asarray(v, np.float64) @ rot.T for v in (up, east, north))
        # view-space components: x right, y up, f along the view axis (GL looks down -z)
        uf, ef, nf = -u[..., 2], -e[..., 2], -n[..., 2]
        # the four corners of the image's box at once (axis 0), the worst of each kept
        ca = np.stack([a0, a0, a1, a1])
        cb = np.stack([b0, b1, b0, b1])
        vertical = np.hypot(u[..., 0] - ca * uf, u[..., 1] - cb * uf).max(axis=0)
        # the largest singular value of the ground's 2×2 image
        m00, m01 = e[..., 0] - ca * ef, n[..., 0] - ca * nf
        m10, m11 = e[..., 1] - cb * ef, n[..., 1] - cb * nf
        sq = m00 * m00 + m01 * m01 + m10 * m10 + m11 * m11
        det = m00 * m11 - m01 * m10
        ground = np.sqrt((sq + np.sqrt(np.maximum(sq * sq - 4.0 * det * det, 0.0))) / 2.0).max(
            axis=0
        )
        # the most any unit direction stretches: what a turned normal may add
        stretch = np.sqrt(1.0 + ca * ca + cb * cb).max(axis=0)
        slack = np.asarray(spread, np.float64) * stretch
        corner = 1.0 / math.sqrt(1.0 + tx * tx + ty * ty)
        per_metre = self.pixels_per_metre(
            np.maximum(zmin, np.asarray(nearest, np.float64) * corner)
        )
        return per_metre * (vertical + slack), per_metre * (ground + slack)

    # --- clip space --------------------------------------------------------------------

    def _clip(self) -> tuple[float, float]:
        if self.near is None or self.far is None:
            raise CameraError("camera has no near/far clip distances yet (use with_clip)")
        return self.near, self.far

    def projection(self) -> NDArray[np.float64]:
        """OpenGL perspective matrix (column vectors)."""
        near, far = self._clip()
        f = 1.0 / math.tan(math.radians(self.fov_y) / 2.0)
        return np.array(
            [
                [f / self.aspect, 0.0, 0.0, 0.0],
                [0.0, f, 0.0, 0.0],
                [0.0, 0.0, (far + near) / (near - far), 2.0 * far * near / (near - far)],
                [0.0, 0.0, -1.0, 0.0],
            ]
        )

    def view_projection(self, origin: ArrayLike) -> NDArray[np.float64]:
        """Projection · view for positions given relative to ``origin`` (ECEF), built in float64.

        The translation (origin - camera) is folded in before the cast to float32, so vertices
        stored relative to a tile centre never meet the Earth-sized numbers on the GPU.
        """
        view = np.eye(4)
        view[:3, :3] = self.rotation
        view[:3, 3] = self.rotation @ (np.asarray(origin, np.float64) - self.position)
        return self.projection() @ view

    def view_projections(self, origins: ArrayLike) -> NDArray[np.float64]:
        """``view_projection`` of each of ``origins`` (N, 3), (N, 4, 4), in a few array
        operations: the matrices differ only in their translation column, P·(R·(o − eye), 1)."""
        o = np.asarray(origins, np.float64).reshape(-1, 3)
        p = self.projection()
        out = np.empty((o.shape[0], 4, 4))
        out[:, :, :3] = p[:, :3] @ self.rotation
        out[:, :, 3] = ((o - self.position) @ self.rotation.T) @ p[:, :3].T + p[:, 3]
        return out

    def ellipsoid_box(
        self, samples: int = 65, axes: tuple[float, float, float] = (WGS84_A, WGS84_A, WGS84_B)
    ) -> tuple[float, float, float, float] | None:
        """Where in the view rays meet the ellipsoid of semi-axes ``axes`` (ECEF): (x0, y0, x1,
        y1) in normalised device coordinates, y up, clipped to the view; None where that is not
        known (the eye inside, or no sampled ray meets it: nothing of it, or less than a lattice
        cell, is in view). The rays of a ``samples``² lattice over the view are tested and the
        box around those that meet it widened by two lattice steps (1/32 of the view): what a
        convex body shows from outside is a convex region, here an ellipse or the inside of a
        conic, stretched no more than a wide lens stretches a circle at its corners, so nothing
        of it reaches a lattice step beyond the rays that meet it (tests/test_camera.py: every
        pixel of 320×180 views from 10 m to 100,000 km, any way the camera looks)."""
        ax = np.asarray(axes, np.float64)
        eye = self.position / ax
        c = float(eye @ eye) - 1.0
        if c <= 0.0:
            return None
        ty = math.tan(math.radians(self.fov_y) / 2.0)
        g = np.linspace(-1.0, 1.0, samples)
        x, y = np.meshgrid(g * ty * self.aspect, g * ty)
        # view-space rays (x, y, -1) to ECEF (the rotation's rows are the view axes), scaled
        r = self.rotation
        d = (x[..., None] * r[0] + y[..., None] * r[1] - r[2]) / ax
        b = d @ eye
        hit = (b < 0.0) & (b * b - (d * d).sum(axis=-1) * c >= 0.0)
        if not hit.any():
            return None
        rows = np.flatnonzero(hit.any(axis=1))
        cols = np.flatnonzero(hit.any(axis=0))
        step = 2.0 * (g[1] - g[0])
        return (
            max(-1.0, float(g[cols[0]]) - step),
            max(-1.0, float(g[rows[0]]) - step),
            min(1.0, float(g[cols[-1]]) + step),
            min(1.0, float(g[rows[-1]]) + step),
        )

    def frustum_planes(self) -> NDArray[np.float64]:
        """Six planes (nx, ny, nz, w), inward unit normals, for points given relative to the
        camera position: p is inside when n·p + w >= 0 for all six (left, right, bottom, top,
        near, far). Worked out once a camera (read-only: a selection asks for them per level)."""
        return self._frustum_planes

    @cached_property
    def _frustum_planes(self) -> NDArray[np.float64]:
        near, far = self._clip()
        rot = self.rotation
        right, up, back = rot[0], rot[1], rot[2]
        fwd = -back
        ty = math.tan(math.radians(self.fov_y) / 2.0)
        tx = ty * self.aspect
        normals = np.stack(
            [
                right + tx * fwd,  # left plane: x >= -tx·z
                -right + tx * fwd,
                up + ty * fwd,
                -up + ty * fwd,
                fwd,
                -fwd,
            ]
        )
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        w = np.array([0.0, 0.0, 0.0, 0.0, -near, far])
        planes = np.concatenate([normals, w[:, None]], axis=1)
        planes.flags.writeable = False
        return planes

    def geodetic(self) -> tuple[float, float, float]:
        lon, lat, h = ecef_to_geodetic(self.position)
        return float(lon), float(lat), float(h)
