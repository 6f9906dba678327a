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
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from os import PathLike
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError
from lodscape.geo.frames import WGS84_A
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.lod.camera import Camera
from lodscape.lod.select import TEXTURE, Selection, SelectOptions, select, tile_boxes
from lodscape.render import DrawItem, Renderer
from lodscape.store.provider import Provider, RasterProvider
from lodscape.store.tileset import TilesetProvider, is_tileset
from lodscape.terrain.mesh import TileMesh
from lodscape.terrain.pyramid import TileTree
from lodscape.terrain.source import ArraySource, HeightSource, RasterSource

__all__ = ["FrameStats", "Scene", "SceneOptions", "open"]

SKY = (0.62, 0.75, 0.88)


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

    def __post_init__(self) -> None:
        if not self.gpu_budget_mb > 0.0:
            raise ValueError(f"Expected a positive gpu_budget_mb, got {self.gpu_budget_mb}")
        if self.workers < 1:
            raise ValueError(f"Expected at least one worker, got {self.workers}")
        if not self.anisotropy >= 1.0:
            raise ValueError(f"Expected anisotropy >= 1, got {self.anisotropy}")


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
        self._previous: Selection | None = None
        self._used: OrderedDict[int, None] = OrderedDict()
        self._pool = ThreadPoolExecutor(max(1, self.options.workers), "lodscape-load")
        self.last: FrameStats | None = None

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
        lv = self.tree.level(self.tree.zmin)
        _, idx = lv.index(x, y)
        probe = camera.with_clip(1.0, 2.0)
        boxes = tile_boxes(
            probe, self.tree.zmin, x, y, lv.min_h.ravel()[idx], lv.max_h.ravel()[idx]
        )
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
        items = draw_items(sel)
        rgb, depth = renderer.draw(cam, items, background=self.options.background)
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
        )
        return rgb, depth

    def frames(
        self, cameras: Iterator[Camera]
    ) -> Iterator[tuple[NDArray[np.uint8], NDArray[np.float32]]]:
        for cam in cameras:
            yield self.render(cam)

    # --- resources --------------------------------------------------------------------------

    def _renderer_for(self, camera: Camera) -> Renderer:
        if self._renderer is None:
            self._renderer = Renderer(
                camera.width,
                camera.height,
                background=self.options.background,
                anisotropy=self.options.anisotropy,
            )
        return self._renderer

    def _prepare(self, key: int) -> TileMesh | NDArray[np.uint8]:
        p = self.provider
        return p.texture(key) if key & 7 == TEXTURE else p.mesh(key)

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
        for k in sel.keys:
            self._used[int(k)] = None
            self._used.move_to_end(int(k))
        drawn = {int(k) for k in sel.keys}
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

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._owns:
            self.provider.close()
            self._owns = False

    def __enter__(self) -> Scene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def draw_items(sel: Selection) -> list[DrawItem]:
    """The renderer's draw list for a selection: each tile's mesh, its texture and the window of
    that texture it covers (a half per level up), and its skirt."""
    up = sel.texture_up
    scale = np.exp2(-up.astype(np.float64))
    u = (sel.x & ((1 << up) - 1)) * scale
    v = (sel.y & ((1 << up) - 1)) * scale
    cols = zip(sel.keys, sel.texture_keys, sel.skirt, u, v, scale, strict=True)
    return [
        DrawItem(int(k), int(t), float(sk), (float(a), float(b), float(c)))
        for k, t, sk, a, b, c in cols
    ]


def open(
    source: str | PathLike[str] | HeightSource | Provider | NDArray[np.floating],
    options: SceneOptions | None = None,
    **array_kwargs: Any,
) -> Scene:
    """A scene over a tileset built by ``lodscape build`` (.lods), a GeoTIFF (any GDAL raster), a
    numpy array (with ``transform``, ``crs``), or a ready HeightSource or Provider. A scene
    opened from a path or an array closes what it opened when it closes."""
    if isinstance(source, np.ndarray):
        return Scene(ArraySource(source, **array_kwargs), options, owns=True)
    if isinstance(source, str | PathLike):
        if is_tileset(source):
            return Scene(TilesetProvider(source), options, owns=True)
        return Scene(RasterSource(source), options, owns=True)
    return Scene(source, options)
