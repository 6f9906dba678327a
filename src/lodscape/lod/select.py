"""Tile selection: which tiles to draw this frame, with which mesh and texture, and what to load.

``select`` is a pure function (cesium-native's ViewUpdateResult, not CesiumJS's queue-editing
visitTile): it walks the quadtree one level per step with numpy, returns the render list, the load
requests and the counters, and touches no IO and no GPU.

The rules, per tile, with T the texels per tile side, and both screen measures taken as the
projection draws them over the tile's box (``Camera.box_scales``: the depth along the view axis
at its nearest point, never nearer than the near plane, and the worst place of its image):
H = h·d/Z·σ (paper 000's h·d/dist, σ the most a ground direction stretches there) the most
pixels its side covers, and a height error e seen as e·d/Z·γ pixels (γ the part of the vertical
across the line of sight, off-axis stretch included: Lindstrom's projected error, as a bound):
- culled when its box (its min/max heights included) lies outside a frustum plane;
- split when H > split·T; kept split while the previous frame had it split and every child still
  covers merge·T pixels or more (hysteresis, no flicker);
- split when even its finest grid cannot keep the screen-space error within ``max_sse``;
- otherwise drawn, with the coarsest grid whose error stays within ``max_sse``, so the mesh
  follows the terrain's roughness. (A tree's "grids" are whatever meshes its tiles have, each
  with its recorded error: regular grids, or ``terrain.tin_tiles``' ladder of error bounds.)
  A drawn tile whose image spans a quarter of the view or more has its γ·d/Z taken as the
  worst over parts of its box in view (``parts_vertical``), not at its nearest depth and its
  image's worst place at once, which over such a box are far apart.
Tiles kept all round by distance (``reach``: paper 004's areas, whatever the view's direction)
are measured as if the camera looked at them: pixels per metre at their nearest point.

Textures are chosen apart from meshes. A drawn tile takes the texture of the ancestor k levels
up for the largest k with H·2^k <= split·T / ``SLOPE_ROOM``: the coarsest whose texels stay
under 1.25 px where the tile is largest on screen (a far sibling of a tile that had to split
takes an ancestor's), so drawn texels stay inside the band (paper 000's 128..384 px for 256 px
tiles) where the tile is farther or seen edge-on, with room for slopes facing the camera.

Imagery layers (the user's orthophotos and tile servers) are chosen the same way, each capped by
its own finest level rather than the terrain's: a tile keeps splitting for its texture down to
the finest level of any layer (below the terrain's own levels its mesh is its parent's surface
refined), and a layer with no tile that fine lends the tile a window of its finest ancestor.

Resources are keyed as ``lodscape.geo.keys`` says: a mesh key per tile and grid, a texture key
per tile and layer.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import WGS84_A, enu_basis, geodetic_to_ecef
from lodscape.geo.keys import (
    grid_of_array,
    is_texture_array,
    layer_of_array,
    mesh_keys_zxy,
    texture_keys_zxy,
    tile_id_of_array,
)
from lodscape.geo.tiles import (
    ORIGIN,
    bounds_array,
    merc_to_lonlat,
    tile_from_id_array,
    tile_id_array,
)
from lodscape.lod.camera import EARTH_MIN_RADIUS, MIN_DISTANCE, Camera
from lodscape.lod.region import region_view

__all__ = [
    "LearnsFromLoads",
    "LevelLike",
    "MadeOnDemand",
    "SelectOptions",
    "Selection",
    "TileStats",
    "TreeLike",
    "hysteresis_steps",
    "parts_vertical",
    "select",
    "tile_boxes",
    "tile_far",
]

I64 = NDArray[np.int64]
U64 = NDArray[np.uint64]
F64 = NDArray[np.float64]

_EMPTY_U = np.zeros(0, dtype=np.uint64)
#: Levels coarser than the pixel band that the terrain's own texture is taken at under imagery
#: layers (it shows where they are transparent or not in yet).
UNDER_LAYERS = 2
#: An imagery layer's key where a tile has none of its tiles to draw (``Selection.layer_keys``).
NO_TEXTURE = np.uint64(0xFFFF_FFFF_FFFF_FFFF)
#: A tile's texture is taken with its texels at most split / SLOPE_ROOM pixels where its box is
#: largest on screen: room for slopes facing the camera (measured: tests/test_screen_error.py).
SLOPE_ROOM = 1.2
#: Slack around each tile's box, as a share of its side.
_MARGIN = 1e-3
#: A box's eight corners: which of its low (False) or high (True) bounds each takes, per axis.
_CORNERS = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)
#: Fewer children than this go straight to their bounds (the region test would cost more).
_REGION_MIN = 32


class TileStats(Protocol):
    """What the selection needs of N tiles of one level (zero where a tile does not exist); the
    terrain's ``TileStats`` is the one the trees give."""

    @property
    def exists(self) -> NDArray[np.bool_]: ...

    @property
    def min_h(self) -> NDArray[np.floating]: ...

    @property
    def max_h(self) -> NDArray[np.floating]: ...

    #: (len(grids), N) metres of geometric error of each grid.
    @property
    def error(self) -> NDArray[np.floating]: ...

    #: Tiles without children (never split), or None.
    @property
    def leaf(self) -> NDArray[np.bool_] | None: ...

    def take(self, m: NDArray[np.bool_]) -> TileStats: ...


class LevelLike(Protocol):
    """One level of a tile tree: stored (a dense pyramid) or computed on demand (fractal
    detail, a procedural planet)."""

    @property
    def z(self) -> int: ...

    def stats(self, x: I64, y: I64) -> TileStats: ...


class TreeLike(Protocol):
    @property
    def grids(self) -> tuple[int, ...]: ...

    @property
    def tile_size(self) -> int: ...

    @property
    def zmin(self) -> int: ...

    @property
    def zmax(self) -> int: ...

    @property
    def texture_zmax(self) -> int | None: ...

    @property
    def height_range(self) -> tuple[float, float]: ...

    def level(self, z: int) -> LevelLike: ...

    def roots(self) -> tuple[I64, I64]: ...


@runtime_checkable
class MadeOnDemand(Protocol):
    """A tree whose statistics are made as selections reach them (``terrain.lazy.LazyTree``):
    a tile splits only where ``ready`` says its children's are known; ``wait`` says whether
    the selection waits for them (a whole picture) or asks and draws the tile whole (a
    streamed frame)."""

    wait: bool

    def ready(self, z: int, x: I64, y: I64) -> NDArray[np.bool_]: ...


@runtime_checkable
class LearnsFromLoads(Protocol):
    """A tree that learns as its tiles come (a terrain server's: a tile's heights are known
    once its mesh is): ``epoch`` grows with each lesson, and a blocking frame selects again."""

    epoch: int


