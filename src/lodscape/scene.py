"""A Scene: a height source, its tile tree and imagery, and a renderer, frame after frame.

    scene = lodscape.open("dem.tif")
    rgb, depth = scene.render(lodscape.Camera(lon, lat, alt, heading=30, pitch=-20))

Each frame selects tiles (pure), meshes the missing ones on worker threads, uploads them on the
calling thread (which owns the GL context), draws, and evicts what the byte budget cannot keep,
never a tile drawn in the last frame.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from os import PathLike
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError, SourceError
from lodscape.geo.frames import WGS84_A, ecef_to_geodetic
from lodscape.geo.keys import is_texture, mesh_key, texture_key, tile_id_of_array, tile_of
from lodscape.geo.tiles import (
    lonlat_to_merc,
    merc_to_lonlat,
    tile_from_id_array,
    tile_id_array,
)
from lodscape.lod.camera import Camera
from lodscape.lod.cull import backfacing
from lodscape.lod.select import Selection, SelectOptions, select, tile_boxes
from lodscape.render import DrawItem, Renderer
from lodscape.render.tess_pass import TessellationUnavailable
from lodscape.store.provider import FractalProvider, Provider, RasterProvider
from lodscape.store.tileset import TilesetProvider, is_tileset
from lodscape.stream import RealClock, Streamer, StreamOptions
from lodscape.stream.streamer import Clock
from lodscape.terrain.detail import (
    DetailHeights,
    DetailTree,
    Fractal,
    ProceduralHeights,
    ProceduralTree,
    parse_procedural,
)
from lodscape.terrain.mesh import TileMesh
from lodscape.terrain.pyramid import TileTree, build_tree
from lodscape.terrain.source import ArraySource, HeightSource, RasterSource

__all__ = ["FrameStats", "Scene", "SceneOptions", "open"]

SKY = (0.62, 0.75, 0.88)
#: Seconds (on the scene's clock) between predictions of where the camera is going.
_PREDICT_EVERY = 0.15


@dataclass(frozen=True)
class SceneOptions:
    """Everything a scene can be tuned with; the defaults are the documented behaviour."""

    select: SelectOptions = field(default_factory=SelectOptions)
    #: GPU bytes the scene may keep resident between frames (tiles of the last frame always stay).
    gpu_budget_mb: float = 512.0
    #: Worker threads that read heights, make textures and build meshes.
    workers: int = 4
    #: Clear colour (RGB, 0..1) where no terrain is drawn.
    background: tuple[float, float, float] = SKY
    #: Anisotropic texture filtering cap (1 turns it off): sharper ground at grazing angles, and
    #: free on a GPU, but it makes a frame about 2.4x slower on Mesa's llvmpipe.
    anisotropy: float = 16.0
    #: Stream tiles through the staged pipeline (never waiting on a load: missing tiles are
    #: drawn from their ancestors) instead of loading every missing tile before drawing.
    stream: StreamOptions | None = None
    #: Skip tiles whose every triangle faces away from the camera (normal cones, paper 003).
    cull_backfacing: bool = True
    #: "cpu": the quadtree's meshes (the spine); "gpu": each tile a few patches tessellated in
    #: hardware and displaced by its height texture (paper 001). Without tessellation (OpenGL
    #: < 4.0) "gpu" falls back to "cpu", and ``Scene.terrain_mode_note`` says why.
    terrain_mode: str = "cpu"
    #: The GPU terrain mode's pixel rule: a patch edge gets a segment per this many pixels of
    #: its length on screen (more where its error table asks for them).
    tess_px: float = 4.0

    def __post_init__(self) -> None:
        if not self.gpu_budget_mb > 0.0:
            raise ValueError(f"Expected a positive gpu_budget_mb, got {self.gpu_budget_mb}")
        if self.workers < 1:
            raise ValueError(f"Expected at least one worker, got {self.workers}")
        if not self.anisotropy >= 1.0:
            raise ValueError(f"Expected anisotropy >= 1, got {self.anisotropy}")
        if not self.tess_px > 0.0:
            raise ValueError(f"Expected a positive tess_px, got {self.tess_px}")
        if self.terrain_mode not in ("cpu", "gpu"):
            raise ValueError(f"Expected terrain_mode cpu or gpu, got {self.terrain_mode!r}")


@dataclass(frozen=True)
class FrameStats:
    """What one frame drew and how long its stages took."""

    selection: dict[str, float | int]
    draw_calls: int
    #: Triangles the renderer drew, skirts included.
    triangles: int
    loaded: int
    resident_mb: float
    select_ms: float
    load_ms: float
    draw_ms: float
    #: The streaming pipeline's figures for this frame (empty when not streaming).
    stream: dict[str, float] = field(default_factory=dict)
    #: Tiles skipped as facing away from the camera, and the triangles they held.
    backfacing: int = 0
    backfacing_triangles: int = 0
    #: The city pass's figures (draw calls, triangles, objects culled…), when a city is on.
    city: dict[str, int] = field(default_factory=dict)
    #: Milliseconds the CPU spent issuing the terrain's draws (in ``draw_ms``, no GPU wait).
    submit_ms: float = 0.0
    terrain_mode: str = "cpu"

    def as_dict(self) -> dict[str, float | int]:
        return {
            **self.selection,
            "triangles": self.triangles,
            "draw_calls": self.draw_calls,
            "loaded": self.loaded,
            "resident_mb": round(self.resident_mb, 2),
            "select_ms": round(self.select_ms, 2),
            "load_ms": round(self.load_ms, 2),
            "draw_ms": round(self.draw_ms, 2),
            "submit_ms": round(self.submit_ms, 2),
            "backfacing": self.backfacing,
            "backfacing_triangles": self.backfacing_triangles,
            **self.stream,
            **self.city,
        }


class Scene:
    """A terrain ready to render from any camera: a provider (a raster meshed on the fly, or a
    prebuilt tileset) and the GPU resources of its tiles."""

    def __init__(
        self,
        source: HeightSource | Provider,
        options: SceneOptions | None = None,
        *,
        tree: TileTree | None = None,
        owns: bool = False,
        clock: Clock | None = None,
    ) -> None:
        # a height source has ``sample``; anything else is already a provider
        if hasattr(source, "sample"):
            self.provider: Provider = RasterProvider(source, tree)  # type: ignore[arg-type]
        else:
            self.provider = source  # type: ignore[assignment]
        self._owns = owns
        self.options = options or SceneOptions()
        self.tree = self.provider.tree
        self._renderer: Renderer | None = None
        #: A context to draw in (a viewer's window) instead of a headless one of its own.
        self._ctx: Any = None
        #: Why frames are drawn in the CPU terrain mode though the options asked for "gpu".
        self.terrain_mode_note: str | None = None
        self.city: Any = None
        self.city_options: Any = None
        self._city_pass: Any = None
        self._previous: Selection | None = None
        self._used: OrderedDict[int, None] = OrderedDict()
        self._pool = ThreadPoolExecutor(max(1, self.options.workers), "lodscape-load")
        self.last: FrameStats | None = None
        self.streamer: Streamer | None = None
        if self.options.stream is not None:
            self.streamer = Streamer(
                self.provider, self.options.stream, clock or RealClock(), prepare=self._heights
            )
        self._motion: tuple[float, NDArray[np.float64]] | None = None
        self._predicted_at = -math.inf
        self._predicted: Future[list[tuple[Literal["memory", "cache"], list[int]]]] | None = None

    # --- geometry helpers ----------------------------------------------------------------

    @property
    def source(self) -> Provider:
        """The provider (its ``name``, ``bounds_merc`` and ``tree``)."""
        return self.provider

    def ground_height(self, lon: float, lat: float) -> float | None:
        """Terrain height at a point, or None outside the data's footprint."""
        return self.provider.ground_height(lon, lat)

    def overview_camera(self, width: int = 1280, height: int = 720, fov_y: float = 60.0) -> Camera:
        """A camera south of the data looking north at its centre, seeing all of it."""
        b = self.source.bounds_merc
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        lon, lat = (w + e) / 2.0, (s + n) / 2.0
        lo, hi = self.tree.height_range
        extent = max(b.right - b.left, b.top - b.bottom) * math.cos(math.radians(lat))
        back = 0.75 * extent
        cam_lat = lat - math.degrees(back / WGS84_A)
        alt = hi + 0.55 * extent
        return Camera.looking_at(
            lon, cam_lat, alt, (lon, lat, (lo + hi) / 2.0), fov_y=fov_y, width=width, height=height
        )

    def prepare(self, camera: Camera) -> Camera:
        """The camera with clip distances fitted to the terrain; refuses one under the ground."""
        ground = self.ground_height(camera.lon, camera.lat)
        lo, hi = self.tree.height_range
        if ground is not None and camera.alt <= ground:
            raise CameraError(
                f"camera is under the ground: alt {camera.alt:.1f} m but the terrain at "
                f"{camera.lon:.5f}, {camera.lat:.5f} is {ground:.1f} m"
            )
        clearance = camera.alt - (ground if ground is not None else hi)
        near = camera.near or min(max(0.1 * clearance, 0.5), 1e5)
        if camera.far is not None:
            return camera.with_clip(near, camera.far)
        x, y = self.tree.roots()
        st = self.tree.level(self.tree.zmin).stats(x, y)
        probe = camera.with_clip(1.0, 2.0)
        boxes = tile_boxes(probe, self.tree.zmin, x, y, st.min_h, st.max_h)
        # everything in the data lies within its root boxes; the horizon bounds it on a planet
        horizon = math.sqrt(max(camera.alt - lo, 1.0) * 2.0 * WGS84_A) + math.sqrt(
            max(hi - lo, 1.0) * 2.0 * WGS84_A
        )
        far = max(min(float(boxes.dist_far.max()), horizon), near * 10.0) * 1.01
        return camera.with_clip(near, far)

    # --- frames ----------------------------------------------------------------------------

    def select(self, camera: Camera) -> Selection:
        """This frame's selection as if everything were resident (no loading, no drawing)."""
        return select(self.options.select, self.prepare(camera), self.tree, previous=self._previous)

    def render(self, camera: Camera) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB (H, W, 3) uint8 and depth (H, W) float32 metres along the view axis (inf: sky)."""
        cam = self.prepare(camera)
        renderer = self._renderer_for(cam)
        if self.streamer is not None:
            return self._render_streaming(cam, renderer, self.streamer)
        t0 = time.perf_counter()
        resident = np.array(sorted(renderer.resident()), dtype=np.uint64)
        sel = select(self.options.select, cam, self.tree, self._previous, resident)
        t1 = time.perf_counter()
        loaded = 0
        if sel.loads.size:
            loaded = self._load(renderer, sel.loads)
            resident = np.array(sorted(renderer.resident()), dtype=np.uint64)
            sel = select(self.options.select, cam, self.tree, self._previous, resident)
        t2 = time.perf_counter()
        items, culled, culled_tris = self._facing(
            renderer, cam, draw_items(sel, self.options.select.max_sse)
        )
        rgb, depth = renderer.draw(
            cam, items, background=self.options.background, after=self._city_passes(renderer)
        )
        t3 = time.perf_counter()
        self._previous = sel
        self._evict(renderer, sel)
        res_mb = sum(renderer.resident().values()) / 2**20
        self.last = FrameStats(
            sel.stats(),
            renderer.last_stats.draw_calls,
            renderer.last_stats.triangles,
            loaded,
            res_mb,
            (t1 - t0) * 1e3,
            (t2 - t1) * 1e3,
            (t3 - t2) * 1e3,
            backfacing=culled,
            backfacing_triangles=culled_tris,
            city=self._city_stats(),
            submit_ms=renderer.last_stats.submit_ms,
            terrain_mode=renderer.terrain_mode,
        )
        return rgb, depth

    def _facing(
        self, renderer: Renderer, cam: Camera, items: list[DrawItem]
    ) -> tuple[list[DrawItem], int, int]:
        """The draw list less the patches facing away from the camera (paper 003): a tile
        with none left is dropped, one with some left draws the runs of its other patches (and
        its skirts). Returns the list, the patches dropped and the triangles they held."""
        if not self.options.cull_backfacing or not items:
            return items, 0, 0
        keys = [it.key for it in items]
        cones, centres, owner = renderer.cones(keys)
        away = backfacing(cones, centres, cam.position)
        if not away.any():
            return items, 0, 0
        counts = np.bincount(owner, minlength=len(items))
        gone = np.bincount(owner, weights=away, minlength=len(items)).astype(np.int64)
        kept: list[DrawItem] = []
        saved = 0
        start = 0
        for i, item in enumerate(items):
            n = int(counts[i])
            if gone[i] == 0 or (gone[i] < n and renderer.terrain_mode == "gpu"):
                # the GPU mode draws a tile whole: it is kept unless all of it faces away
                kept.append(item)
            else:
                total = renderer.triangles([item.key])
                if gone[i] == n:
                    saved += total
                else:
                    per = (total - _skirt_triangles(total, n)) // n
                    runs = _runs(~away[start : start + n], per, total)
                    saved += total - sum(c for _, c in runs)
                    kept.append(replace(item, runs=runs))
            start += n
        return kept, int(away.sum()), saved

    def _render_streaming(
        self, cam: Camera, renderer: Renderer, streamer: Streamer
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """One frame that never waits on the pipeline, except for tiles with nothing resident
        above them (the roots, at the start): those are taken at once and counted as a stall."""
        opts = self.options
        before = streamer.stats.snapshot()
        t0 = time.perf_counter()
        sel = select(opts.select, cam, self.tree, self._previous, _keys(renderer))
        on_gpu = renderer.has
        stall = 0.0
        unresolved = [k for k in _drawn_keys(sel) if not on_gpu(k)]
        taken = 0
        if unresolved:
            # the roots above them come at once, and the rest streams in while they stand in
            ts = time.perf_counter()
            for keys in (_roots(unresolved, self.tree.zmin), None):
                if keys is None:
                    keys = [k for k in _drawn_keys(sel) if not on_gpu(k)]
                for key in keys:
                    if not on_gpu(key):
                        _upload(renderer, key, streamer.take(key))
                        taken += 1
                sel = select(opts.select, cam, self.tree, self._previous, _keys(renderer))
            stall = (time.perf_counter() - ts) * 1e3
        t1 = time.perf_counter()
        streamer.request((int(k) for k in sel.loads), "memory", on_gpu)
        self._prefetch(cam, streamer, on_gpu)
        streamer.collect()
        wanted = [int(k) for k in sel.loads]
        budget = streamer.options.upload_ms
        uploaded = streamer.upload(renderer, [*wanted, *list(streamer.memory)], budget)
        if uploaded:
            sel = select(opts.select, cam, self.tree, self._previous, _keys(renderer))
        t2 = time.perf_counter()
        items, culled, culled_tris = self._facing(
            renderer, cam, draw_items(sel, self.options.select.max_sse)
        )
        rgb, depth = renderer.draw(
            cam, items, background=opts.background, after=self._city_passes(renderer)
        )
        t3 = time.perf_counter()
        self._previous = sel
        self._evict(renderer, sel)
        gpu = sum(renderer.resident().values())
        stages = streamer.resident()
        stream = {
            **streamer.stats.since(before),
            "stall_ms": round(stall, 2),
            "frame_cpu_ms": round((t2 - t0) * 1e3, 2),
            "gpu_bytes": gpu,
            "memory_bytes": stages["memory"],
            "cache_bytes": stages["cache"],
            "in_flight": streamer.in_flight(),
        }
        self.last = FrameStats(
            sel.stats(),
            renderer.last_stats.draw_calls,
            renderer.last_stats.triangles,
            uploaded + taken,
            gpu / 2**20,
            (t1 - t0) * 1e3,
            (t2 - t1) * 1e3,
            (t3 - t2) * 1e3,
            stream,
            culled,
            culled_tris,
            self._city_stats(),
            renderer.last_stats.submit_ms,
            renderer.terrain_mode,
        )
        return rgb, depth

    def _prefetch(self, cam: Camera, streamer: Streamer, on_gpu: Callable[[int], bool]) -> None:
        """The memory and cache radii: what the camera will want ``ahead`` seconds on along its
        velocity. The predicted selections run on a worker (a few milliseconds each), and their
        keys are asked for once they are ready; what they ask for then may be a frame stale."""
        pending = self._predicted
        if pending is not None and pending.done():
            self._predicted = None
            for stage, keys in pending.result():
                streamer.request(keys, stage, on_gpu)
        now = streamer.clock.now()
        pos = cam.position
        last, self._motion = self._motion, (now, pos)
        ahead = streamer.options.ahead
        if last is None or not ahead or self._predicted is not None or now <= last[0]:
            return
        # a few times a second is enough: the radii move little in a tenth of a second
        if now - self._predicted_at < _PREDICT_EVERY:
            return
        self._predicted_at = now
        velocity = (pos - last[1]) / (now - last[0])
        self._predicted = self._pool.submit(self._predict, cam, pos, velocity, ahead)

    def _predict(
        self,
        cam: Camera,
        pos: NDArray[np.float64],
        velocity: NDArray[np.float64],
        ahead: tuple[float, ...],
    ) -> list[tuple[Literal["memory", "cache"], list[int]]]:
        out: list[tuple[Literal["memory", "cache"], list[int]]] = []
        for i, seconds in enumerate(ahead):
            lon, lat, alt = ecef_to_geodetic(pos + velocity * seconds)
            try:
                future = self.prepare(cam.moved(lon=float(lon), lat=float(lat), alt=float(alt)))
            except CameraError:
                continue  # the path would go under the ground: nothing to fetch for it
            sel = select(self.options.select, future, self.tree)
            keys = [int(k) for k in np.concatenate([sel.texture_keys, sel.keys])]
            out.append(("memory" if i == 0 else "cache", keys))
        return out

    def frames(
        self, cameras: Iterator[Camera]
    ) -> Iterator[tuple[NDArray[np.uint8], NDArray[np.float32]]]:
        for cam in cameras:
            yield self.render(cam)

    # --- resources --------------------------------------------------------------------------

    # --- the city (paper 001) ---------------------------------------------------------------

    def add_city(self, city: str | PathLike[str] | Any, options: Any = None) -> Any:
        """Drape a city on the terrain: an OSM file (.osm.pbf, .osm) or a built ``CityModel``;
        its objects stand on this scene's ground. Returns the model."""
        from lodscape.city.model import CityModel, CityOptions, build_city
        from lodscape.city.osm import City, read_osm

        if isinstance(city, CityModel):
            model = city
        else:
            model = build_city(
                city if isinstance(city, City) else read_osm(str(city)), self.heights
            )
        if self._city_pass is not None:
            self._city_pass.release()
            self._city_pass = None
        self.city = model
        self.city_options = options or CityOptions()
        return model

    def set_city_options(self, options: Any) -> None:
        """Change how the city is drawn (``CityOptions``); occlusion culling starts afresh."""
        self.city_options = options
        if self._city_pass is not None:
            self._city_pass.reset()

    def heights(self, lon: NDArray[np.float64], lat: NDArray[np.float64]) -> NDArray[np.float64]:
        """Ground heights at many points (NaN outside the data)."""
        lon = np.asarray(lon, np.float64)
        lat = np.asarray(lat, np.float64)
        provider: Any = self.provider
        # through the wrappers that change only the textures (imagery, land cover)
        while getattr(provider, "source", None) is None and getattr(provider, "base", None):
            provider = provider.base
        source = getattr(provider, "source", None)
        if source is not None and hasattr(source, "sample"):
            xm, ym = lonlat_to_merc(lon, lat)
            h, ok = source.sample(xm, ym, source.resolution_merc)
            return np.where(ok, np.asarray(h, np.float64), np.nan)
        if hasattr(provider, "heights") and callable(provider.heights):  # a tileset
            return np.asarray(provider.heights(lon, lat), np.float64)
        out = [
            self.ground_height(float(a), float(b))
            for a, b in zip(lon.ravel(), lat.ravel(), strict=False)
        ]
        return np.array([np.nan if v is None else v for v in out]).reshape(lon.shape)

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

    def _city_passes(self, renderer: Renderer) -> list[Callable[[Camera, Any], None]]:
        if self.city is None:
            return []
        if self._city_pass is None:
            from lodscape.render.city_pass import CityPass

            self._city_pass = CityPass(renderer.ctx, self.city, renderer.anisotropy)
        cp, opts = self._city_pass, self.city_options

        def draw(camera: Camera, fbo: Any) -> None:
            cp.draw(camera, opts, fbo)

        return [draw]

    def _city_stats(self) -> dict[str, int]:
        if self._city_pass is None or self.city is None:
            return {}
        stats: dict[str, int] = self._city_pass.last.as_dict()
        return stats

    def _renderer_for(self, camera: Camera) -> Renderer:
        if self._renderer is None:
            mode = self.options.terrain_mode
            try:
                self._renderer = Renderer(
                    camera.width,
                    camera.height,
                    ctx=self._ctx,
                    background=self.options.background,
                    anisotropy=self.options.anisotropy,
                    terrain_mode=mode,
                    tess_px=self.options.tess_px,
                    ground=self.ground,
                )
            except TessellationUnavailable as exc:
                self.terrain_mode_note = f"{exc}; drawing in the CPU terrain mode"
                self._renderer = Renderer(
                    camera.width,
                    camera.height,
                    ctx=self._ctx,
                    background=self.options.background,
                    anisotropy=self.options.anisotropy,
                    ground=self.ground,
                )
        return self._renderer

    @property
    def ground(self) -> str:
        """ "landcover" where the provider's textures are land-cover masks, else "imagery"."""
        return "landcover" if getattr(self.provider, "landcover", None) is not None else "imagery"

    def use_context(self, ctx: Any) -> None:
        """Draw in ``ctx`` (a window's OpenGL context) from the next frame on; frames then stay
        in ``renderer.framebuffer`` instead of coming back as arrays."""
        if self._renderer is not None:
            raise RuntimeError("use_context before the first frame")
        self._ctx = ctx

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

    def _prepare(self, key: int) -> TileMesh | NDArray[np.uint8]:
        p = self.provider
        return p.texture(key) if is_texture(key) else self._heights(key, p.mesh(key))

    def _heights(self, key: int, made: Any) -> Any:
        """On a worker: in the GPU terrain mode, a mesh's height texture made beside it, so the
        GL thread only uploads."""
        if self.terrain_mode != "gpu" or not isinstance(made, TileMesh):
            return made
        if made.height_tile is not None:
            return made
        from lodscape.terrain.heightmap import height_tile

        t = tile_of(key)
        return replace(made, height_tile=height_tile(made, t.z, t.x, t.y))

    def _load(self, renderer: Renderer, keys: NDArray[np.uint64]) -> int:
        # workers read, mesh and shade; this thread, which owns the GL context, uploads
        todo = [int(k) for k in keys]
        for key, made in zip(todo, self._pool.map(self._prepare, todo), strict=True):
            if isinstance(made, TileMesh):
                renderer.upload(made)
            else:
                renderer.upload_texture(key, made)
        return len(todo)

    def _evict(self, renderer: Renderer, sel: Selection) -> None:
        drawn = _drawn_keys(sel)
        for k in drawn:
            self._used[k] = None
            self._used.move_to_end(k)
        budget = self.options.gpu_budget_mb * 2**20
        sizes = renderer.resident()
        total = sum(sizes.values())
        for key in list(self._used):
            if total <= budget:
                break
            if key in drawn:
                continue
            total -= sizes.get(key, 0)
            renderer.release(key)
            del self._used[key]

    def release_provider(self) -> None:
        """Stop owning the provider: closing the scene then leaves it open (for a caller that
        wraps it in another scene)."""
        self._owns = False

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        if self.streamer is not None:
            self.streamer.close()
        if self._renderer is not None:
            if self._city_pass is not None:
                self._renderer._use()
                self._city_pass.release()
                self._city_pass = None
            self._renderer.close()
            self._renderer = None
        if self._owns:
            self.provider.close()
            self._owns = False

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _keys(renderer: Renderer) -> NDArray[np.uint64]:
    return np.array(sorted(renderer.resident()), dtype=np.uint64)


