"""The frame loop's GL side (``lodscape.frame``): the renderer's target, and a pass for each
layer that draws into it."""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future
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
from lodscape.render.tess_pass import MAX_OVERLAYS, TessellationUnavailable

__all__ = [
    "CityDrawPass",
    "EllipsoidPass",
    "GlobeFacetPass",
    "GlobeImageryPass",
    "RendererTarget",
    "TerrainPass",
    "make_renderer",
    "prefetch_blue_marble",
]

Rgb = tuple[float, float, float]


def make_renderer(
    camera: Camera,
    *,
    ctx: moderngl.Context | None,
    terrain_mode: str,
    tess_px: float,
    layers: int,
    earth: tuple[float, float, float, float] | None,
    **options: Any,
) -> tuple[Renderer, str | None]:
    """A scene's renderer: in ``terrain_mode`` where the GL has tessellation (else the CPU
    mode, and the note that says why), drawing at most ``MAX_OVERLAYS`` of ``layers`` imagery
    layers (more are refused by the frame that carries them), the Blue Marble on its ellipsoid
    outside the ``earth`` box (west, south, east, north) where installed; ``options`` are the
    ``Renderer``'s. A texture compression the GL cannot do is said on stderr."""
    from lodscape.imagery.layers import warn_stderr

    common = {"ctx": ctx, "layers": min(layers, MAX_OVERLAYS), **options}
    note = None
    try:
        renderer = Renderer(
            camera.width, camera.height, terrain_mode=terrain_mode, tess_px=tess_px, **common
        )
    except TessellationUnavailable as exc:
        note = f"{exc}; drawing in the CPU terrain mode"
        renderer = Renderer(camera.width, camera.height, **common)
    if renderer.compress_note is not None:
        warn_stderr(renderer.compress_note)
    if renderer.ellipsoid and earth is not None:
        renderer.set_earth(_blue_marble(), earth)
    return renderer, note


_EARTH: Future[NDArray[np.uint8] | None] | None = None
_EARTH_LOCK = threading.Lock()


def prefetch_blue_marble() -> None:
    """Start reading NASA's Blue Marble on a thread of its own, once a process: a scene that
    draws it asks for it as it opens, so its decoding (a sixth of a second) runs beside the
    DEM's reading instead of before the first picture."""
    global _EARTH
    with _EARTH_LOCK:
        if _EARTH is not None:
            return
        future: Future[NDArray[np.uint8] | None] = Future()
        _EARTH = future
    threading.Thread(
        target=_read_blue_marble, args=(future,), name="lodscape-earth", daemon=True
    ).start()


def _read_blue_marble(future: Future[NDArray[np.uint8] | None]) -> None:
    from lodscape.imagery.globe import earth_image

    try:
        image, notice = earth_image()
    except BaseException as exc:
        future.set_exception(exc)
        return
    future.set_result(None if notice is not None else image)


def _blue_marble() -> NDArray[np.uint8] | None:
    """NASA's Blue Marble for the world outside the data, read once a process (None: not
    installed; the ellipsoid stays grey); a read that failed is tried again next time."""
    global _EARTH
    prefetch_blue_marble()
    future = _EARTH
    assert future is not None
    try:
        return future.result()
    except BaseException:
        with _EARTH_LOCK:
            if _EARTH is future:
                _EARTH = None
        raise


class RendererTarget:
    """The renderer's colour + distance target (``frame.Target``), or with ``labelled`` its
    label target: per pixel the view-space normal and the semantic label, for datasets."""

    def __init__(self, renderer: Renderer, *, labelled: bool = False) -> None:
        self.renderer = renderer
        self.labelled = labelled

    def begin(self, camera: Camera, *, background: Rgb | None = None) -> moderngl.Framebuffer:
        return self.renderer.target.begin(camera, background=background, labelled=self.labelled)

    def end(self, camera: Camera) -> tuple[NDArray[Any], NDArray[np.float32]]:
        return self.renderer.target.end(camera, self.labelled)

    @property
    def fbo(self) -> moderngl.Framebuffer:
        """The framebuffer being drawn."""
        return self.renderer.target.fbo(self.labelled)

    def camera(self, camera: Camera) -> Camera:
        """``camera`` as the frame begun draws it (``FrameTarget.camera``)."""
        return self.renderer.target.camera(camera)


class TerrainPass:
    """The terrain's tiles (either terrain mode)."""

    def __init__(self, renderer: Renderer) -> None:
        self.renderer = renderer

    def draw(self, draws: TerrainDraws, target: RendererTarget) -> None:
        self.renderer.draw_tiles(target.camera(draws.camera), draws.items, labelled=target.labelled)

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
        self.renderer.draw_ellipsoid(target.camera(draws.camera), labelled=target.labelled)

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
        camera = target.camera(draws.camera)
        if not target.labelled:
            cp.draw(camera, opts, fbo)
            fbo.use()
            return
        # the label pass draws the same objects again: its figures stay the colour frame's
        cp.use_labels(True)
        last = cp.last
        try:
            cp.draw(camera, opts, fbo)
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
            self.globe.draw_facets(target.camera(draws.camera), draws.mesh, target.fbo)
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
        colour, dist = r.target.attachments
        camera = target.camera(draws.camera)
        self.globe.draw_imagery(camera, draws.layers, colour, dist, r.texture)
        target.fbo.use()

    def figures(self) -> dict[str, Any]:
        return {}