@dataclass(frozen=True)
class SelectOptions:
    """How selection trades detail for speed; the defaults follow paper 000's 128..384 px band."""

    #: Split a tile that covers more than split × its texture size in pixels.
    split: float = 1.5
    #: Merge four children back only when one would cover less than merge × its texture size.
    merge: float = 0.5
    #: Bound on every drawn tile's geometric screen-space error, pixels.
    max_sse: float = 2.0
    #: Deepest level to use (None: the tree's finest).
    max_level: int | None = None
    #: A tile split for its error merges back only when its finest grid's error falls below
    #: this share of ``max_sse`` (hysteresis, as ``merge`` is for the pixel band).
    sse_merge: float = 0.75
    #: Drop children outside the visible region (frustum ∩ the slab of their parents' heights,
    #: paper 003's quadrangle made conservative) before asking for their bounds. Off by
    #: default: each tile's exact box test already prunes, and the region costs more than the
    #: bounds it spares (bench/bench_detail.py).
    region: bool = False
    #: A tile keeps at least its parent's resolution (the grid of half the segments its parent
    #: would be drawn with): splitting never coarsens the ground, so it never jumps there. It
    #: costs triangles where a rough parent splits into smooth children (``bench_morph.py``
    #: measures it). None: where the frames geomorph (``TerrainView.morph``, a scene's
    #: streamed frames), not in a still picture, which has nothing to glide.
    hold_parent_grid: bool | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.merge < self.split:
            raise ValueError(f"Expected 0 < merge < split, got {self.merge} and {self.split}")
        if not 2.0 * self.merge <= self.split:
            # a texture one level up doubles the pixels per texel: the band must hold both
            raise ValueError(f"Expected split >= 2·merge, got {self.merge} and {self.split}")
        if not self.max_sse > 0.0:
            raise ValueError(f"Expected a positive max_sse, got {self.max_sse}")
        if not 0.0 < self.sse_merge <= 1.0:
            raise ValueError(f"Expected 0 < sse_merge <= 1, got {self.sse_merge}")


@dataclass(frozen=True, eq=False)
class Selection:
    """A frame's render list, load requests and counters. Arrays run over the drawn tiles."""

    z: I64
    x: I64
    y: I64
    #: Index into the tree's grids of the grid each tile is drawn with.
    grid: I64
    #: Mesh resource keys (``geo.keys.mesh_key``) of the drawn tiles.
    keys: U64
    #: Texture resource keys; the texture of the ancestor ``texture_up`` levels up.
    texture_keys: U64
    texture_up: I64
    screen_px: F64
    sse: F64
    dist_near: F64
    #: Metres to hang each tile's skirt: its own error plus what a neighbour's may be.
    skirt: F64
    #: Levels each drawn tile stands above the one wanted (0: drawn as wanted).
    fallback: I64
    #: Ids of the tiles refined this frame, sorted (the next frame's hysteresis).
    refined: U64
    #: Keys wanted but not resident, most urgent first (coarse levels, then near tiles).
    loads: U64
    visited: int = 0
    culled: int = 0
    #: Tiles dropped by the visible region before their bounds were asked for.
    outside: int = 0
    #: Tiles whose texture is drawn above split × its size: the data has no finer texture, or
    #: the near plane cuts the tile.
    magnified: int = 0
    texture_size: int = 256
    grids: tuple[int, ...] = field(default=(16, 32, 64, 128, 256))
    #: Levels up each tile's texture would be for the pixel band alone, uncapped (hysteresis).
    band_up: I64 | None = None
    #: (L, N) keys of each imagery layer's tile each drawn tile wears (``NO_TEXTURE``: none
    #: resident yet), and how many levels above the tile it is.
    layer_keys: U64 = field(default_factory=lambda: np.zeros((0, 0), np.uint64))
    layer_up: I64 = field(default_factory=lambda: np.zeros((0, 0), np.int64))
    #: (tile, layer) pairs drawn with an ancestor's imagery tile or none, for want of theirs.
    layer_fallbacks: int = 0

    @property
    def count(self) -> int:
        return int(self.z.size)

    @property
    def max_depth(self) -> int:
        return int(self.z.max()) if self.z.size else -1

    @property
    def max_sse(self) -> float:
        return float(self.sse.max()) if self.sse.size else 0.0

    @property
    def triangles(self) -> int:
        """Triangles of the drawn tiles' grids, skirts included: for TINs (``terrain.tin_tiles``,
        whose "grids" are the finest grid's) a bound; what is drawn is ``FrameStats``'."""
        s = np.asarray(self.grids, dtype=np.int64)[self.grid]
        return int((2 * s * s + 8 * s).sum())

    @property
    def px_per_texel(self) -> F64:
        """Screen pixels per texel of each drawn tile's texture (1: the texture's own size)."""
        return self.screen_px * np.exp2(self.texture_up) / self.texture_size

    @property
    def px_per_texel_range(self) -> tuple[float, float]:
        if not self.z.size:
            return (0.0, 0.0)
        r = self.px_per_texel
        return float(r.min()), float(r.max())

    def layer_px_per_texel(self, layer: int) -> F64:
        """Screen pixels per texel of imagery layer ``layer`` (1..) on each drawn tile (NaN where
        the tile has none of its tiles)."""
        up = self.layer_up[layer - 1]
        r = self.screen_px * np.exp2(up) / self.texture_size
        return np.where(self.layer_keys[layer - 1] == NO_TEXTURE, np.nan, r)

    def stats(self) -> dict[str, float | int]:
        lo, hi = self.px_per_texel_range
        return {
            "tiles": self.count,
            "visited": self.visited,
            "culled": self.culled,
            "outside": self.outside,
            "refined": int(self.refined.size),
            "max_depth": self.max_depth,
            "max_sse_px": round(self.max_sse, 3),
            "px_per_texel_min": round(lo, 3),
            "px_per_texel_max": round(hi, 3),
            "magnified": self.magnified,
            "triangles": self.triangles,
            "textures": int(np.unique(self.texture_keys).size),
            "layer_tiles": int(np.unique(self.layer_keys[self.layer_keys != NO_TEXTURE]).size),
            "layer_fallbacks": self.layer_fallbacks,
            "loads": int(self.loads.size),
            "fallback_max": int(self.fallback.max()) if self.fallback.size else 0,
        }


@dataclass(frozen=True, eq=False)
class Boxes:
    """Oriented boxes of tiles, relative to the camera, with their screen metrics."""

    inside: NDArray[np.bool_]
    dist_near: F64
    dist_far: F64
    ground: F64
    #: Box centres relative to the camera, ECEF metres (N, 3).
    centre: F64
    #: The most pixels a metre of height error covers anywhere in the box on screen
    #: (``Camera.box_scales``): what a tile's geometric error is charged at.
    vertical: F64
    #: The most pixels a metre along the ground covers anywhere in the box on screen.
    horizontal: F64


#: What ``_box_frames`` gives per tile: its basis (N, 3, 3), its box in that frame (lo, hi:
#: (N, 3)), its ground size (N), and the box with its margin in ECEF: its eight corners
#: (N, 8, 3) and its centre (N, 3).
BoxFrames = tuple[F64, F64, F64, F64, F64, F64]