def _roots(keys: list[int], zmin: int) -> list[int]:
    """The mesh (coarsest grid) and texture keys of the root tiles above ``keys``."""
    ids = tile_id_of_array(keys)
    z, x, y = tile_from_id_array(ids)
    up = z - zmin
    rid = np.unique(tile_id_array(np.full(z.size, zmin), x >> up, y >> up))
    return [mesh_key(int(r), 0) for r in rid] + [texture_key(int(r)) for r in rid]


def _drawn_keys(sel: Selection) -> set[int]:
    """The meshes and textures a selection draws."""
    return {int(k) for k in sel.keys} | {int(k) for k in sel.texture_keys}


def _upload(renderer: Renderer, key: int, made: TileMesh | NDArray[np.uint8]) -> None:
    if isinstance(made, TileMesh):
        renderer.upload(made)
    else:
        renderer.upload_texture(key, made)


def _skirt_triangles(total: int, patches: int) -> int:
    """Skirt triangles of a grid mesh of ``total`` triangles in ``patches`` patches: 8·S for S
    segments, where total = 2·S² + 8·S."""
    if patches <= 1:
        # a TIN's patch is its whole surface; a small grid is one patch: skirts go with it
        return 0
    s = int((-8 + (64 + 8 * total) ** 0.5) / 4 + 0.5)
    return 8 * s


