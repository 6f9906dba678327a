"""Paper 004's three areas around a flying camera: the visible area, the memory area and the
cache area, each a radius corrected per direction. Pure numpy.

Every iteration each chunk (a tile at the level its distance asks for) is classified by its
nearest distance from the camera against the radii, corrected by the angle between the view
direction and the chunk (the scalar product: larger in front, smaller behind) and pushed out
ahead of the motion by the speed. The base radius is what the camera can see: its horizon
(which grows with altitude) or the far plane, whichever is nearer. The level of detail comes
from the same distance (paper 000's pixel band at that distance), so a chunk is asked for at
the level the camera will draw it at when it gets there:

- inside the **memory radius**: decoded into the memory stage (ready to upload);
- inside the **cache radius**: its bytes fetched into the cache stage;
- beyond: left on disk (or on the server).

    r_memory(θ) = memory_share · r_visible · f(cos θ_view) + speed · memory_s · max(cos θ_move, 0)
    r_cache(θ)  =                r_visible · f(cos θ_view) + speed · cache_s  · max(cos θ_move, 0)
    f(c) = behind + (1 − behind) · (1 + c) / 2
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import WGS84_A

__all__ = ["AREAS", "Radii", "RadiiOptions", "Reach", "horizon", "radii_for"]

F64 = NDArray[np.float64]
#: A selection's stand-in for the frustum test: (box centres from the camera (N, 3), nearest
#: distances (N,)) -> which chunks to keep.
Reach = Callable[[F64, F64], NDArray[np.bool_]]

#: Area codes, nearest first: what ``Radii.classify`` returns.
AREAS = ("memory", "cache", "disk")


@dataclass(frozen=True)
class RadiiOptions:
    """How far the memory and cache areas reach."""

    #: The memory radius as a share of the visible radius (the cache radius is all of it).
    memory_share: float = 0.5
    #: Seconds of travel the memory and cache radii reach ahead of the motion.
    memory_s: float = 1.0
    cache_s: float = 3.0
    #: The radii behind the camera as a share of those in front (the scalar product's
    #: correction: 1 would make them circles).
    behind: float = 0.35

    def __post_init__(self) -> None:
        if not 0.0 < self.memory_share <= 1.0:
            raise ValueError(f"Expected 0 < memory_share <= 1, got {self.memory_share}")
        if not 0.0 <= self.memory_s <= self.cache_s:
            raise ValueError(
                f"Expected 0 <= memory_s <= cache_s, got {self.memory_s} and {self.cache_s}"
            )
        if not 0.0 < self.behind <= 1.0:
            raise ValueError(f"Expected 0 < behind <= 1, got {self.behind}")


@dataclass(frozen=True)
class Radii:
    """One iteration's radii: the base (visible) radius, the view and motion directions and
    the speed, in metres and ECEF unit vectors."""

    visible: float
    view: F64
    motion: F64
    speed: float
    options: RadiiOptions

    def radius(self, area: str, direction: F64) -> F64:
        """The ``area``'s radius ("memory" or "cache") towards each unit ``direction`` (N, 3)
        from the camera, metres."""
        o = self.options
        c_view = direction @ self.view
        c_move = np.maximum(direction @ self.motion, 0.0)
        f = o.behind + (1.0 - o.behind) * (1.0 + c_view) / 2.0
        share, ahead = (o.memory_share, o.memory_s) if area == "memory" else (1.0, o.cache_s)
        out: F64 = share * self.visible * f + self.speed * ahead * c_move
        return out

    def classify(self, centre: F64, dist_near: F64) -> NDArray[np.int64]:
        """Per chunk (box centre relative to the camera (N, 3), nearest distance (N,)), its
        area: 0 memory, 1 cache, 2 disk (``AREAS``)."""
        return self.rank(centre, dist_near)[0]

    def rank(self, centre: F64, dist_near: F64) -> tuple[NDArray[np.int64], F64]:
        """Per chunk its area (as ``classify``) and its urgency: its distance in units of the
        cache radius towards it (ahead before behind; below 1 inside the cache area)."""
        norm = np.linalg.norm(centre, axis=1)
        direction = centre / np.maximum(norm, 1e-9)[:, None]
        # the camera's own chunk: counted as in front
        direction[norm < 1e-9] = self.view
        cache = self.radius("cache", direction)
        area = np.full(len(centre), 2, np.int64)
        area[dist_near <= cache] = 1
        area[dist_near <= self.radius("memory", direction)] = 0
        urgency: F64 = dist_near / np.maximum(cache, 1e-9)
        return area, urgency

    def reach(self, area: str) -> Reach:
        """The test a selection keeps a chunk by: inside ``area`` ("memory" or "cache")."""
        limit = AREAS.index(area)

        def inside(centre: F64, dist_near: F64) -> NDArray[np.bool_]:
            out: NDArray[np.bool_] = self.classify(centre, dist_near) <= limit
            return out

        return inside


def horizon(height: float) -> float:
    """Metres to the horizon from ``height`` metres above the ground (a sphere of the
    equatorial radius)."""
    h = max(height, 1.0)
    return math.sqrt(h * (2.0 * WGS84_A + h))


def radii_for(
    position: F64,
    view: F64,
    velocity: F64,
    height: float,
    far: float,
    options: RadiiOptions,
) -> Radii:
    """The radii of a camera at ``position`` (ECEF) looking along ``view`` (unit), moving at
    ``velocity`` (m/s, ECEF), ``height`` metres above the ground below it, its far plane at
    ``far`` metres: the visible radius is the nearer of the horizon and the far plane."""
    speed = float(np.linalg.norm(velocity))
    motion = velocity / speed if speed > 1e-6 else np.asarray(view, np.float64)
    visible = min(horizon(height), far)
    return Radii(visible, np.asarray(view, np.float64), motion, speed, options)