def _box_frames(
    z: int, x: I64, y: I64, min_h: NDArray[np.floating], max_h: NDArray[np.floating]
) -> BoxFrames:
    """Per tile: its local ENU basis (N, 3, 3), the box of its n×n lattice at its min and max
    height in that frame about the Earth's centre (lo, hi: (N, 3)), and its ground size; n is
    chosen per level so that the Earth's curve bulges less between lattice points than the
    box's margin. Then the box widened by its margin in ECEF, as ``tile_boxes`` tests it
    (where the camera is enters only as a shift): its corners and its centre."""
    if x.size == 0:
        return (
            np.zeros((0, 3, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 8, 3)),
            np.zeros((0, 3)),
        )
    left, bottom, right, top = bounds_array(z, x, y)
    side = 2.0 * ORIGIN / (1 << z)
    # a chord of length L sags L²/(8R) below the sphere: keep that under the margin
    n = min(2 + math.ceil(math.sqrt(side / (8.0 * WGS84_A * _MARGIN))), 33)
    f = np.linspace(0.0, 1.0, n)
    xs = left[:, None] + f * (right - left)[:, None]
    ys = bottom[:, None] + f * (top - bottom)[:, None]
    lon, lat = merc_to_lonlat(xs[:, None, :], ys[:, :, None])
    clon, clat = merc_to_lonlat((left + right) / 2.0, (bottom + top) / 2.0)
    basis = enu_basis(clon, clat)
    lo_h = np.asarray(min_h, np.float64)[:, None, None]
    hi_h = np.asarray(max_h, np.float64)[:, None, None]
    pts = np.concatenate(
        [geodetic_to_ecef(lon, lat, lo_h), geodetic_to_ecef(lon, lat, hi_h)], axis=1
    ).reshape(len(x), -1, 3)
    local = np.einsum("nij,npj->npi", basis, pts)
    ground = (right - left) * np.cos(np.radians(clat))
    lo, hi = local.min(axis=1), local.max(axis=1)
    margin = (_MARGIN * ground)[:, None]
    lo_m, hi_m = lo - margin, hi + margin
    corners = np.einsum(
        "nci,nij->ncj", np.where(_CORNERS, hi_m[:, None, :], lo_m[:, None, :]), basis
    )
    centre = np.einsum("ni,nij->nj", (lo_m + hi_m) / 2.0, basis)
    return basis, lo, hi, ground, corners, centre


class _BoxFrames:
    """``_box_frames`` of the tiles selections have met, per level (sorted tile ids and their
    rows), so a frame works out only the tiles new to it: what a box is in its own frame does
    not depend on the camera. A tile whose height range changed (a tree that learns it) is
    worked out again. Bounded: a level's table is emptied when it outgrows ``limit``."""

    def __init__(self, limit: int = 1 << 15) -> None:
        self.limit = limit
        self._levels: dict[int, tuple[NDArray[Any], ...]] = {}
        self._lock = threading.Lock()

    def get(
        self, z: int, x: I64, y: I64, min_h: NDArray[np.floating], max_h: NDArray[np.floating]
    ) -> BoxFrames:
        lo_h = np.asarray(min_h, np.float64)
        hi_h = np.asarray(max_h, np.float64)
        if x.size == 0:
            return _box_frames(z, x, y, lo_h, hi_h)
        ids = tile_id_array(z, x, y)
        with self._lock:
            table = self._levels.get(z)
        n = ids.size
        if table is None:
            found = np.zeros(n, bool)
            row = np.zeros(n, np.int64)
        else:
            keys = table[0]
            row = np.minimum(np.searchsorted(keys, ids), max(keys.size - 1, 0))
            found = (keys[row] == ids) & (table[-2][row] == lo_h) & (table[-1][row] == hi_h)
        if found.all() and table is not None:
            return tuple(c[row] for c in table[1:-2])  # type: ignore[return-value]
        new = ~found
        made = _box_frames(z, x[new], y[new], lo_h[new], hi_h[new])
        out = tuple(np.empty((n, *c.shape[1:])) for c in made)
        for o, c in zip(out, made, strict=True):
            o[new] = c
        if table is not None and found.any():
            r = row[found]
            for o, c in zip(out, table[1:-2], strict=True):
                o[found] = c[r]
        with self._lock:
            table = self._levels.get(z)
            cols = [ids[new], *made, lo_h[new], hi_h[new]]
            if table is not None and table[0].size + int(new.sum()) <= self.limit:
                # the new rows win over stale ones of the same tile (a changed height range)
                stale = np.isin(table[0], ids[new])
                cols = [np.concatenate([t[~stale], c]) for t, c in zip(table, cols, strict=True)]
            order = np.argsort(cols[0], kind="stable")
            self._levels[z] = tuple(c[order] for c in cols)
        return out  # type: ignore[return-value]


_BOX_FRAMES = _BoxFrames()


def tile_boxes(
    camera: Camera,
    z: int,
    x: I64,
    y: I64,
    min_h: NDArray[np.floating],
    max_h: NDArray[np.floating],
    all_round: bool = False,
) -> Boxes:
    """Frustum test and distances for N tiles of one level, each boxed in its local ENU frame.

    The box holds an n×n lattice of the tile at its min and max height, with n chosen per level so
    that the Earth's curve bulges less between lattice points than the box's margin. Its scales
    are the projection's (``Camera.box_scales``); ``all_round`` (tiles kept by distance all
    round, paper 004's areas, whatever the view's direction) takes them as if the camera looked
    at the box's nearest point instead: pixels per metre there.
    """
    basis, lo0, hi0, ground, corners0, centre0 = _BOX_FRAMES.get(z, x, y, min_h, max_h)
    eye = camera.position
    lo, hi = _eye_box(basis, lo0, hi0, ground, eye)
    # the camera sits at the origin of these camera-relative coordinates
    gap = np.maximum(lo, 0.0) + np.maximum(-hi, 0.0)
    dist_near = np.linalg.norm(gap, axis=1)
    dist_far = _farthest(lo, hi)
    centre = centre0 - eye
    half = (hi - lo) / 2.0
    planes = camera.frustum_planes()
    s = centre @ planes[:, :3].T + planes[:, 3]
    r = np.einsum("ni,npi->np", half, np.abs(np.einsum("pj,nij->npi", planes[:, :3], basis)))
    inside = np.all(s + r >= 0.0, axis=1)
    if all_round:
        vertical = horizontal = camera.pixels_per_metre(dist_near)
    else:
        corners = corners0 - eye
        spread = _spread(ground)
        vertical, horizontal = camera.box_scales(
            corners, basis[:, 2], basis[:, 0], basis[:, 1], spread, dist_near
        )
    return Boxes(inside, dist_near, dist_far, ground, centre, vertical, horizontal)


#: A drawn tile large on screen is charged in parts (``parts_vertical``): ``Camera.box_scales``
#: charges a box at its nearest depth and at its image's worst place, which over a box that
#: fills the view are far apart (a tile under a camera looking down is nearest where its image
#: stretches least, and its nearest corner may be out of view). Its vertical scale (what its
#: height error is charged at) is then the worst of k × k parts side by side, each its full
#: height, in view, with k SUB_PER_VIEW times the share of the view its image spans, rounded up
#: (at most SUB_MAX), for boxes spanning SUB_MIN_SPAN of the view or more. Measured during the
#: walk for every tile, parts an eighth of the view across cost a selection about a third more
#: CPU than whole boxes (the eleventh pass, reverted); for the drawn tiles spanning a quarter of
#: the view, nothing measurable on the spine's views.
SUB_PER_VIEW = 8
SUB_MAX = 8
SUB_MIN_SPAN = 0.25