def _runs(keep: NDArray[np.bool_], per: int, total: int) -> tuple[tuple[int, int], ...]:
    """Contiguous (first, count) runs of triangles of the kept patches (``per`` triangles
    each), then the skirts that follow the last patch."""
    edges = np.diff(np.concatenate([[0], keep.astype(np.int8), [0]]))
    starts, ends = np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]
    out = [(int(a) * per, int(b - a) * per) for a, b in zip(starts, ends, strict=True)]
    n = keep.size
    if total > n * per:
        out.append((n * per, total - n * per))
    return tuple(out)


def draw_items(sel: Selection, max_sse: float = 2.0) -> list[DrawItem]:
    """The renderer's draw list for a selection: each tile's mesh, its texture and the window of
    that texture it covers (a half per level up), its skirt, and the screen-space error the GPU
    terrain mode's tessellation may add to the tile's own (``max_sse`` less it, at least a
    tenth of ``max_sse``)."""
    up = sel.texture_up
    scale = np.exp2(-up.astype(np.float64))
    u = (sel.x & ((1 << up) - 1)) * scale
    v = (sel.y & ((1 << up) - 1)) * scale
    budget = np.maximum(max_sse - sel.sse, 0.1 * max_sse)
    cols = zip(sel.keys, sel.texture_keys, sel.skirt, u, v, scale, budget, strict=True)
    return [
        DrawItem(int(k), int(t), float(sk), (float(a), float(b), float(c)), sse_budget=float(e))
        for k, t, sk, a, b, c, e in cols
    ]


