"""The terrain as a frame's layer (its quadtree selection, its tiles' loads and the patches
facing away), and the layers that stand on it: the city and the ellipsoid behind it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError
from lodscape.lod.camera import Camera
from lodscape.lod.radii import RadiiOptions, radii_for
from lodscape.lod.select import LearnsFromLoads, MadeOnDemand
from lodscape.lod.view import DrawItem, FramePlan, TerrainView
from lodscape.stream.loader import Areas, Loader, LoadReport

__all__ = ["CameraDraws", "CityLayer", "EllipsoidLayer", "TerrainDraws", "TerrainLayer"]


@dataclass(frozen=True)
class TerrainDraws:
    """The terrain's tiles a frame draws, with the camera fitted to them."""

    camera: Camera
    items: list[DrawItem]


@dataclass(frozen=True)
class CameraDraws:
    """A layer drawn whole from the frame's camera (the city's objects, the ellipsoid), and the
    camera's height above the ground under it (None: no ground there)."""

    camera: Camera
    above_ground: float | None = None


class TerrainLayer:
    """A tile tree's selection for each camera (``lod.view.TerrainView``): the tiles to draw,
    the loads they need, and (once served) the draw list less what faces away."""

    name = "terrain"

    def __init__(
        self,
        view: TerrainView,
        fit: Callable[[Camera], Camera],
        ground: Callable[[float, float], float | None] | None = None,
    ) -> None:
        self.view = view
        #: The camera with its clip distances fitted to the terrain (refuses one underground),
        #: and the ground's height under a point (None: outside the data).
        self.fit = fit
        self.ground = ground
        self.tree: Any = view.tree
        #: Draw tiles whole unless all of them faces away (the GPU terrain mode's patches).
        self.whole_tiles = False
        #: The last plan (None before the first).
        self.last: FramePlan | None = None
        self._epoch: int | None = None
        self._figures: dict[str, Any] = {}

    @property
    def camera(self) -> Camera:
        """The last plan's fitted camera."""
        if self.last is None:
            raise RuntimeError("no frame planned yet")
        return self.last.camera

    def plan(self, camera: Camera, resident: NDArray[np.uint64], *, blocking: bool) -> FramePlan:
        cam = self.fit(camera)
        tree = self.tree
        self._epoch = tree.epoch if isinstance(tree, LearnsFromLoads) else None
        if isinstance(tree, MadeOnDemand):
            # a whole picture waits for the statistics it needs, a streamed frame does not
            tree.wait = blocking
        self.last = self.view.update(cam, resident, blocking=blocking)
        return self.last

    def learned(self) -> bool:
        # a tree that learns as tiles come (a server's): a level deeper a round
        return self._epoch is not None and self.tree.epoch != self._epoch

    def draws(self, report: LoadReport, loader: Loader) -> TerrainDraws:
        plan = self.last
        assert plan is not None
        if report.absent:
            # a root the server failed is not drawn (what is behind shows there) until it comes
            kept = [
                it
                for it in plan.items
                if it.key not in report.absent and it.texture not in report.absent
            ]
            plan = replace(plan, items=kept)
        items, culled, culled_tris = self.view.facing(
            plan, loader.gpu.meshes, whole_tiles=self.whole_tiles
        )
        self._figures = {
            "selection": plan.selection.stats(),
            "backfacing": culled,
            "backfacing_triangles": culled_tris,
        }
        return TerrainDraws(plan.camera, items)

    def figures(self) -> dict[str, Any]:
        return self._figures

    # --- what the loader asks ahead of the frames (on its workers) ---------------------------

    def predict(self, camera: Camera) -> list[int] | None:
        """The keys a camera the flight is heading for would draw (None: it cannot be)."""
        try:
            return self.view.predict(self.fit(camera))
        except CameraError:
            return None

    def areas_within(self, radii: RadiiOptions | None) -> Areas | None:
        """Paper 004's areas with ``radii`` (None: no areas, the loader predicts alone)."""
        if radii is None:
            return None

        def areas(
            camera: Camera, velocity: NDArray[np.float64]
        ) -> tuple[list[int], list[int], dict[str, int]] | None:
            return self.areas(camera, velocity, radii)

        return areas

    def areas(
        self, camera: Camera, velocity: NDArray[np.float64], radii: RadiiOptions
    ) -> tuple[list[int], list[int], dict[str, int]] | None:
        """The memory and cache areas around ``camera`` moving at ``velocity``
        (``lod.radii``), as keys to prefetch (None: the camera cannot be)."""
        try:
            cam = self.fit(camera)
        except CameraError:
            return None
        ground = None if self.ground is None else self.ground(cam.lon, cam.lat)
        floor = self.tree.height_range[0] if ground is None else ground
        assert cam.far is not None
        r = radii_for(cam.position, cam.forward, velocity, cam.alt - floor, cam.far, radii)
        return self.view.areas(cam, r)


class _StandsOnTerrain:
    """A layer with nothing to load, drawn from the terrain layer's fitted camera."""

    name = ""

    def __init__(
        self, terrain: TerrainLayer, ground: Callable[[float, float], float | None]
    ) -> None:
        self.terrain = terrain
        self.ground = ground

    def plan(self, camera: Camera, resident: NDArray[np.uint64], *, blocking: bool) -> None:
        return None

    def learned(self) -> bool:
        return False

    def draws(self, report: LoadReport, loader: Loader) -> CameraDraws:
        cam = self.terrain.camera
        ground = self.ground(cam.lon, cam.lat)
        return CameraDraws(cam, None if ground is None else cam.alt - ground)

    def figures(self) -> dict[str, Any]:
        return {}


class CityLayer(_StandsOnTerrain):
    """The city's objects (paper 001): its R-tree scene is culled and its LODs chosen by the
    pass itself, on the GPU's occlusion queries."""

    name = "city"


class EllipsoidLayer(_StandsOnTerrain):
    """The ellipsoid (height 0) wherever the terrain leaves the sky: the world outside the data
    and under its holes (cesium-native's ``EllipsoidTilesetLoader``, one ray per pixel)."""

    name = "ellipsoid"