def _sub_count(camera: Camera, corners: F64) -> I64:
    """k per box: how many parts a side its measure takes (``SUB_PER_VIEW``), from its corners
    relative to the camera (N, 8, 3): the share of the view its image spans."""
    cam = corners @ camera.rotation.T
    depth = -cam[..., 2]
    floor = max(camera.near or 0.0, MIN_DISTANCE)
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    tx = ty * camera.aspect
    zs = np.maximum(depth, floor)
    a = np.clip(cam[..., 0] / zs, -tx, tx)
    b = np.clip(cam[..., 1] / zs, -ty, ty)
    span = np.maximum(
        (a.max(axis=-1) - a.min(axis=-1)) / (2 * tx), (b.max(axis=-1) - b.min(axis=-1)) / (2 * ty)
    )
    span = np.where(depth.min(axis=-1) < floor, 1.0, span)
    k: I64 = np.clip(np.ceil(span * SUB_PER_VIEW - 1e-9), 1, SUB_MAX).astype(np.int64)
    return np.where(span >= SUB_MIN_SPAN, k, 1)


def _parts_vertical(
    camera: Camera, planes: F64, basis: F64, lo: F64, hi: F64, spread: F64, k: I64
) -> F64:
    """The worst vertical ``Camera.box_scales`` over each box's k × k parts in the view (k per
    box), all boxes' parts at once."""
    rot = camera.rotation
    axes = basis @ rot.T  # (n, 3, 3): east, north, up in view space
    count = k * k
    owner = np.repeat(np.arange(k.size), count)
    first = np.cumsum(count) - count
    r = np.arange(owner.size) - first[owner]
    kk = k[owner]
    i, j = r % kk, r // kk
    side_e, side_n = hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1]
    x = lo[owner, 0, None] + np.stack([i, i + 1], axis=1) / kk[:, None] * side_e[owner, None]
    y = lo[owner, 1, None] + np.stack([j, j + 1], axis=1) / kk[:, None] * side_n[owner, None]
    h = np.stack([lo[:, 2], hi[:, 2]], axis=1)[owner]  # (P, 2)
    ax = axes[owner]
    # the parts' eight corners in view space (P, 2, 2, 2, 3): east, north, height
    pts = (
        (x[:, :, None] * ax[:, None, 0, :])[:, :, None, None, :]
        + (y[:, :, None] * ax[:, None, 1, :])[:, None, :, None, :]
        + (h[:, :, None] * ax[:, None, 2, :])[:, None, None, :, :]
    ).reshape(-1, 8, 3)
    floor = max(camera.near or 0.0, MIN_DISTANCE)
    ty = math.tan(math.radians(camera.fov_y) / 2.0)
    tx = ty * camera.aspect
    depth = -pts[..., 2:3]
    ab = pts[..., :2] / np.maximum(depth, floor)
    pv = planes[:, :3] @ rot.T  # the frustum's planes in view space
    sides = pts @ pv.T + planes[:, 3]  # (P, 8, 6)
    least = np.concatenate([depth, ab], axis=-1).min(axis=1)
    most = np.concatenate([ab, sides], axis=-1).max(axis=1)
    zmin = least[:, 0]
    crosses = zmin < floor
    a0 = np.where(crosses, -tx, np.clip(least[:, 1], -tx, tx))
    a1 = np.where(crosses, tx, np.clip(most[:, 0], -tx, tx))
    b0 = np.where(crosses, -ty, np.clip(least[:, 2], -ty, ty))
    b1 = np.where(crosses, ty, np.clip(most[:, 1], -ty, ty))
    # in view: not wholly beyond one frustum plane
    seen = np.all(most[:, 2:] >= 0.0, axis=1)
    u = ax[:, 2, :]
    ux, uy, uf = u[:, 0], u[:, 1], -u[:, 2]
    vertical = np.maximum(
        np.maximum(np.hypot(ux - a0 * uf, uy - b0 * uf), np.hypot(ux - a0 * uf, uy - b1 * uf)),
        np.maximum(np.hypot(ux - a1 * uf, uy - b0 * uf), np.hypot(ux - a1 * uf, uy - b1 * uf)),
    )
    stretch = np.sqrt(1.0 + np.maximum(a0 * a0, a1 * a1) + np.maximum(b0 * b0, b1 * b1))
    gap = np.maximum(np.stack([x[:, 0], y[:, 0], h[:, 0]], 1), 0.0) + np.maximum(
        -np.stack([x[:, 1], y[:, 1], h[:, 1]], 1), 0.0
    )
    corner = 1.0 / math.sqrt(1.0 + tx * tx + ty * ty)
    nearest = np.linalg.norm(gap, axis=1) * corner
    scale = camera.pixels_per_metre(np.maximum(zmin, nearest)) * (
        vertical + spread[owner] * stretch
    )
    v = np.maximum.reduceat(np.where(seen, scale, 0.0), first)
    # a box out of view has no part in it: it keeps the worst of all its parts
    out: F64 = np.where(v > 0.0, v, np.maximum.reduceat(scale, first))
    return out


def parts_vertical(
    camera: Camera,
    z: int,
    x: I64,
    y: I64,
    min_h: NDArray[np.floating],
    max_h: NDArray[np.floating],
) -> tuple[I64, F64]:
    """How many parts a side each tile's box is measured in (``SUB_PER_VIEW`` times the share
    of the view its image spans, rounded up, at most ``SUB_MAX``; 1 where it spans less than
    ``SUB_MIN_SPAN``), and where more than one, the most pixels a metre of height error covers
    over its parts in view (``Camera.box_scales`` of each part, each the box's full height;
    the parts cover the box, so the worst of them bounds it); NaN where one."""
    eye = camera.position
    basis, lo0, hi0, ground, corners0, _ = _BOX_FRAMES.get(z, x, y, min_h, max_h)
    ks = _sub_count(camera, corners0 - eye)
    out = np.full(ks.size, np.nan)
    big = np.flatnonzero(ks > 1)
    if big.size:
        lo, hi = _eye_box(basis[big], lo0[big], hi0[big], ground[big], eye)
        spread = _spread(ground[big])
        planes = camera.frustum_planes()
        out[big] = _parts_vertical(camera, planes, basis[big], lo, hi, spread, ks[big])
    return ks, out


def _coarser_in_parts(
    options: SelectOptions,
    camera: Camera,
    z: int,
    tiles: tuple[I64, I64, NDArray[np.floating], NDArray[np.floating]],
    err: NDArray[np.floating],
    scale: F64,
    px: F64,
    k: I64,
    draw: NDArray[np.bool_],
) -> tuple[I64, F64]:
    """The drawn tiles of level ``z`` (x, y, min and max heights in ``tiles``) large on screen
    whose grid is not the coarsest, charged their height error at the worst of their box's
    parts in view (``parts_vertical``) instead of at the whole box's nearest depth and its
    image's worst place at once (which over a box that fills the view are far apart: a tile
    under a camera looking down is nearest where its image stretches least), and drawn with
    the coarsest grid within the bound there. Their ``k`` and ``scale`` so changed. Only
    tiles whose side may cover ``SUB_MIN_SPAN`` of the view (most tiles, in the texture
    band, are smaller there: measuring them again would cost more than it saves)."""
    x, y, lo_h, hi_h = tiles
    m = np.flatnonzero(draw & (k > 0) & (px >= SUB_MIN_SPAN * min(camera.width, camera.height)))
    if m.size == 0:
        return k, scale
    ks, parts = parts_vertical(camera, z, x[m], y[m], lo_h[m], hi_h[m])
    m, parts = m[ks > 1], parts[ks > 1]
    if m.size == 0:
        return k, scale
    v = np.minimum(parts, scale[m])  # never more than the whole box's charge
    kk, _ = _grid_choice(options, np.asarray(err)[:, m], v)
    k, scale = k.copy(), scale.copy()
    k[m] = np.minimum(k[m], kk)
    scale[m] = v
    return k, scale