def open(
    source: str | PathLike[str] | HeightSource | Provider | NDArray[np.floating],
    options: SceneOptions | None = None,
    *,
    clock: Clock | None = None,
    detail: Fractal | None = None,
    landcover: Any = None,
    **array_kwargs: Any,
) -> Scene:
    """A scene over a tileset built by ``lodscape build`` (.lods), a GeoTIFF (any GDAL raster), a
    numpy array (with ``transform``, ``crs``), the procedural planet (``"procedural:seed=N"``),
    or a ready HeightSource or Provider. ``detail`` adds fractal detail below a raster's
    resolution (paper 003). ``landcover`` (an ``imagery.landcover.Landcover``) colours the
    ground from its class masks instead of the tint. A scene opened from a path or an array
    closes what it opened when it closes."""
    if landcover is None:
        return _open_terrain(source, options, clock=clock, detail=detail, **array_kwargs)
    from lodscape.store.provider import LandcoverProvider

    raster = isinstance(source, np.ndarray) or (
        isinstance(source, str | PathLike)
        and not is_tileset(source)
        and not str(source).startswith("procedural")
    )
    if detail is None and raster:
        # a mask is worth metres, not the DEM's resolution: the tree goes on below the data
        # with heights interpolated (fractal detail of no amplitude), and its masks with it
        detail = Fractal(0.7, 0.0, 0)
    terrain = _open_terrain(source, options, detail=detail, **array_kwargs)
    provider = LandcoverProvider(terrain.provider, landcover)
    terrain.release_provider()
    terrain.close()
    return Scene(provider, options, owns=True, clock=clock)


