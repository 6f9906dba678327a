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

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.errors import CameraError
from lodscape.geo.frames import ecef_to_geodetic, enu_basis, geodetic_to_ecef

__all__ = ["MIN_DISTANCE", "Camera"]

#: Metres: the closest distance a screen-space formula sees (below it, a point is on the eye).
MIN_DISTANCE = 1e-3


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
        return replace(self, near=near, far=far)

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
        """Screen-space error in pixels of a geometric error (metres) seen at ``distance``: the
        quadtree, the globe and the city all refine by this one formula."""
        return self.screen_size(error, distance)

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

    def frustum_planes(self) -> NDArray[np.float64]:
        """Six planes (nx, ny, nz, w), inward unit normals, for points given relative to the
        camera position: p is inside when n·p + w >= 0 for all six (left, right, bottom, top,
        near, far)."""
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
        return np.concatenate([normals, w[:, None]], axis=1)

    def geodetic(self) -> tuple[float, float, float]:
        lon, lat, h = ecef_to_geodetic(self.position)
        return float(lon), float(lat), float(h)