def _spread(ground: F64) -> F64:
    """Radians the ellipsoid's normal turns by within boxes of ground size ``ground``: from
    their centre to a corner, over the least radius of curvature."""
    out: F64 = ground * math.sqrt(0.5) / EARTH_MIN_RADIUS
    return out


def tile_far(
    camera: Camera,
    z: int,
    x: I64,
    y: I64,
    min_h: NDArray[np.floating],
    max_h: NDArray[np.floating],
) -> F64:
    """``tile_boxes``' ``dist_far`` alone: the farthest any point of each tile's box is from
    the camera (no clip distances needed), what fitting a camera's far plane asks."""
    basis, lo0, hi0, ground = _BOX_FRAMES.get(z, x, y, min_h, max_h)[:4]
    return _farthest(*_eye_box(basis, lo0, hi0, ground, camera.position))


def _eye_box(basis: F64, lo0: F64, hi0: F64, ground: F64, eye: F64) -> tuple[F64, F64]:
    """Each tile's box in its own frame with its margin, the camera at the origin: the
    lattice's box is the camera's business only through where the camera is, which moving the
    origin to the camera shifts it by (the camera's position in that frame)."""
    shift = basis @ eye
    margin = (_MARGIN * ground)[:, None]
    return lo0 - shift - margin, hi0 - shift + margin


def _farthest(lo: F64, hi: F64) -> F64:
    """The farthest any point of each camera-relative box (``_eye_box``) is from the camera."""
    far: F64 = np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi)), axis=1)
    return far


@dataclass(frozen=True, eq=False)
class _Metrics:
    """Screen metrics of N tiles of one level: what both the traversal and fallbacks need."""

    boxes: Boxes
    #: (len(grids), N) geometric error of each grid, metres.
    err: NDArray[np.float32]
    #: The most pixels a metre of height error covers in each tile's box.
    scale: F64

    @property
    def px(self) -> F64:
        """The most pixels the tile's side would cover anywhere in its box (H, as projected)."""
        return self.boxes.ground * self.boxes.horizontal


def _metrics(
    camera: Camera, z: int, x: I64, y: I64, st: TileStats, all_round: bool = False
) -> _Metrics:
    box = tile_boxes(camera, z, x, y, st.min_h, st.max_h, all_round)
    return _Metrics(box, np.asarray(st.error, dtype=np.float32), box.vertical)


def _grid_choice(
    options: SelectOptions, err: NDArray[np.float32], scale: F64
) -> tuple[I64, NDArray[np.bool_]]:
    """Coarsest grid meeting the error bound at each tile's nearest point, else the coarsest
    of the least error (the finest grid; a ladder's split rung where the rungs below it cost
    as much: ``terrain.tin_tiles.SPLIT_RUNG``); whether none meets it."""
    fits = err * scale <= options.max_sse
    anyfit = np.asarray(fits.any(axis=0), dtype=bool)
    k = np.where(anyfit, fits.argmax(axis=0), err.argmin(axis=0)).astype(np.int64)
    return k, ~anyfit


def select(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    previous: Selection | None = None,
    resident: U64 | None = None,
    texture_levels: tuple[int, ...] | None = None,
    reach: Callable[[F64, F64], NDArray[np.bool_]] | None = None,
) -> Selection:
    """The tiles to draw for ``camera``.

    ``previous`` is last frame's selection (hysteresis). ``resident`` (sorted keys) lists the
    meshes and textures that can be drawn now; None means everything can. Wanted resources that
    are not resident come back as ``loads``, and are drawn meanwhile from their nearest resident
    ancestor, so no hole opens. ``texture_levels`` gives the finest level of the terrain's own
    texture, then of each imagery layer (None: the tree's textures alone). ``reach`` (paper
    004's areas, ``lod.radii.Radii.reach``) keeps the tiles within a radius all round instead
    of those in the frustum, each at the level its distance asks for.
    """
    if camera.near is None or camera.far is None:
        raise ValueError("select needs a camera with near/far set (Camera.with_clip)")
    tsize = tree.tile_size
    zmax = tree.zmax if options.max_level is None else min(tree.zmax, options.max_level)
    own = tree.zmax if tree.texture_zmax is None else tree.texture_zmax
    levels = (own,) if texture_levels is None else tuple(int(v) for v in texture_levels)
    # below the finest level of every texture a tile splits for its geometric error alone
    ztex = min(max(levels), zmax)
    t, refined, counts = _walk(options, camera, tree, previous, reach, zmax, ztex)
    visited, culled, outside = counts
    band = _band_levels(options, tree, t, previous)
    # under imagery layers the terrain's own texture shows only where they are transparent or
    # not in yet: it is taken UNDER_LAYERS levels coarser (a sixteenth of the memory)
    under = UNDER_LAYERS if len(levels) > 1 else 0
    tex_up = _capped(band + under, t, levels[0], tree.zmin)
    layer_up = [_capped(band, t, zl, tree.zmin) for zl in levels[1:]]
    layer_keys = [
        texture_keys_zxy(t.z - up, t.x >> up, t.y >> up, j + 1) for j, up in enumerate(layer_up)
    ]
    loads = _EMPTY_U
    layer_fallbacks = 0
    if resident is not None:
        t, band, tex_up, layer_up, layer_keys, loads, layer_fallbacks = _on_resident(
            options, camera, tree, previous, resident, t, tex_up, layer_keys, levels, under
        )
    # magnified: the finest texture a tile wears is above the band (no finer one exists)
    finest_up = np.min(np.vstack([tex_up - under, *layer_up]), axis=0) if t.z.size else tex_up
    magnified = int((t.px * np.exp2(finest_up) > options.split * tsize).sum())
    # a neighbour's edge may sit up to its own error away (a bound seen at an angle allows
    # metres of error that a distance alone would not: the skirt hangs the drawn ones' own)
    skirt = t.err + _neighbour_error(t)
    return Selection(
        z=t.z,
        x=t.x,
        y=t.y,
        grid=t.k,
        keys=mesh_keys_zxy(t.z, t.x, t.y, t.k),
        texture_keys=texture_keys_zxy(t.z - tex_up, t.x >> tex_up, t.y >> tex_up),
        texture_up=tex_up,
        screen_px=t.px,
        sse=t.sse,
        dist_near=t.dist_near,
        skirt=skirt,
        fallback=t.fallback,
        refined=refined,
        loads=loads,
        visited=visited,
        culled=culled,
        outside=outside,
        magnified=magnified,
        texture_size=tsize,
        grids=tuple(tree.grids),
        band_up=band,
        layer_keys=np.array(layer_keys, np.uint64).reshape(len(levels) - 1, t.z.size),
        layer_up=np.array(layer_up, np.int64).reshape(len(levels) - 1, t.z.size),
        layer_fallbacks=layer_fallbacks,
    )