def _open_terrain(
    source: str | PathLike[str] | HeightSource | Provider | NDArray[np.floating],
    options: SceneOptions | None = None,
    *,
    clock: Clock | None = None,
    detail: Fractal | None = None,
    **array_kwargs: Any,
) -> Scene:
    """``open`` without a land cover."""
    if isinstance(source, str) and (source == "procedural" or source.startswith("procedural:")):
        return Scene(procedural_provider(source, detail), options, owns=True, clock=clock)
    if isinstance(source, str) and source.startswith("flat:"):
        src: HeightSource = flat_source(source)
    elif isinstance(source, np.ndarray):
        src = ArraySource(source, **array_kwargs)
    elif isinstance(source, str | PathLike):
        if is_tileset(source):
            if detail is not None:
                raise SourceError(
                    f"{source}: fractal detail needs a raster source; a tileset keeps no lattice "
                    "of the data to add it to"
                )
            return Scene(TilesetProvider(source), options, owns=True, clock=clock)
        src = RasterSource(source)
    else:
        if detail is not None:
            raise SourceError("fractal detail needs a raster source, not a ready provider")
        return Scene(source, options, clock=clock)
    if detail is None:
        return Scene(src, options, owns=True, clock=clock)
    try:
        return Scene(fractal_provider(src, detail), options, owns=True, clock=clock)
    except BaseException:
        src.close()
        raise


