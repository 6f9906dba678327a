"""The whole globe (paper 002) from Python: the QTM facets, the imagery layers over all of the
Earth, and the terrain's own tiles (and its city) where it has data, in one frame loop, one
target and one depth test.

    with lodscape.open("dem.tif", globe=lodscape.GlobeOptions()) as globe:
        rgb, depth = globe.render(lodscape.Camera(lon, lat, 2e6, pitch=-90))

With a terrain whose tiles are drawn, the globe's layers join the terrain scene's own frames
(its loader, its renderer, its read-back); without one, the globe has a loop of its own over
its imagery layers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import LodscapeError
from lodscape.frame import FrameLoop, FrameStats, Layer, Pass
from lodscape.frame.globe import (
    SKY_HIGH,
    SKY_LOW,
    GlobeImageryLayer,
    GlobeLayer,
    GlobeOptions,
    LayerSource,
    background_at,
)
from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, Selection

if TYPE_CHECKING:
    import moderngl

    from lodscape.imagery.layers import ImageryLayer
    from lodscape.render.globe_pass import GlobePass
    from lodscape.scene import Scene
    from lodscape.stream import StreamOptions
    from lodscape.stream.streamer import Clock

__all__ = ["SKY_HIGH", "SKY_LOW", "Globe", "GlobeOptions", "background_at"]

F64 = NDArray[np.float64]


@dataclass
class Globe:
    """The globe, with heights and tiles from ``terrain`` (a Scene over a DEM or a tileset)
    where it has data, and imagery layers (``lodscape.imagery.layers.ImageryLayer``; None: the
    terrain's) streamed over all of it. Frames stream on ``clock`` with ``stream`` options
    (None: the terrain's when it streams, else one-shot frames that load what they draw)."""

    terrain: Scene | None = None
    options: GlobeOptions = field(default_factory=GlobeOptions)
    last: dict[str, Any] = field(default_factory=dict)
    layers: list[ImageryLayer] | None = None
    clock: Clock | None = None
    stream: StreamOptions | None = None
    #: The frames' context (the globe's own unless a window's), the globe's pass in it, and
    #: the loop of a globe without terrain tiles.
    _ctx: moderngl.Context | None = None
    _owns_ctx: bool = False
    #: The context is a window's (``use_context``): frames stay in its target.
    _window: bool = False
    _pass: GlobePass | None = None
    _loop: FrameLoop | None = None
    _stats: FrameStats | None = None
    _covered: int = 0

    def __post_init__(self) -> None:
        # a streaming terrain sets the pace: the globe's imagery streams on its clock
        if self.stream is None and self.terrain is not None and self.terrain.streaming:
            self.stream, self.clock = self.terrain.options.stream, self.terrain.clock
        tiles = self.terrain is not None and self.options.terrain_tiles
        self._globe = GlobeLayer(self.options, self.terrain, tiles=tiles)
        layers = self.imagery_layers
        self._imagery = GlobeImageryLayer(layers, self._globe) if layers else None

    def __enter__(self) -> Globe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the globe's geometry ---------------------------------------------------------------

    def heights(self, lat: F64, lon: F64) -> F64:
        """Heights at (lat, lon): the terrain's where it has data, the ellipsoid's (0) elsewhere."""
        return self._globe.heights(lat, lon)

    def camera(self, camera: Camera) -> Camera:
        """The camera with clip distances for the globe; refuses one under the ground."""
        return self._globe.camera(camera)

    def select(self, camera: Camera) -> Selection:
        return self._globe.select(camera)

    def mesh(self, camera: Camera) -> tuple[Camera, Selection, GlobeMesh]:
        return self._globe.mesh(camera)

    def base_image(self) -> NDArray[np.uint8]:
        """The equirectangular image under everything (see ``lodscape.imagery.globe``); the
        plain Earth's notice said once on stderr."""
        from lodscape.imagery.globe import earth_image, global_image

        if self.options.earth == "procedural":
            return global_image()
        image, notice = earth_image()
        if notice is not None:
            from lodscape.imagery.layers import warn_stderr

            warn_stderr(notice)
        return image

    @property
    def _joined(self) -> Scene | None:
        """The terrain scene whose frames the globe joins (its tiles drawn); None: alone."""
        return self.terrain if self._globe.tiles else None

    # --- frames -----------------------------------------------------------------------------

    def render(
        self, camera: Camera, *, depth: bool = True
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB and view distance of the globe from ``camera``: the globe's facets and imagery,
        then the terrain's tiles and its city, one loop, one target, one depth test, read back
        once (not at all in a window)."""
        return self._frame(camera, depth=depth, ring=0)

    def render_behind(self, camera: Camera, ring: int = 3) -> NDArray[np.uint8] | None:
        """Render ``camera`` and return the picture of ``ring - 1`` frames before (None for the
        first ones), read through a ring of pixel-pack buffers (``Scene.render_behind``)."""
        if ring < 1:
            raise ValueError(f"ring must be at least 1, got {ring}")
        rgb, _ = self._frame(camera, depth=False, ring=ring)
        return rgb if rgb.size else None

    def drain(self) -> list[NDArray[np.uint8]]:
        """The pictures ``render_behind`` has not returned yet, oldest first."""
        target = self.renderer
        return [] if target is None else list(target.target.drain())

    @property
    def columns(self) -> tuple[str, ...]:
        """The figures a flight records of each frame (``frame_stats``)."""
        from lodscape.flight import GLOBE_COLUMNS

        return GLOBE_COLUMNS

    def _frame(
        self, camera: Camera, *, depth: bool, ring: int
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        self._globe.camera(camera)  # a camera under the ground is refused before any GL
        stages = self._stages()
        background = background_at(self.options, camera.alt)
        joined = self._joined
        if joined is not None:
            rgb, dist, _ = joined._render(
                camera, depth=depth, ring=ring, before=stages, background=background
            )
            stats = joined.last
            target = joined.renderer
        else:
            loop = self._own_loop(camera)
            loop.stages = stages
            target = loop.target.renderer  # type: ignore[attr-defined]
            frames = target.target
            if ring != frames.ring and frames.pending:
                raise RuntimeError("pictures left in the read ring: take them with drain() first")
            frames.ring, frames.read_depth = ring, depth
            rgb, dist = loop.run(camera, blocking=not self.streaming, background=background)
            stats = loop.last
        assert stats is not None
        self._stats = stats
        assert target is not None
        self._covered = target.target.covered if joined is not None else 0
        globe = stats.section("globe")
        sel = self._globe.selection
        self.last = {
            "triangles": globe.get("facets", 0),
            "levels": {k: len(v) for k, v in sorted(sel.levels.items())} if sel else {},
            "max_level": globe.get("max_level", 0),
            "extended": globe.get("extended", 0),
            "screen_error_px": globe.get("screen_error_px", 0.0),
            "select_ms": globe.get("globe_select_ms", 0.0),
            "draw_ms": round(stats.draw_ms, 2),
            "terrain_pixels": self._covered,
            **stats.section("globe_imagery"),
        }
        return rgb, dist

    def _stages(self) -> list[tuple[Layer, Pass]]:
        """The globe's layers and their passes, drawn first in the frame."""
        from lodscape.render.passes import GlobeFacetPass, GlobeImageryPass

        globe = self._pass_for()
        globe.behind_region = self._joined is not None and globe.region is not None
        stages: list[tuple[Layer, Pass]] = [(self._globe, GlobeFacetPass(globe))]
        if self._imagery is not None:
            stages.append((self._imagery, GlobeImageryPass(globe)))
        return stages

    def _pass_for(self) -> Any:
        """The globe's pass, made once in the frames' context (the window's, or one of the
        globe's own that the terrain then draws in)."""
        if self._pass is not None:
            return self._pass
        from lodscape.render._context import create_context
        from lodscape.render.globe_pass import GlobePass

        joined = self._joined
        if joined is not None and joined.renderer is not None:
            raise LodscapeError(
                "the terrain of a globe draws in the globe's frames: make the Globe before "
                "the terrain's first frame"
            )
        if self._ctx is None:
            self._ctx = create_context()
            self._owns_ctx = True
        if joined is not None:
            joined.join_globe(self._ctx, window=self._window)
        self._pass = GlobePass(self._ctx, self.base_image())
        # the drape, and where the terrain's tiles are drawn, what the globe only fills
        if self.terrain is not None and (self.options.imagery or self._joined is not None):
            from lodscape.imagery.globe import regional_image

            region = regional_image(self.terrain.provider)
            if region is not None:
                self._pass.set_region(*region)
        return self._pass

    def _own_loop(self, camera: Camera) -> FrameLoop:
        """The loop of a globe without terrain tiles: its imagery layers' loader, and a
        renderer with no tiles of its own as the target (and the imagery's GPU)."""
        if self._loop is None:
            from lodscape.render import Renderer
            from lodscape.render.passes import RendererTarget
            from lodscape.stream import RealClock, StreamOptions
            from lodscape.stream.loader import Loader

            target = Renderer(
                camera.width,
                camera.height,
                ctx=self._ctx,
                ellipsoid=False,
                layers=0,
                log_depth=True,
            )
            target.read_back = not self._window  # a window shows its target
            o = self.options
            loader = Loader(
                LayerSource(self.imagery_layers),
                target,
                self.stream or StreamOptions(cache_mb=64.0, ahead=()),
                self.clock or RealClock(),
                gpu_budget_bytes=o.imagery_budget_mb * 2**20,
                optional=lambda key: True,
                imagery_wait=o.imagery_timeout,
            )
            self._loop = FrameLoop(loader, [], RendererTarget(target))
        return self._loop

    def frame_stats(self) -> dict[str, float]:
        """The last frame's figures by name (``lodscape.flight.GLOBE_COLUMNS``): the frame's,
        its layers' (the terrain's, the globe's, its imagery's), the servers'."""
        if self._stats is None:
            return {}
        out: dict[str, float] = dict(self._stats.as_dict())
        layers = self.imagery_layers
        if layers:
            from lodscape.imagery.layers import server_figures

            out.update(server_figures(layers))
        out["terrain_pixels"] = self._covered
        return out

    @property
    def imagery_layers(self) -> list[Any]:
        """The layers drawn over the globe: those given, or the terrain's."""
        if self.layers is not None:
            return self.layers
        if self.terrain is not None:
            return list(getattr(self.terrain.provider, "layers", None) or [])
        return []

    @property
    def streaming(self) -> bool:
        """Whether frames stream (the globe's imagery and the terrain's tiles) on a clock."""
        return self.stream is not None

    # --- what the viewer asks of a scene ----------------------------------------------------

    def use_context(self, ctx: Any) -> None:
        """Draw in ``ctx`` (a window's) from the first frame on."""
        if self._pass is not None:
            raise RuntimeError("use_context before the first frame")
        self._ctx = ctx
        self._window = True

    @property
    def renderer(self) -> Any:
        """The renderer whose target the frames are drawn in (None before the first)."""
        joined = self._joined
        if joined is not None:
            return joined.renderer
        return None if self._loop is None else self._loop.target.renderer  # type: ignore[attr-defined]

    @property
    def terrain_mode(self) -> str:
        return f"QTM {self.options.mode}"

    def ground_height(self, lon: float, lat: float) -> float | None:
        return float(self.heights(np.array([lat]), np.array([lon]))[0])

    def hud_stats(self) -> dict[str, Any]:
        """The last frame's figures in the viewer's names (``view.Viewable``)."""
        return {
            "tiles": self.last.get("triangles", 0),
            "triangles": self.last.get("triangles", 0),
            "max_sse_px": self.last.get("screen_error_px", 0.0),
            "max_depth": self.last.get("max_level", 0),
        }

    def toggle_culling(self) -> bool | None:
        """The globe culls by its horizon and frustum only: nothing to toggle."""
        return None

    def close(self) -> None:
        if self._loop is not None:
            self._loop.loader.close()
            self._loop.target.renderer.close()  # type: ignore[attr-defined]
            self._loop = None
        if self._pass is not None:
            self._pass.close()
            self._pass = None
        if self.layers is not None:
            for layer in self.layers:
                layer.close()
            self.layers = None
        if self.terrain is not None:
            self.terrain.close()
        if self._owns_ctx and self._ctx is not None:
            self._ctx.release()
            self._ctx = None
            self._owns_ctx = False