def _walk(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    previous: Selection | None,
    reach: Callable[[F64, F64], NDArray[np.bool_]] | None,
    zmax: int,
    ztex: int,
) -> tuple[_Drawn, U64, tuple[int, int, int]]:
    """The quadtree walk from the roots, a level at a time: a tile outside the view (or
    ``reach``) is culled, one too big on screen (above ``ztex``) or too rough splits (with
    hysteresis against ``previous``, and only where an on-demand tree knows its children), the
    rest are drawn at their grid. Returns the drawn tiles, the ids refined, and the tiles
    visited, culled, and left out by the region test."""
    tsize = tree.tile_size
    prev = previous.refined if previous is not None else _EMPTY_U
    drawn: list[tuple[NDArray[np.generic], ...]] = []
    refined_ids: list[U64] = []
    visited = culled = outside = 0

    view = region_view(camera) if options.region else None
    prev_grids = _previous_grids(previous.keys) if previous is not None else None
    steps = hysteresis_steps(tree)
    # an on-demand tree's test of which tiles' children it knows (a protocol's isinstance
    # is tens of microseconds: once a selection)
    ready = tree.ready if isinstance(tree, MadeOnDemand) else None
    x, y = tree.roots()
    # the grid each tile's parent would be drawn with (-1: the roots have no parent)
    parent_k = np.full(x.size, -1, np.int64)
    for z in range(tree.zmin, zmax + 1):
        if x.size == 0:
            break
        st = tree.level(z).stats(x, y)
        ok = st.exists
        x, y, parent_k = x[ok], y[ok], parent_k[ok]
        visited += int(x.size)
        if x.size == 0:
            break
        st = st.take(ok)
        m = _metrics(camera, z, x, y, st, reach is not None)
        keep = m.boxes.inside if reach is None else reach(m.boxes.centre, m.boxes.dist_near)
        culled += int((~keep).sum())
        x, y, parent_k = x[keep], y[keep], parent_k[keep]
        lo_h, hi_h = st.min_h[keep], st.max_h[keep]
        scale, err = m.scale[keep], m.err[:, keep]
        px = m.px[keep]
        k, too_rough = _grid_choice(options, err, scale)
        ids = tile_id_array(z, x, y)
        leaf = st.leaf[keep] if st.leaf is not None else None
        asks = (px > options.split * tsize, too_rough, leaf)
        refine = _refine(
            options, camera, tree, (z, zmax, ztex), (x, y, ids), asks, err, scale, prev, ready
        )
        refined_ids.append(ids[refine])
        draw = ~refine
        if reach is None:
            # a tile drawn large on screen: charged at the worst of its parts in view
            k, scale = _coarser_in_parts(
                options, camera, z, (x, y, lo_h, hi_h), err, scale, px, k, draw
            )
        # the next level's tiles keep at least their parent's resolution (a child's grid of
        # half its parent's segments is its parent's surface): a split never coarsens what is
        # drawn, so it never jumps (and geomorphing glides where it refines)
        next_parent_k = np.repeat(k[refine], 4)
        if prev_grids is not None:
            k = _keep_finer_grid(ids, k, prev_grids, steps)
        if options.hold_parent_grid:
            k = np.minimum(np.maximum(k, parent_k - steps), len(tree.grids) - 1)
        kd = k[draw]
        errd = err[kd, np.nonzero(draw)[0]].astype(np.float64)
        drawn.append(
            (
                np.full(kd.size, z),
                x[draw],
                y[draw],
                kd,
                px[draw],
                errd * scale[draw],
                m.boxes.dist_near[keep][draw],
                errd,
            )
        )
        parent_k = next_parent_k
        x = (2 * x[refine][:, None] + np.array([0, 1, 0, 1])).ravel()
        y = (2 * y[refine][:, None] + np.array([0, 0, 1, 1])).ravel()
        if view is not None and x.size >= _REGION_MIN:
            # a tile's bounds hold its children's: their slab is their parents'
            region = view.slab(float(np.min(lo_h[refine])), float(np.max(hi_h[refine])))
            if region is not None:
                hit = region.hits(z + 1, x, y)
                outside += int(x.size - hit.sum())
                x, y, parent_k = x[hit], y[hit], parent_k[hit]

    cols = [np.concatenate(c) for c in zip(*drawn, strict=True)] if drawn else [np.zeros(0)] * 8
    ints = [a.astype(np.int64) for a in cols[:4]]
    floats = [a.astype(np.float64) for a in cols[4:]]
    i, f = ints, floats
    t = _Drawn(i[0], i[1], i[2], i[3], f[0], f[1], f[2], f[3], np.zeros_like(i[0]))
    refined = np.unique(np.concatenate(refined_ids)) if refined_ids else _EMPTY_U
    return t, refined, (visited, culled, outside)


def _refine(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    levels: tuple[int, int, int],
    tiles: tuple[I64, I64, U64],
    asks: tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_] | None],
    err: NDArray[np.floating],
    scale: F64,
    prev: U64,
    ready: Callable[[int, I64, I64], NDArray[np.bool_]] | None,
) -> NDArray[np.bool_]:
    """Which tiles of level z (of zmax, textures to ztex) split: too ``big`` on screen above
    the finest texture level, or ``too_rough`` for their finest grid, never a ``leaf`` (nothing
    finer was built there); one split last frame (``prev``) stays split until it is well
    under the bound and its children's textures would not be magnified; on a tree made on
    demand (its ``ready``; None: another tree), only where its children's statistics are
    known."""
    z, zmax, ztex = levels
    x, y, ids = tiles
    big, too_rough, leaf = asks
    can = z < zmax
    refine = can & ((big & (z < ztex)) | too_rough)
    if leaf is not None:
        refine &= ~leaf  # nothing finer was built there
    if can and prev.size:
        was = _member(ids, prev) & ~refine
        if was.any():
            rough = err[-1, was] * scale[was] > options.sse_merge * options.max_sse
            hold = np.zeros(rough.shape, dtype=bool)
            if z < ztex:
                hold = _children_hold(options, camera, tree, z, x[was], y[was])
            refine[was] = rough | hold
    if ready is not None and can and refine.any():
        # a tree made on demand splits where its children's statistics are known (the rest
        # are asked for and drawn whole meanwhile, as a tile whose children have not loaded)
        idx = np.flatnonzero(refine)
        refine[idx] = ready(z, x[idx], y[idx])
    return refine


