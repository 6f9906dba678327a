"""A Scene: the facade over a terrain's frame loop (``lodscape.frame``): its options, its
cameras, and what a frame gives back (a picture, a dataset's capture, the viewer's and the
widget's hooks).

    scene = lodscape.open("dem.tif")
    rgb, depth = scene.render(lodscape.Camera(lon, lat, alt, heading=30, pitch=-20))

Each frame plans its layers (the terrain's tiles, the ellipsoid, the city; a globe's facets
and imagery when it joins), meshes the missing tiles on worker threads, uploads them on the
calling thread (which owns the GL context), draws the passes into one target, and evicts what
the byte budget cannot keep, never a tile drawn in the last frame.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from os import PathLike
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from lodscape._watch import ImageryWatch
from lodscape.errors import LodscapeError
from lodscape.frame import FrameLoop, FrameStats, Layer, Pass
from lodscape.frame.terrain import CityLayer, EllipsoidLayer, TerrainLayer
from lodscape.geo.keys import is_overlay
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.lod.camera import Camera
from lodscape.lod.select import Selection, select
from lodscape.lod.view import TerrainView
from lodscape.options import SKY, SceneOptions
from lodscape.picture import Capture, Picture
from lodscape.render import Renderer
from lodscape.render.passes import EllipsoidPass, RendererTarget, TerrainPass, make_renderer
from lodscape.store.provider import Provider, RasterProvider
from lodscape.stream import RealClock, StreamOptions
from lodscape.stream.loader import Loader
from lodscape.stream.streamer import Clock
from lodscape.terrain.pyramid import TileTree
from lodscape.terrain.source import HeightSource

__all__ = ["SKY", "Capture", "FrameStats", "Picture", "Scene", "SceneOptions"]


def _everything(key: int) -> bool:
    return True


_T = TypeVar("_T")


class GLThread:
    """One thread that does every GL call of a context: an OpenGL context is current in one
    thread, and a ``Renderer`` refuses any other. Work handed to it from any thread runs there,
    one call at a time, its result or its exception handed back; from the thread itself it
    runs at once. Started on the first call."""

    def __init__(self, name: str = "lodscape-gl") -> None:
        self._name = name
        self._lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None
        self._ident: int | None = None

    def call(self, fn: Callable[..., _T], *args: Any, **kwargs: Any) -> _T:
        if threading.get_ident() == self._ident:
            return fn(*args, **kwargs)
        with self._lock:
            if self._pool is None:
                self._pool = ThreadPoolExecutor(1, thread_name_prefix=self._name)
                self._ident = self._pool.submit(threading.get_ident).result()
            pool = self._pool
        return pool.submit(fn, *args, **kwargs).result()

    def close(self) -> None:
        with self._lock:
            pool, self._pool, self._ident = self._pool, None, None
        if pool is not None:
            pool.shutdown(wait=True)


class Scene:
    """A terrain ready to render from any camera: a provider (a raster meshed on the fly, or a
    prebuilt tileset), the view that plans its frames, and the loader and renderer that carry
    them out. One frame path for one-shot renders (a blocking loader) and streaming."""

    def __init__(
        self,
        source: HeightSource | Provider,
        options: SceneOptions | None = None,
        *,
        tree: TileTree | None = None,
        owns: bool = False,
        clock: Clock | None = None,
    ) -> None:
        # a height source samples heights; anything else is already a provider
        if hasattr(source, "sample"):
            self.provider: Provider = RasterProvider(source, tree)  # type: ignore[arg-type]
        else:
            self.provider = source  # type: ignore[assignment]
        self._owns = owns
        self._options = options or SceneOptions()
        o = self._options
        morphs = o.morph and o.stream is not None
        if o.terrain_mode == "cpu" and (o.meshes == "tin" or (o.meshes == "auto" and not morphs)):
            by_error = getattr(self.provider, "mesh_by_error", None)
            if by_error is not None:
                by_error()
        else:  # grids (the GPU terrain mode's too): the finest only where a tile cannot split
            split_first = getattr(self.provider, "split_before_finest", None)
            if split_first is not None:
                split_first()
        self.tree = self.provider.tree
        self.view = TerrainView(
            self.tree,
            self._options.select,
            cull_backfacing=self._options.cull_backfacing,
            texture_levels=self.provider.texture_levels,
        )
        # frame after frame (flights, the viewer): a one-shot render shows its own surfaces
        self.view.morph = self._options.morph and self._options.stream is not None
        self.clock: Clock = clock or RealClock()
        self._terrain = TerrainLayer(self.view, self.prepare, self.ground_height)
        self._loop: FrameLoop | None = None
        self._renderer: Renderer | None = None
        #: The thread that does the GL work of a context of the scene's own.
        self._gl = GLThread()
        self._loader: Loader | None = None
        #: A context to draw in (a viewer's window) instead of a headless one of its own.
        self._ctx: Any = None
        #: Frames are drawn under a globe (``join_globe``).
        self._under_globe = False
        #: Frames stay in the target, a window's to show (``use_context``): none is read back.
        self._window = False
        #: Why frames are drawn in the CPU terrain mode though the options asked for "gpu".
        self.terrain_mode_note: str | None = None
        self.city: Any = None
        self.city_options: Any = None
        self._city_pass: Any = None
        #: The frame loop's pass over it (made again with it).
        self._city_draw: Any = None
        #: The last frame's camera, its clip distances fitted (what ``capture`` reports).
        self._drawn: Camera | None = None
        self.last: FrameStats | None = None
        self._watch = ImageryWatch(
            self.provider, self._options.imagery_timeout, self._options.imagery_strict
        )

    @property
    def options(self) -> SceneOptions:
        return self._options

    @options.setter
    def options(self, options: SceneOptions) -> None:
        """New options from the next frame on (the viewer's culling key); the selection's and
        the loader's stay those the scene was made with."""
        self._options = options
        self.view.cull_backfacing = options.cull_backfacing
        self.view.morph = options.morph and options.stream is not None

    @property
    def streaming(self) -> bool:
        """Whether frames stream (never waiting but for the roots) rather than load everything."""
        return self._options.stream is not None

    # --- geometry helpers ----------------------------------------------------------------

    @property
    def source(self) -> Provider:
        """The provider (its ``name``, ``bounds_merc`` and ``tree``)."""
        return self.provider

    def ground_height(self, lon: float, lat: float) -> float | None:
        """Terrain height at a point, or None outside the data's footprint."""
        return self.provider.ground_height(lon, lat)

    def show(self, camera: Camera | None = None, width: int = 640, height: int = 400) -> Picture:
        """Render ``camera`` (default: the overview at ``width``×``height``, or the city's
        camera when a city is draped) as a ``Picture``, which a notebook shows inline."""
        if camera is None:
            camera = self.default_camera(width, height)
        rgb, depth = self.render(camera)
        return Picture(rgb, depth, camera)

    def default_camera(self, width: int = 1280, height: int = 720, fov_y: float = 60.0) -> Camera:
        """The city's camera where a city is draped, else the overview."""
        if self.city is not None:
            return self.city_camera(width, height, fov_y)
        return self.overview_camera(width, height, fov_y)

    def widget(self, camera: Camera | None = None, width: int = 640, height: int = 400) -> Any:
        """A notebook widget showing ``camera`` (default: ``show()``'s) that the user flies
        with the keys and mouse, rendered here and streamed to the browser
        (``lodscape.widget.SceneWidget``; needs ``pip install 'lodscape[jupyter]'``)."""
        try:
            from lodscape.widget import SceneWidget
        except ImportError as exc:
            raise LodscapeError(
                f"the notebook widget needs anywidget ({exc}): pip install 'lodscape[jupyter]'"
            ) from None
        return SceneWidget(self, camera, width=width, height=height)

    def _repr_png_(self) -> bytes:
        """A notebook's inline view of the scene: ``show()``'s picture."""
        return self.show().png()

    def overview_camera(self, width: int = 1280, height: int = 720, fov_y: float = 60.0) -> Camera:
        """A camera south of the data looking north at its centre, seeing all of it."""
        return self.view.overview(self.provider.bounds_merc, width, height, fov_y)

    def prepare(self, camera: Camera) -> Camera:
        """The camera with clip distances fitted to the terrain; refuses one under the ground."""
        return self.view.fit(camera, self.ground_height(camera.lon, camera.lat))

    # --- frames ----------------------------------------------------------------------------

    def select(self, camera: Camera) -> Selection:
        """This frame's selection as if everything were resident (no loading, no drawing)."""
        fitted = self.prepare(camera)
        return select(self.view.select_options, fitted, self.tree, self.view.history(fitted))

    def render(
        self, camera: Camera, *, depth: bool = True
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB (H, W, 3) uint8 and depth (H, W) float32 metres along the view axis (inf: sky);
        ``depth`` False: the distance is not read back (an empty (0, 0) array)."""
        rgb, dist, _ = self._render(camera, depth=depth, ring=0)
        return rgb, dist

    def capture(self, camera: Camera) -> Capture:
        """Render ``camera`` for a dataset: the picture and its distance, then the same frame
        once more for each pixel's surface normal and semantic label (``Capture``)."""
        rgb, dist, got = self._render(camera, depth=True, ring=0, labels=True)
        assert got is not None
        # the GL's view axes (x right, y up, z backwards) to OpenCV's (x right, y down, z ahead)
        normals = got[..., :3] * np.array([1.0, -1.0, -1.0], np.float32)
        labels = np.rint(got[..., 3]).clip(0, 255).astype(np.uint8)
        assert self._drawn is not None
        return Capture(rgb, dist, np.ascontiguousarray(normals), labels, self._drawn)

    def render_behind(self, camera: Camera, ring: int = 3) -> NDArray[np.uint8] | None:
        """Render ``camera`` and return the picture of ``ring - 1`` frames before (None for the
        first ones): pictures are read through a ring of ``ring`` pixel-pack buffers, so the GL
        copies one while the next frames render (paper 001's triple buffering). ``drain``
        gives the pictures still in the ring (``render`` refuses while some are left)."""
        if ring < 1:
            raise ValueError(f"ring must be at least 1, got {ring}")
        rgb, _, _ = self._render(camera, depth=False, ring=ring)
        return rgb if rgb.size else None

    @property
    def columns(self) -> tuple[str, ...]:
        """The figures a flight records of each frame (``frame_stats``)."""
        from lodscape.flight import STAT_COLUMNS

        return STAT_COLUMNS

    def drain(self) -> list[NDArray[np.uint8]]:
        """The pictures ``render_behind`` has not returned yet, oldest first."""
        renderer = self._renderer
        if renderer is None:
            return []
        return self.on_gl(renderer.target.drain)

    def _render(
        self,
        camera: Camera,
        *,
        depth: bool,
        ring: int,
        labels: bool = False,
        before: Sequence[tuple[Layer, Pass]] = (),
        background: tuple[float, float, float] | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.float32] | None]:
        """One frame through the loop: ``before`` (layer, pass) stages first (the globe's). In a
        context of the scene's own, on its GL thread, whichever thread asks (a notebook's
        comm messages come on another thread than the cell's)."""
        if not isinstance(camera, Camera):
            raise LodscapeError(
                f"render: expected a lodscape.Camera, got {type(camera).__name__} "
                "(lodscape.Camera(lon=…, lat=…, alt=…, heading=…, pitch=…))"
            )
        return self.on_gl(
            self._render_here,
            camera,
            depth=depth,
            ring=ring,
            labels=labels,
            before=before,
            background=background,
        )

    def on_gl(self, fn: Callable[..., _T], *args: Any, **kwargs: Any) -> _T:
        """``fn(*args, **kwargs)`` where this scene's GL work is done (what touches its
        ``renderer``): its GL thread for a headless context of its own, the caller's for a
        window's (the viewer's, a globe's)."""
        if self._ctx is not None:
            return fn(*args, **kwargs)
        return self._gl.call(fn, *args, **kwargs)

    def _render_here(
        self,
        camera: Camera,
        *,
        depth: bool,
        ring: int,
        labels: bool,
        before: Sequence[tuple[Layer, Pass]],
        background: tuple[float, float, float] | None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32], NDArray[np.float32] | None]:
        if self._renderer is None:
            self.prepare(camera)  # a camera under the ground is refused before any GL
        renderer = self._renderer_for(camera)
        frames = renderer.target
        if ring != frames.ring and frames.pending:
            raise RuntimeError("pictures left in the read ring: take them with drain() first")
        frames.ring, frames.read_depth = ring, depth
        loop = self._loop_for(renderer)
        loop.stages = [*before, *self._stages(renderer)]
        loader = loop.loader
        late = loader.late
        rgb, dist = loop.run(
            camera,
            blocking=not self.streaming,
            background=self._options.background if background is None else background,
        )
        self._drawn = self._terrain.camera
        labelled = None
        if labels:
            # the same draws again, for each pixel's normal and label
            target = RendererTarget(renderer, labelled=True)
            target.begin(self._drawn)
            for (_, each), what in zip(loop.stages, loop.draws, strict=True):
                each.draw(what, target)
            labelled, _ = target.end(self._drawn)
        assert loop.last is not None
        self.last = loop.last.with_section("imagery", self._watch.after(loader, late))
        return rgb, dist, labelled

    def _loop_for(self, renderer: Renderer) -> FrameLoop:
        if self._loop is None:
            self._terrain.whole_tiles = renderer.terrain_mode == "gpu"
            self._loop = FrameLoop(self._loader_for(renderer), [], RendererTarget(renderer))
        return self._loop

    def _stages(self, renderer: Renderer) -> list[tuple[Layer, Pass]]:
        """The terrain's layers and their passes, in the order they draw."""
        stages: list[tuple[Layer, Pass]] = [(self._terrain, TerrainPass(renderer))]
        if renderer.ellipsoid:
            stages.append(
                (EllipsoidLayer(self._terrain, self.ground_height), EllipsoidPass(renderer))
            )
        if self.city is not None:
            stages.append(
                (CityLayer(self._terrain, self.ground_height), self._city_stage(renderer))
            )
        return stages

    def frame_stats(self) -> dict[str, float]:
        """The last frame's figures by name (``FrameStats.as_dict``); empty before the first."""
        return {} if self.last is None else dict(self.last.as_dict())

    def imagery_failures(self) -> dict[str, int]:
        """Failed imagery tiles by kind, all layers together, since the scene opened."""
        return self._watch.failures()

    def _loader_for(self, renderer: Renderer) -> Loader:
        if self._loader is None:
            opts = self._options
            # one-shot renders keep a modest cache of fetched bytes and predict nothing
            stream = opts.stream or StreamOptions(workers=opts.workers, cache_mb=64.0, ahead=())
            self._loader = Loader(
                self.provider,
                renderer,
                stream,
                self.clock,
                gpu_budget_bytes=opts.gpu_budget_mb * 2**20,
                predict=self._terrain.predict,
                optional=is_overlay if self.provider.layers else None,
                imagery_wait=opts.imagery_timeout,
                areas=self._terrain.areas_within(opts.stream.radii if opts.stream else None),
                remote=_everything if self.provider.network else None,
            )
        return self._loader

    def frames(
        self, cameras: Iterator[Camera]
    ) -> Iterator[tuple[NDArray[np.uint8], NDArray[np.float32]]]:
        for cam in cameras:
            yield self.render(cam)

    # --- the city (paper 001) ---------------------------------------------------------------

    def add_city(self, city: str | PathLike[str] | Any, options: Any = None) -> Any:
        """Drape a city on the terrain: an OSM file (.osm.pbf, .osm) or a built ``CityModel``;
        its objects stand on this scene's ground, in a scene tree packed as ``options.packing``
        says (a built model keeps its own). Returns the model. What a file's objects could not
        be made of (a missing node, a ring that does not close) is said once on stderr and
        counted (``City.skipped``)."""
        from lodscape.city.model import CityModel, CityOptions, build_city
        from lodscape.city.osm import City, read_osm
        from lodscape.imagery.layers import warn_stderr

        options = options or CityOptions()
        if isinstance(city, CityModel):
            model = city
        else:
            if not isinstance(city, City):
                city = read_osm(str(city))
                note = city.skipped_note()
                if note is not None:
                    warn_stderr(note)
            model = build_city(city, self.heights, packing=options.packing)
        self._drop_city_pass()
        self.city = model
        self.city_options = options
        return model

    def _drop_city_pass(self, reset: bool = False) -> None:
        """The city pass released (made again at the next frame), or only ``reset``, in its
        renderer's context on the scene's GL thread."""
        if self._city_pass is None:
            return

        def drop() -> None:
            if self._renderer is not None:
                self._renderer._use()
            if reset:
                self._city_pass.reset()
            else:
                self._city_pass.release()
                self._city_pass = None

        self.on_gl(drop)

    def set_city_options(self, options: Any) -> None:
        """Change how the city is drawn (``CityOptions``); occlusion culling starts afresh."""
        old = self.city_options
        rebuild = old is not None and options.buffers != old.buffers
        self.city_options = options
        # the buffers' path is made with the pass: made again at the next frame
        self._drop_city_pass(reset=not rebuild)

    def heights(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        """Ground heights at many points (NaN outside the data)."""
        return self.provider.heights_at(np.asarray(lon, np.float64), np.asarray(lat, np.float64))

    def city_camera(self, width: int = 1280, height: int = 720, fov_y: float = 60.0) -> Camera:
        """A camera south of the city looking north over it, a little above its roofs."""
        if self.city is None:
            raise ValueError("no city in this scene (add_city first)")
        box = self.city.tree.levels[-1][0]
        extent = float(max(box[3] - box[0], box[4] - box[1], 50.0))
        lon, lat = self.city.frame.lon, self.city.frame.lat
        back = 0.6 * extent
        dlat = math.degrees(back / 6_371_000.0)
        ground = self.ground_height(lon, lat - dlat) or 0.0
        alt = ground + max(0.25 * extent, float(box[5] - box[2]) + 30.0)
        return Camera.looking_at(
            lon, lat - dlat, alt, (lon, lat, ground), fov_y=fov_y, width=width, height=height
        )

    def _city_stage(self, renderer: Renderer) -> Any:
        """The city's pass in the renderer's context, made when first drawn."""
        from lodscape.render.city_pass import CityPass
        from lodscape.render.passes import CityDrawPass

        if self._city_pass is None:
            self._city_pass = CityPass(
                renderer.ctx,
                self.city,
                renderer.anisotropy,
                compress=renderer.compress,
                buffers=self.city_options.buffers,
                log_depth=renderer.log_depth,
            )
        if self._city_draw is None or self._city_draw.city is not self._city_pass:
            self._city_draw = CityDrawPass(self._city_pass, lambda: self.city_options)
        return self._city_draw

    def _renderer_for(self, camera: Camera) -> Renderer:
        if self._renderer is None:
            opts = self._options
            # under a globe, the globe is the world outside the data
            ellipsoid = opts.ellipsoid and not self._under_globe
            b = self.provider.bounds_merc
            (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
            self._renderer, self.terrain_mode_note = make_renderer(
                camera,
                ctx=self._ctx,
                background=opts.background,
                anisotropy=opts.anisotropy,
                ground=self.ground,
                terrain_mode=opts.terrain_mode,
                tess_px=opts.tess_px,
                ellipsoid=ellipsoid,
                log_depth=self._under_globe,
                compress=opts.compress_textures,
                layers=len(self.provider.layers),
                earth=(float(w), float(s), float(e), float(n)) if opts.earth else None,
            )
            # a window's frames stay in its target from the first (drawn as the GL draws)
            self._renderer.read_back = not self._window
        return self._renderer

    @property
    def ground(self) -> str:
        """ "landcover" where the provider's textures are land-cover masks, else "imagery"."""
        return self.provider.textures

    def use_context(self, ctx: Any) -> None:
        """Draw in ``ctx`` (a window's OpenGL context) from the next frame on; frames then stay
        in ``renderer.target.framebuffer`` instead of coming back as arrays."""
        if self._renderer is not None:
            raise RuntimeError("use_context before the first frame")
        self._ctx = ctx
        self._window = True

    def join_globe(self, ctx: Any, *, window: bool = False) -> None:
        """Draw in ``ctx`` under a globe from the next frame on: the globe's pass first in the
        same target, one logarithmic depth for both (``render._depth``), and no ellipsoid of
        the terrain's own (the globe is the world outside the data); ``window``: a window's
        context, whose frames stay in the target."""
        if self._renderer is not None:
            raise RuntimeError("join_globe before the first frame")
        self._ctx = ctx
        self._under_globe = True
        self._window = window

    @property
    def renderer(self) -> Renderer | None:
        """The renderer of the frames so far (None before the first)."""
        return self._renderer

    @property
    def terrain_mode(self) -> str:
        """The terrain mode frames are drawn in ("gpu" only where tessellation is there)."""
        if self._renderer is not None:
            return self._renderer.terrain_mode
        return self.options.terrain_mode

    def hud_stats(self) -> dict[str, Any]:
        """The last frame's figures (``view.Viewable``)."""
        return {} if self.last is None else dict(self.last.as_dict())

    def toggle_culling(self) -> bool | None:
        """Back-face culling off if on, on if off; returns the new setting (``view.Viewable``)."""
        self.options = replace(self._options, cull_backfacing=not self._options.cull_backfacing)
        return self._options.cull_backfacing

    def close(self) -> None:
        if self._loader is not None:
            self._loader.close()
            self._loader = None
        if self._renderer is not None:
            self.on_gl(self._release_gl)
        self._gl.close()
        if self._owns:
            self.provider.close()
            self._owns = False

    def _release_gl(self) -> None:
        renderer = self._renderer
        if renderer is None:
            return
        if self._city_pass is not None:
            renderer._use()
            self._city_pass.release()
            self._city_pass = None
        renderer.close()
        self._renderer = None

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
