"""The frame loop's GL side (``lodscape.frame``): the renderer's target, and a pass for each
layer that draws into it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import moderngl
import numpy as np
from numpy.typing import NDArray

from lodscape.frame.globe import GlobeDraws, ImageryDraws
from lodscape.frame.terrain import CameraDraws, TerrainDraws
from lodscape.lod.camera import Camera
from lodscape.render._context import is_software
from lodscape.render.city_pass import CityPass
from lodscape.render.globe_pass import GlobePass
from lodscape.render.terrain_pass import Renderer

__all__ = [
    "CityDrawPass",
    "EllipsoidPass",
    "GlobeFacetPass",
    "GlobeImageryPass",
    "RendererTarget",
    "TerrainPass",
]

Rgb = tuple[float, float, float]


class RendererTarget:
    """The renderer's colour + distance target (``frame.Target``), or with ``labelled`` its
    label target: per pixel the view-space normal and the semantic label, for datasets."""

    def __init__(self, renderer: Renderer, *, labelled: bool = False) -> None:
        self.renderer = renderer
        self.labelled = labelled

    def begin(self, camera: Camera, *, background: Rgb | None = None) -> moderngl.Framebuffer:
        return self.renderer.begin(camera, background=background, labelled=self.labelled)

    def end(self, camera: Camera) -> tuple[NDArray[Any], NDArray[np.float32]]:
        return self.renderer.end(camera, self.labelled)

    @property
    def fbo(self) -> moderngl.Framebuffer:
        """The framebuffer being drawn."""
        r = self.renderer
        got = r.label_framebuffer if self.labelled else r.framebuffer
        if got is None:
            raise RuntimeError("no frame begun")
        return got


class TerrainPass:
    """The terrain's tiles (either terrain mode)."""

    def __init__(self, renderer: Renderer) -> None:
        self.renderer = renderer

    def draw(self, draws: TerrainDraws, target: RendererTarget) -> None:
        self.renderer.draw_tiles(draws.camera, draws.items, labelled=target.labelled)

    def figures(self) -> dict[str, Any]:
        st = self.renderer.last_stats
        return {
            "triangles": st.triangles,
            "draw_calls": st.draw_calls,
            "submit_ms": round(st.submit_ms, 2),
            "terrain_mode": self.renderer.terrain_mode,
        }


class EllipsoidPass:
    """The ellipsoid where nothing was drawn (one ray per pixel, behind everything)."""

    def __init__(self, renderer: Renderer) -> None:
        self.renderer = renderer

    def draw(self, draws: CameraDraws, target: RendererTarget) -> None:
        self.renderer.draw_ellipsoid(draws.camera, labelled=target.labelled)

    def figures(self) -> dict[str, Any]:
        return {}


class CityDrawPass:
    """The city's objects, in the same target (their LODs by the camera's height above the
    ground; occlusion queries against what is drawn before them)."""

    def __init__(self, city: CityPass, options: Callable[[], Any]) -> None:
        self.city = city
        self.options = options
        self.software = is_software(city.ctx)

    def draw(self, draws: CameraDraws, target: RendererTarget) -> None:
        cp = self.city
        fbo = target.fbo
        opts = self.options().resolved(self.software, draws.above_ground)
        if not target.labelled:
            cp.draw(draws.camera, opts, fbo)
            fbo.use()
            return
        # the label pass draws the same objects again: its figures stay the colour frame's
        cp.use_labels(True)
        last = cp.last
        try:
            cp.draw(draws.camera, opts, fbo)
        finally:
            cp.use_labels(False)
            cp.last = last
        fbo.use()

    def figures(self) -> dict[str, Any]:
        figures: dict[str, Any] = self.city.last.as_dict()
        return figures


class GlobeFacetPass:
    """The globe's facets, first in the frame (a dataset's label pass leaves them out)."""

    def __init__(self, globe: GlobePass) -> None:
        self.globe = globe

    def draw(self, draws: GlobeDraws, target: RendererTarget) -> None:
        if not target.labelled:
            self.globe.draw_facets(draws.camera, draws.mesh, target.fbo)
            target.fbo.use()

    def figures(self) -> dict[str, Any]:
        return {}


class GlobeImageryPass:
    """The imagery layers' tiles over the globe's facets, their images the target renderer's
    textures (loaded with the terrain's by the frame's one loader)."""

    def __init__(self, globe: GlobePass) -> None:
        self.globe = globe

    def draw(self, draws: ImageryDraws, target: RendererTarget) -> None:
        if target.labelled or not draws.layers:
            return
        r = target.renderer
        colour, dist = r.attachments
        self.globe.draw_imagery(draws.camera, draws.layers, colour, dist, r.texture)
        target.fbo.use()

    def figures(self) -> dict[str, Any]:
        return {}