def _on_resident(
    options: SelectOptions,
    camera: Camera,
    tree: TreeLike,
    previous: Selection | None,
    resident: U64,
    t: _Drawn,
    tex_up: I64,
    layer_keys: list[U64],
    levels: tuple[int, ...],
    under: int,
) -> tuple[_Drawn, I64, I64, list[I64], list[U64], U64, int]:
    """What ``resident`` lets the frame draw now: the loads its tiles want, each tile drawn
    from its nearest resident ancestor meanwhile, and textures from the nearest resident
    level (an imagery layer none of whose levels is resident is not drawn). Returns the
    drawn tiles, their band, texture levels up, each layer's levels up and keys, the loads,
    and the layer tiles drawn from an ancestor or not at all."""
    # what the wanted tiles need; then what stands in for it while it loads
    wanted = [k[~_member(k, resident)] for k in layer_keys]
    loads = _missing(resident, t, tex_up)
    t = _fall_back(camera, tree, resident, t)
    band = _band_levels(options, tree, t, previous)
    own_up = _capped(band + under, t, levels[0], tree.zmin)
    tex_up, own_keys, ok = _texture_fall_back(tree.zmin, resident, t, own_up, 0)
    # a tile with no texture of its own resident anywhere above it must have it loaded
    unresolved = np.unique(own_keys[~ok])
    layer_up, layer_keys = [], []
    layer_fallbacks = 0
    for j, zl in enumerate(levels[1:]):
        want_up = _capped(band, t, zl, tree.zmin)
        got_up, got, ok = _texture_fall_back(tree.zmin, resident, t, want_up, j + 1)
        # an imagery layer is never waited for: where none is resident it is not drawn
        got[~ok] = NO_TEXTURE
        layer_up.append(got_up)
        layer_keys.append(got)
        layer_fallbacks += int(((got_up > want_up) | ~ok).sum())
    extra = np.concatenate([unresolved, *wanted])
    loads = _order_loads(np.concatenate([loads, extra[~_member(extra, loads)]]))
    return t, band, tex_up, layer_up, layer_keys, loads, layer_fallbacks


@dataclass(frozen=True, eq=False)
class _Drawn:
    """Columns of the drawn tiles, as the traversal and the fallback pass them along."""

    z: I64
    x: I64
    y: I64
    k: I64
    px: F64
    sse: F64
    dist_near: F64
    err: F64
    fallback: I64

    def take(self, m: NDArray[np.bool_] | I64) -> _Drawn:
        return _Drawn(*(getattr(self, f)[m] for f in _DRAWN_FIELDS))

    @staticmethod
    def concat(a: _Drawn, b: _Drawn) -> _Drawn:
        return _Drawn(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in _DRAWN_FIELDS))


_DRAWN_FIELDS = tuple(_Drawn.__dataclass_fields__)


def _band_levels(
    options: SelectOptions, tree: TreeLike, t: _Drawn, previous: Selection | None
) -> I64:
    """Levels up to each tile's texture for the pixel band: the most that keep its texels
    within split / ``SLOPE_ROOM`` pixels where the tile is largest on screen (so where it is
    farther or seen edge-on they stay above ``merge`` as far as one texture can, and a slope
    facing the camera, which the box does not measure, has room under ``split``), before any
    texture's finest level caps them.

    Last frame's choice stands while it is still inside the band, so textures do not flicker.
    """
    low = options.merge * tree.tile_size
    high = options.split / SLOPE_ROOM * tree.tile_size
    # largest k >= 0 with px·2^k <= high (px is positive for every drawn tile)
    up = np.floor(np.log2(high / np.maximum(t.px, 1e-300))).clip(min=0.0).astype(np.int64)
    if previous is None or previous.count == 0 or previous.band_up is None:
        return up
    pid = tile_id_array(previous.z, previous.x, previous.y)
    order = np.argsort(pid)
    pid, pup = pid[order], previous.band_up[order]
    ids = tile_id_array(t.z, t.x, t.y)
    pos = np.clip(np.searchsorted(pid, ids), 0, pid.size - 1)
    hit = pid[pos] == ids
    before = pup[pos]
    ratio = t.px * np.exp2(before)
    stays = hit & (ratio >= low) & (ratio <= options.split * tree.tile_size)
    out: I64 = np.where(stays, before, up)
    return out


def _neighbour_error(t: _Drawn) -> F64:
    """Per drawn tile, the largest error (metres) of the drawn tiles whose squares touch it, at
    any level (a coarser neighbour found as its covering ancestor, finer ones by the largest
    error under each of the tile's eight neighbours): one numpy pass per pair of levels."""
    out = np.zeros(t.z.size)
    if not t.z.size:
        return out
    levels = np.unique(t.z)
    ids = tile_id_array(t.z, t.x, t.y)
    # per level m: the drawn tiles of level m, sorted (coarser neighbours are found there), and
    # the largest error of the drawn tiles at or under each tile of level m (finer ones)
    at: dict[int, tuple[U64, F64]] = {}
    under: dict[int, tuple[U64, F64]] = {}
    for m in levels.tolist():
        mine = t.z == m
        order = np.argsort(ids[mine])
        at[m] = (ids[mine][order], t.err[mine][order])
        deep = t.z >= m
        s = t.z[deep] - m
        anc = tile_id_array(np.full(s.size, m), t.x[deep] >> s, t.y[deep] >> s)
        uid, inv = np.unique(anc, return_inverse=True)
        worst = np.zeros(uid.size)
        np.maximum.at(worst, inv, t.err[deep])
        under[m] = (uid, worst)
    step = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy])
    for lvl in levels.tolist():
        mine = np.flatnonzero(t.z == lvl)
        nx = (t.x[mine, None] + step[:, 0]) % (1 << lvl)
        ny = t.y[mine, None] + step[:, 1]
        ok = (ny >= 0) & (ny < 1 << lvl)
        nx, ny = nx[ok], ny[ok]
        row = np.broadcast_to(np.arange(mine.size)[:, None], ok.shape)[ok]
        best = np.zeros(row.size)
        for m in levels[levels <= lvl].tolist():
            s = lvl - m
            uid, worst = under[m] if m == lvl else at[m]
            want = tile_id_array(np.full(nx.size, m), nx >> s, ny >> s)
            pos = np.clip(np.searchsorted(uid, want), 0, max(uid.size - 1, 0))
            hit = uid[pos] == want if uid.size else np.zeros(want.size, bool)
            best = np.where(hit, np.maximum(best, worst[pos]), best)
        agg = np.zeros(mine.size)
        np.maximum.at(agg, row, best)
        out[mine] = agg
    return out


def _capped(band: I64, t: _Drawn, finest: int, zmin: int) -> I64:
    """The band's levels up for a texture whose finest level is ``finest``: none below it, none
    above the roots."""
    out: I64 = np.minimum(np.maximum(band, t.z - finest), t.z - zmin)
    return out


def _previous_grids(prev_keys: U64) -> tuple[U64, I64]:
    """Last frame's drawn tiles (sorted ids) and each one's grid, for ``_keep_finer_grid``:
    worked out once a selection, not per level."""
    pk = np.sort(prev_keys)
    return tile_id_of_array(pk), grid_of_array(pk).astype(np.int64)


def _keep_finer_grid(ids: U64, k: I64, prev: tuple[U64, I64], steps: int = 1) -> I64:
    """Grid hysteresis: a tile keeps last frame's grid while the one it needs is at most
    ``steps`` grids coarser (a finer grid only lowers the error), so a camera that hovers does
    not reload meshes. ``prev``: ``_previous_grids`` of last frame's keys."""
    pid, grids = prev
    if pid.size == 0:
        return k
    pos = np.minimum(np.searchsorted(pid, ids), pid.size - 1)
    kprev = grids[pos]
    return np.where((pid[pos] == ids) & (kprev > k) & (kprev <= k + steps), kprev, k)