def flat_source(spec: str) -> ArraySource:
    """``flat:WEST,SOUTH,EAST,NORTH[,HEIGHT]``: level ground (the ellipsoid, or HEIGHT metres
    above it) over a box in degrees, for cities and tests with no DEM."""
    try:
        vals = [float(v) for v in spec.split(":", 1)[1].split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (4, 5) or not all(math.isfinite(v) for v in vals):
        raise SourceError(f"{spec}: expected flat:WEST,SOUTH,EAST,NORTH[,HEIGHT] in degrees")
    w, s, e, n = vals[:4]
    h = vals[4] if len(vals) == 5 else 0.0
    if not (-180.0 <= w < e <= 180.0 and -85.0 <= s < n <= 85.0):
        raise SourceError(f"{spec}: the box must have west < east and south < north, in degrees")
    size = 65
    from affine import Affine

    transform = Affine(
        (e - w) / (size - 1),
        0.0,
        w - 0.5 * (e - w) / (size - 1),
        0.0,
        -(n - s) / (size - 1),
        n + 0.5 * (n - s) / (size - 1),
    )
    src = ArraySource(np.full((size, size), h), transform, crs="EPSG:4326")
    src.name = spec
    return src


def fractal_provider(source: HeightSource, fractal: Fractal) -> FractalProvider:
    """A raster with fractal detail below its resolution."""
    tree = DetailTree.over(build_tree(source), fractal)
    return FractalProvider(DetailHeights(source, tree), tree)


def procedural_provider(spec: str, override: Fractal | None = None) -> FractalProvider:
    """The procedural planet of ``procedural:seed=N[,hurst=H][,sigma=S]``; ``override``'s
    fields, where given, win over the spec's."""
    try:
        f = parse_procedural(spec)
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    if override is not None:
        f = Fractal(
            override.hurst,
            override.sigma if override.sigma is not None else f.sigma,
            override.seed,
        )
    sigma = float(f.sigma if f.sigma is not None else 0.0)
    tree = ProceduralTree(f, sigma)
    return FractalProvider(ProceduralHeights(tree), tree)