def hysteresis_steps(tree: TreeLike) -> int:
    """How many of ``tree``'s grids a tile holds on to (``_keep_finer_grid``) and a split
    keeps of its parent's (``SelectOptions.hold_parent_grid``): one of the regular grids,
    which halve their segments a step; a tree's ``hysteresis_steps`` where its grids are closer
    (``terrain.tin_tiles.ErrorLadder``'s rungs)."""
    return int(getattr(tree, "hysteresis_steps", 1))


def _member(a: U64, sorted_b: U64) -> NDArray[np.bool_]:
    """a ∈ b for a sorted b, vectorised."""
    if sorted_b.size == 0:
        return np.zeros(a.shape, dtype=bool)
    pos = np.clip(np.searchsorted(sorted_b, a), 0, sorted_b.size - 1)
    found: NDArray[np.bool_] = sorted_b[pos] == a
    return found


def _children_hold(
    options: SelectOptions, camera: Camera, tree: TreeLike, z: int, x: I64, y: I64
) -> NDArray[np.bool_]:
    """For tiles split last frame: does every visible child still cover merge·T pixels?"""
    cx = (2 * x[:, None] + np.array([0, 1, 0, 1])).ravel()
    cy = (2 * y[:, None] + np.array([0, 0, 1, 1])).ravel()
    st = tree.level(z + 1).stats(cx, cy)
    ok = st.exists
    m = _metrics(camera, z + 1, cx, cy, st)
    # absent or culled children do not hold their parent back
    small = ok & m.boxes.inside & (m.px < options.merge * tree.tile_size)
    held = ~np.asarray(small.reshape(-1, 4).any(axis=1), dtype=bool)
    return held


def _nearest_resident(
    z: I64, x: I64, y: I64, have: U64, zmin: int, first: int | I64
) -> tuple[NDArray[np.bool_], I64]:
    """For each tile, the fewest levels up, ``first`` or more, to an ancestor (or itself, at 0)
    whose id is in the sorted ``have``; (found, steps). One numpy pass per level, not per tile."""
    found = np.zeros(z.size, dtype=bool)
    steps = np.zeros(z.size, dtype=np.int64)
    first = np.broadcast_to(np.asarray(first, dtype=np.int64), z.shape)
    top = int(z.max()) - zmin if z.size else -1
    for s in range(int(first.min()) if z.size else 0, top + 1):
        todo = ~found & (z - s >= zmin) & (s >= first)
        if not todo.any():
            break
        i = np.nonzero(todo)[0]
        hit = _member(tile_id_array(z[i] - s, x[i] >> s, y[i] >> s), have)
        found[i[hit]] = True
        steps[i[hit]] = s
    return found, steps


def _missing(resident: U64, t: _Drawn, tex_up: I64) -> U64:
    """The meshes and textures the wanted tiles need that are not resident, most urgent first."""
    mesh = mesh_keys_zxy(t.z, t.x, t.y, t.k)
    tex = texture_keys_zxy(t.z - tex_up, t.x >> tex_up, t.y >> tex_up)
    keys = np.concatenate([tex, mesh])
    dist = np.concatenate([t.dist_near, t.dist_near])
    m = ~_member(keys, resident)
    return _order_loads(keys[m], dist[m])


def _fall_back(camera: Camera, tree: TreeLike, resident: U64, t: _Drawn) -> _Drawn:
    """Draw each tile whose mesh is not resident from the nearest resident mesh: the same tile at
    another grid, or its nearest ancestor (no holes)."""
    keys = mesh_keys_zxy(t.z, t.x, t.y, t.k)
    present = _member(keys, resident)
    if present.all():
        return t
    meshes = resident[~is_texture_array(resident)]
    mesh_ids = np.unique(tile_id_of_array(meshes))
    miss = t.take(~present)
    found, up = _nearest_resident(miss.z, miss.x, miss.y, mesh_ids, tree.zmin, 0)
    # tiles with no resident mesh anywhere above them stay as wanted: the caller must load them
    up = up[found]
    anc = tile_id_array(miss.z[found] - up, miss.x[found] >> up, miss.y[found] >> up)
    fid = np.unique(anc)
    # how many levels each fallback stands in for: the deepest of the tiles it replaces
    depth = np.zeros(fid.size, dtype=np.int64)
    np.maximum.at(depth, np.searchsorted(fid, anc), up)
    # drop wanted tiles, present or not, that a fallback ancestor already covers
    covered, _ = _nearest_resident(t.z, t.x, t.y, fid, tree.zmin, 1)
    stays = present.copy()
    stays[~present] = ~found
    keep = stays & ~covered
    # each fallback tile is drawn with its finest resident grid
    mk = np.sort(meshes)
    last = np.searchsorted(tile_id_of_array(mk), fid, side="right") - 1
    fk = grid_of_array(mk[last])
    uz, ux, uy = tile_from_id_array(fid)
    back = _metrics_many(camera, tree, uz, ux, uy, fk, depth)
    return _Drawn.concat(t.take(keep), back)


def _metrics_many(
    camera: Camera, tree: TreeLike, z: I64, x: I64, y: I64, k: I64, fallback: I64
) -> _Drawn:
    """Screen metrics of tiles of mixed levels (the few fallback tiles), one numpy call a level."""
    n = z.size
    px, sse, dn, err = (np.zeros(n) for _ in range(4))
    for lvl in np.unique(z):
        m = z == lvl
        st = tree.level(int(lvl)).stats(x[m], y[m])
        mt = _metrics(camera, int(lvl), x[m], y[m], st)
        e = mt.err[k[m], np.arange(int(m.sum()))].astype(np.float64)
        px[m], sse[m] = mt.px, e * mt.scale
        dn[m], err[m] = mt.boxes.dist_near, e
    return _Drawn(z, x, y, k, px, sse, dn, err, fallback)


def _texture_fall_back(
    zmin: int, resident: U64, t: _Drawn, up: I64, layer: int
) -> tuple[I64, U64, NDArray[np.bool_]]:
    """Each drawn tile's nearest resident texture of ``layer`` (0: the terrain's own) at or
    above the level it wants: (levels up, its keys, whether one is resident). A tile with none
    keeps the level it wants."""
    want = texture_keys_zxy(t.z - up, t.x >> up, t.y >> up, layer)
    m = ~_member(want, resident)
    if not m.any():
        return up, want, np.ones(want.size, dtype=bool)
    mine = resident[is_texture_array(resident)]
    ids = np.sort(tile_id_of_array(mine[layer_of_array(mine) == layer]))
    # only from the wanted level up: a texture finer than the band asks for is not used
    found, steps = _nearest_resident(t.z[m], t.x[m], t.y[m], ids, zmin, up[m])
    i = np.nonzero(m)[0][found]
    new = up.copy()
    new[i] = steps[found]
    keys = want.copy()
    keys[i] = texture_keys_zxy(t.z[i] - new[i], t.x[i] >> new[i], t.y[i] >> new[i], layer)
    ok = ~m
    ok[i] = True
    return new, keys, ok


def _order_loads(keys: U64, dist: F64 | None = None) -> U64:
    """Keys once each, coarse levels first, then nearest first (then in the order given)."""
    z, _, _ = tile_from_id_array(tile_id_of_array(keys))
    d = np.zeros(keys.size) if dist is None else dist
    order = np.lexsort((d, z))
    ordered = keys[order]
    _, first = np.unique(ordered, return_index=True)
    result: U64 = ordered[np.sort(first)]
    return result
