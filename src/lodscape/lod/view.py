"""The terrain's view of one frame, with no IO, no GL and no threads (cesium-native's
``Tileset::updateView`` and its ``ViewUpdateResult``).

``TerrainView.update(camera, resident)`` selects once and returns a ``FramePlan``: the render
list, what the frame cannot be drawn without (``required``), what it would like loaded
(``loads``, most urgent first) and the keys the draw list uses (which the GPU stage must not
evict). Two policies share it:

- **blocking** (one-shot renders): every wanted tile is drawn as wanted, and all of its resources
  are required;
- **streaming**: only what is resident is drawn; a wanted tile that is not stands in as its
  nearest resident ancestor. The roots are always taken as drawable, so no tile is ever left
  without a stand-in, and a root that is drawn but not resident is required (the one stall, at
  the start).

Back-facing patches (paper 003) are dropped by ``facing`` once the drawn meshes' normal cones are
known, that is once they are resident.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import CameraError
from lodscape.geo.cones import CONE_SIZE
from lodscape.geo.frames import WGS84_A, geodetic_to_ecef
from lodscape.geo.keys import mesh_keys_zxy, texture_keys_zxy
from lodscape.geo.tiles import Bbox, bounds_array, merc_to_lonlat, tile_id_array
from lodscape.lod.camera import Camera
from lodscape.lod.cull import backfacing
from lodscape.lod.radii import Radii
from lodscape.lod.select import (
    NO_TEXTURE,
    LearnsFromLoads,
    MadeOnDemand,
    Selection,
    SelectOptions,
    TreeLike,
    select,
    tile_far,
)

#: Frames a tile takes to glide from the surface it replaced to its own (a third of a second
#: at 30 frames a second).
MORPH_FRAMES = 10

__all__ = ["MORPH_FRAMES", "DrawItem", "FramePlan", "MeshInfo", "TerrainView", "draw_items"]

U64 = NDArray[np.uint64]
I64 = NDArray[np.int64]
F64 = NDArray[np.float64]


@dataclass(frozen=True)
class DrawItem:
    """One tile in a frame: an uploaded mesh, the uploaded texture it wears, and how far its
    skirts hang this frame."""

    key: int
    texture: int
    #: Metres to lower skirt vertices (0 hides them inside the tile's edge).
    skirt: float = 0.0
    #: The window of the texture the tile covers: offset u, offset v, scale (1: all of it).
    uv: tuple[float, float, float] = (0.0, 0.0, 1.0)
    #: Runs of triangles to draw, (first, count); None: the whole mesh.
    runs: tuple[tuple[int, int], ...] | None = None
    #: Screen-space error (pixels) the GPU terrain mode's tessellation may add to this tile's.
    sse_budget: float = 1.0
    #: Per imagery layer, bottom to top: the key of its tile the tile wears (-1: none) and the
    #: window of it the tile covers, as ``uv``.
    layers: tuple[tuple[int, tuple[float, float, float]], ...] = ()
    #: Geomorphing: how far (0..1) the tile's vertices still lie on the surface it replaced
    #: (its grid of half the segments: its parent's, or its own coarser grid); 0: its own.
    morph: float = 0.0


@dataclass(frozen=True, eq=False)
class MeshInfo:
    """What the view keeps of a resident mesh: its centre (ECEF), its patches' normal cones
    ((P, 10), ``geo.cones``; None: no cone) and its triangles, skirts included."""

    center: F64
    cone: F64 | None
    triangles: int


@dataclass(frozen=True, eq=False)
class FramePlan:
    """One frame's decisions (``TerrainView.update``)."""

    #: The camera with its clip distances fitted to the terrain.
    camera: Camera
    selection: Selection
    #: The draw list, before back-facing patches are dropped.
    items: list[DrawItem]
    #: Keys the frame cannot be drawn without, that are not resident.
    required: list[int]
    #: Keys wanted and not resident, most urgent first (coarse levels, then near tiles).
    loads: U64
    #: Every key the draw list uses.
    drawn: frozenset[int]
    select_ms: float


#: Degrees of sky an overview keeps above the horizon, and of margin around the data.
SKY_DEG = 4.0
MARGIN_DEG = 2.0


def horizon_view(
    extent: float, lo: float, hi: float, aspect: float, fov_y: float
) -> tuple[float, float, float] | None:
    """(distance back from the data's centre, altitude, pitch) of a camera looking north over
    square data ``extent`` metres across (heights ``lo``..``hi``) that sees all of it and the
    horizon with ``SKY_DEG`` of sky above, on a viewport of ``aspect``; None where no such
    camera is (a field of view too narrow to hold both)."""
    half_v = fov_y / 2.0
    half_h = math.degrees(math.atan(math.tan(math.radians(half_v)) * aspect))
    for k in range(60):
        back = extent * (0.55 + 0.05 * k)
        near, far = back - extent / 2.0, back + extent / 2.0
        # as high as keeps the data's near edge just above the picture's bottom (the data fills
        # the picture under the horizon); the horizon's dip follows the height, so twice
        alt = hi + 0.45 * back
        for _ in range(2):
            dip = math.degrees(math.acos(WGS84_A / (WGS84_A + max(alt, 0.0))))
            pitch = SKY_DEG - dip - half_v
            bottom = pitch - half_v  # the lowest ray, below the horizontal
            alt = lo + near * math.tan(math.radians(min(-bottom - MARGIN_DEG, 80.0)))
        if alt <= hi or bottom < -89.0:
            continue
        # the corners, in the camera's frame: their bearing over their depth along the view
        depth = near * math.cos(math.radians(pitch)) + (hi - alt) * math.sin(math.radians(pitch))
        if depth <= 0.0:
            continue
        if math.degrees(math.atan2(extent / 2.0, depth)) > half_h - MARGIN_DEG:
            continue
        # the far edge must lie below the horizon's sky band (it does, seen from above it)
        if math.degrees(math.atan2(alt - hi, far)) < dip:
            continue
        return back, alt, pitch
    return None


def follows(before: Camera, camera: Camera, scale: float) -> bool:
    """Whether ``camera`` is the next frame of one motion after ``before``, so that the
    hysteresis carries over: the same viewport and field of view, the eye moved at most half
    of ``scale`` (the metres that set the scene's size around the eye: its height above the
    ground, the smaller of the two frames') and the view turned at most half the field of view.
    Anything else is a cut: a picture of an unrelated view is selected as if it were the first,
    the same whatever was rendered before it."""
    if (before.width, before.height, before.fov_y) != (camera.width, camera.height, camera.fov_y):
        return False
    if float(np.linalg.norm(camera.position - before.position)) > 0.5 * max(scale, 1.0):
        return False
    turn = float(np.clip(before.forward @ camera.forward, -1.0, 1.0))
    return math.degrees(math.acos(turn)) <= camera.fov_y / 2.0


class TerrainView:
    """Selection and culling of one terrain's tile tree, frame after frame (it remembers the
    last selection, for hysteresis between the frames of one motion: ``follows``)."""

    def __init__(
        self,
        tree: TreeLike,
        options: SelectOptions | None = None,
        *,
        cull_backfacing: bool = True,
        texture_levels: tuple[int, ...] | None = None,
    ) -> None:
        self.tree = tree
        self.options = options or SelectOptions()
        self.cull_backfacing = cull_backfacing
        #: Geomorph between levels (``DrawItem.morph``): no vertex jumps where a tile splits.
        self.morph = True
        #: The last frame's meshes (their infos) and their patches' cones (``facing``).
        self._cones_of: tuple[list[MeshInfo | None], tuple[F64, F64, NDArray[np.int64]]] = (
            [],
            (np.zeros((0, CONE_SIZE)), np.zeros((0, 3)), np.zeros(0, np.int64)),
        )
        #: Frames a tile takes to glide from the surface it replaced to its own.
        self.morph_frames = MORPH_FRAMES
        #: Last frame's drawn tiles: sorted ids, their grids and how far each still morphed.
        self._shown: tuple[U64, I64, F64] = (
            np.zeros(0, np.uint64),
            np.zeros(0, np.int64),
            np.zeros(0),
        )
        #: The finest level of the terrain's own texture, then of each imagery layer.
        self.texture_levels = texture_levels
        #: Last frame's selection (hysteresis), None before the first.
        self.previous: Selection | None = None
        #: The camera and the options ``previous`` was selected with, and that frame's scale
        #: (``_scale``).
        self._previous_of: tuple[Camera, SelectOptions, float] | None = None
        #: The last camera ``fit`` made and its height above the ground (or the data's top).
        self._fitted: tuple[Camera, float] | None = None
        #: Frames planned by ``update`` so far (one selection each, or the last one again).
        self.selections = 0
        #: Of those, frames whose plan was the last one (``update``: nothing it is made from
        #: had changed, and it had already made itself again).
        self.reused = 0
        #: What the last plan was made from (``_inputs`` and the resident keys), and the
        #: plan while a frame of the same inputs makes it again.
        self._last_inputs: tuple[tuple[Any, ...] | None, U64] = (None, np.zeros(0, np.uint64))
        self._steady: FramePlan | None = None
        x, y = tree.roots()
        z = np.full(x.size, tree.zmin)
        self._roots = np.sort(
            np.concatenate([mesh_keys_zxy(z, x, y, np.zeros_like(x)), texture_keys_zxy(z, x, y)])
        )

    # --- the camera ----------------------------------------------------------------------------

    def fit(self, camera: Camera, ground: float | None) -> Camera:
        """``camera`` with clip distances fitted to the terrain (``ground``: its height under the
        camera, None outside the data); refuses a camera under the ground."""
        lo, hi = self.tree.height_range
        if ground is not None and camera.alt <= ground:
            raise CameraError(
                f"camera is under the ground: alt {camera.alt:.1f} m but the terrain at "
                f"{camera.lon:.5f}, {camera.lat:.5f} is {ground:.1f} m"
            )
        clearance = camera.alt - (ground if ground is not None else hi)
        near = camera.near or min(max(0.1 * clearance, 0.5), 1e5)
        if camera.far is not None:
            fitted = camera.with_clip(near, camera.far)
            self._fitted = (fitted, clearance)
            return fitted
        x, y = self.tree.roots()
        st = self.tree.level(self.tree.zmin).stats(x, y)
        reach = tile_far(camera, self.tree.zmin, x, y, st.min_h, st.max_h)
        # everything in the data lies within its root boxes; the horizon bounds it on a planet
        # tangent lengths sqrt(h(2R + h)): exact from orbit too, where h is not small against R
        up, rise = max(camera.alt - lo, 1.0), max(hi - lo, 1.0)
        horizon = math.sqrt(up * (2.0 * WGS84_A + up)) + math.sqrt(rise * (2.0 * WGS84_A + rise))
        far = max(min(float(reach.max()), horizon), near * 10.0) * 1.01
        fitted = camera.with_clip(near, far)
        self._fitted = (fitted, clearance)
        return fitted

    def overview(self, b: Bbox, width: int, height: int, fov_y: float) -> Camera:
        """A camera south of the data (``b``, EPSG:3857) looking north over it, seeing all of it
        and, above it, the horizon and a band of sky (``horizon_view``)."""
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        lon, lat = (w + e) / 2.0, (s + n) / 2.0
        lo, hi = self.tree.height_range
        extent = max(b.right - b.left, b.top - b.bottom) * math.cos(math.radians(lat))
        view = horizon_view(extent, lo, hi, width / height, fov_y)
        back = view[0] if view is not None else 0.75 * extent
        cam_lat = lat - math.degrees(back / WGS84_A)
        south = cam_lat < -89.0
        if south:
            # data near the south pole (or a continent's width): look at it from the north
            cam_lat = lat + math.degrees(back / WGS84_A)
        if cam_lat > 89.0 or back > 0.25 * math.pi * WGS84_A:
            # a cap or the whole globe: straight down from above its centre, far enough out
            lat = min(max(lat, -89.0), 89.0)
            alt = min(hi + extent / math.tan(math.radians(fov_y) / 2.0), 3.0e7)
            return Camera(lon, lat, alt, pitch=-90.0, fov_y=fov_y, width=width, height=height)
        if view is None:
            return Camera.looking_at(
                lon, cam_lat, hi + 0.55 * extent, (lon, lat, (lo + hi) / 2.0),
                fov_y=fov_y, width=width, height=height,
            )  # fmt: skip
        _, alt, pitch = view
        heading = 180.0 if south else 0.0
        return Camera(
            lon, cam_lat, alt, heading=heading, pitch=pitch, fov_y=fov_y, width=width, height=height
        )

    # --- frames --------------------------------------------------------------------------------

    def update(self, camera: Camera, resident: U64, *, blocking: bool = False) -> FramePlan:
        """This frame's plan for a fitted ``camera`` (``fit``) given the sorted ``resident`` keys:
        one selection. Remembered as the previous frame's."""
        t0 = time.perf_counter()
        levels = self.texture_levels
        options = self.select_options
        inputs = self._inputs(camera, options, blocking)
        steady, (last, last_resident) = self._steady, self._last_inputs
        same = inputs is not None and inputs == last and np.array_equal(resident, last_resident)
        if steady is not None and same:
            # a still camera over a still terrain: GeoMipTerrain's update is as idle there
            self.selections += 1
            self.reused += 1
            return replace(steady, select_ms=(time.perf_counter() - t0) * 1e3)
        before = self.history(camera)
        if blocking:
            sel = select(options, camera, self.tree, before, texture_levels=levels)
        else:
            drawable = np.union1d(resident, self._roots)
            sel = select(options, camera, self.tree, before, drawable, levels)
        self.selections += 1
        self.previous = sel
        self._previous_of = (camera, options, self._scale(camera, sel))
        worn = sel.layer_keys[sel.layer_keys != NO_TEXTURE]
        drawn = np.union1d(np.union1d(sel.keys, sel.texture_keys), worn)
        absent = _absent(drawn, resident)
        # blocking: what is drawn and absent is loaded now; streaming: the selection's loads
        loads = absent if blocking else sel.loads
        items = draw_items(sel, self.options.max_sse, self._morphs(sel) if self.morph else None)
        ms = (time.perf_counter() - t0) * 1e3
        required = [int(k) for k in absent]
        plan = FramePlan(camera, sel, items, required, loads, frozenset(drawn.tolist()), ms)
        # the selection is a pure function of its inputs and the one before: made again from
        # the same inputs, and the same as the one before, it is what every next frame of
        # them would make
        fixed = same and before is not None and _same_selection(before, sel)
        self._steady = plan if fixed else None
        self._last_inputs = (inputs, resident.copy())
        return plan

    def _inputs(
        self, camera: Camera, options: SelectOptions, blocking: bool
    ) -> tuple[Any, ...] | None:
        """What a frame's plan is made from besides the resident keys and the last selection,
        or None where a frame of the same may plan otherwise: geomorphing frames (their tiles
        glide a step a frame), a tree made on demand that does not wait (its statistics come
        between frames). A tree that learns from loads counts its lessons (``epoch``)."""
        tree = self.tree
        if self.morph or (isinstance(tree, MadeOnDemand) and not blocking):
            return None
        epoch = tree.epoch if isinstance(tree, LearnsFromLoads) else None
        return (camera, options, self.texture_levels, blocking, epoch)

    def history(self, camera: Camera) -> Selection | None:
        """The last selection, where a frame of (fitted) ``camera`` follows it in one motion
        with the same options (``follows``); None after a cut: no hysteresis from an unrelated
        view, another bound or a selection set aside (``previous`` set by hand)."""
        prev, of = self.previous, self._previous_of
        if prev is None or of is None or of[1] != self.select_options:
            return None
        scale = min(of[2], self._scale(camera, prev))
        return prev if follows(of[0], camera, scale) else None

    def _scale(self, camera: Camera, drawn: Selection) -> float:
        """The metres that set the scene's size around ``camera``: its height above the ground
        where ``fit`` made it (the ground under a flight's eye is its nearest surface, however
        rough), else the distance to the nearest tile ``drawn``."""
        fitted = self._fitted
        if fitted is not None and fitted[0] is camera and fitted[1] > 0.0:
            return fitted[1]
        return float(drawn.dist_near.min()) if drawn.count else 0.0

    @property
    def select_options(self) -> SelectOptions:
        """The options a frame is selected with: a split holds its parent's resolution
        (``SelectOptions.hold_parent_grid``) where the frames geomorph, unless said."""
        if self.options.hold_parent_grid is not None:
            return self.options
        return replace(self.options, hold_parent_grid=self.morph)

    def _morphs(self, sel: Selection) -> F64:
        """Per drawn tile, how far it still shows the surface it replaced (geomorphing over
        ``morph_frames`` frames, from the frame it first appears):

        - a tile drawn last frame with the same grid glides on by 1/morph_frames;
        - one that replaces its own coarser grid (one step), or its parent drawn with the same
          grid (whose surface over the tile is the tile's grid of half the segments), starts
          at 1: it shows exactly what was there;
        - one whose parent was drawn with the next finer grid (the tile's own surface, and the
          parent's next coarser grid the tile's of half the segments) takes on where the
          parent's glide was (a tile splits rather than take its finest grid,
          ``terrain.tin_tiles.SplitBeforeFinest``: often while it still glides onto the grid
          before; a jump of 1.4 px at a 4 px bound on ``bench_morph``'s fBm without this);
        - anything else (a merge; the first frame) starts at 0.

        The offsets a mesh moves by (``TileMesh.morph``) lead onto its grid of half the
        segments, so the picture never jumps where a tile splits or refines its grid; a merge
        (moving away) still does."""
        ids = tile_id_array(sel.z, sel.x, sel.y)
        k = np.zeros(sel.count)
        prev_ids, prev_grid, prev_k = self._shown
        if prev_ids.size and sel.count:
            step = 1.0 / max(self.morph_frames, 1)
            i = np.minimum(np.searchsorted(prev_ids, ids), prev_ids.size - 1)
            same_tile = prev_ids[i] == ids
            pg = np.where(same_tile, prev_grid[i], -1)
            kept = same_tile & (pg == sel.grid)
            k[kept] = np.maximum(prev_k[i][kept] - step, 0.0)
            finer_grid = same_tile & (pg == sel.grid - 1)
            parent = tile_id_array(sel.z - 1, sel.x >> 1, sel.y >> 1)
            j = np.minimum(np.searchsorted(prev_ids, parent), prev_ids.size - 1)
            split = ~same_tile & (prev_ids[j] == parent) & (prev_grid[j] == sel.grid)
            k[finer_grid | split] = 1.0 - step
            # its parent drawn with the next finer grid, still gliding onto it: the tile's grid
            # and its grid of half the segments are that glide's two ends, so it glides on
            glide = ~same_tile & (prev_ids[j] == parent) & (prev_grid[j] == sel.grid + 1)
            k[glide] = np.maximum(prev_k[j][glide] - step, 0.0)
        order = np.argsort(ids)
        self._shown = (ids[order], sel.grid[order], k[order])
        return k

    def predict(self, camera: Camera) -> list[int]:
        """Every key a selection from ``camera`` (fitted) would draw, textures first (what a
        prefetch asks for); not remembered, so it leaves the next frame's hysteresis alone."""
        sel = select(self.select_options, camera, self.tree, texture_levels=self.texture_levels)
        return [
            int(k) for k in np.concatenate([sel.texture_keys, sel.layer_keys.ravel(), sel.keys])
        ]

    def areas(self, camera: Camera, radii: Radii) -> tuple[list[int], list[int], dict[str, int]]:
        """Paper 004's areas for a fitted ``camera``: every chunk (a tile at the level its
        distance asks for) within the cache radius all round, classified by the radii. Returns
        the memory area's keys and the cache area's (nearest first in units of the radius towards
        them, so ahead before behind; textures before meshes)
        and how many chunks each area holds."""
        sel = select(
            self.select_options,
            camera,
            self.tree,
            texture_levels=self.texture_levels,
            reach=radii.reach("cache"),
        )
        if sel.count == 0:
            return [], [], {"area_memory": 0, "area_cache": 0}
        left, bottom, right, top = bounds_array(sel.z, sel.x, sel.y)
        lon, lat = merc_to_lonlat((left + right) / 2.0, (bottom + top) / 2.0)
        centre = geodetic_to_ecef(lon, lat, 0.0) - camera.position
        area, urgency = radii.rank(centre, sel.dist_near)
        order = np.argsort(urgency, kind="stable")
        out: list[list[int]] = []
        seen: set[int] = set()
        for a in (0, 1):
            pick = order[area[order] == a]
            keys = np.concatenate(
                [sel.texture_keys[pick], sel.layer_keys[:, pick].ravel(), sel.keys[pick]]
            )
            keys = keys[keys != NO_TEXTURE]
            # a texture several chunks wear (an ancestor's, below its level) once, in the
            # nearer area: a key is in one area only
            _, first = np.unique(keys, return_index=True)
            ordered = [int(k) for k in keys[np.sort(first)]]
            out.append([k for k in ordered if k not in seen])
            seen.update(ordered)
        counts = {"area_memory": int((area == 0).sum()), "area_cache": int((area == 1).sum())}
        return out[0], out[1], counts

    def facing(
        self,
        plan: FramePlan,
        meshes: Mapping[int, MeshInfo],
        whole_tiles: bool = False,
    ) -> tuple[list[DrawItem], int, int]:
        """The draw list less the patches facing away from the camera (paper 003): a tile with
        none left is dropped, one with some left draws the runs of its other patches (and its
        skirts); with ``whole_tiles`` (the GPU terrain mode) a tile is kept unless all of it
        faces away. Returns the list, the patches dropped and the triangles they held."""
        items = plan.items
        if not self.cull_backfacing or not items:
            return items, 0, 0
        infos = [meshes.get(it.key) for it in items]
        # the patches' cones of the same meshes as last frame's are last frame's (a still or
        # slow camera draws the same tiles frame after frame)
        kept_cones = self._cones_of
        if len(kept_cones[0]) == len(infos) and all(
            a is b for a, b in zip(kept_cones[0], infos, strict=True)
        ):
            cones, centres, owner = kept_cones[1]
        else:
            cones, centres, owner = _cones(infos)
            self._cones_of = (infos, (cones, centres, owner))
        away = backfacing(cones, centres, plan.camera.position)
        if not away.any():
            return items, 0, 0
        counts = np.bincount(owner, minlength=len(items))
        gone = np.bincount(owner, weights=away, minlength=len(items)).astype(np.int64)
        kept: list[DrawItem] = []
        saved = 0
        start = 0
        for i, item in enumerate(items):  # per drawn tile (tens), with numpy per patch
            n = int(counts[i])
            info = infos[i]
            if gone[i] == 0 or (gone[i] < n and whole_tiles):
                kept.append(item)
            else:
                total = info.triangles if info is not None else 0
                if gone[i] == n:
                    saved += total
                else:
                    per = (total - _skirt_triangles(total, n)) // n
                    runs = _runs(~away[start : start + n], per, total)
                    saved += total - sum(c for _, c in runs)
                    kept.append(replace(item, runs=runs))
            start += n
        return kept, int(away.sum()), saved


def _same_selection(a: Selection, b: Selection) -> bool:
    """Whether two selections are the same, every column and counter."""
    for f in fields(Selection):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        if isinstance(va, np.ndarray) or isinstance(vb, np.ndarray):
            if not (isinstance(va, np.ndarray) and isinstance(vb, np.ndarray)):
                return False
            if va.shape != vb.shape or not np.array_equal(va, vb):
                return False
        elif va != vb:
            return False
    return True


def _absent(keys: U64, resident: U64) -> U64:
    """``keys`` not in the sorted ``resident``."""
    if resident.size == 0:
        return keys
    pos = np.clip(np.searchsorted(resident, keys), 0, resident.size - 1)
    out: U64 = keys[resident[pos] != keys]
    return out


def _cones(infos: list[MeshInfo | None]) -> tuple[F64, F64, NDArray[np.int64]]:
    """Every patch of the drawn meshes: its cone (NaN rows where it has none), its mesh's
    centre and the index of its mesh."""
    cones, centres, owner = [], [], []
    for i, info in enumerate(infos):
        if info is None or info.cone is None:
            cones.append(np.full((1, CONE_SIZE), np.nan))
            centres.append(np.zeros((1, 3)))
            owner.append(np.full(1, i))
            continue
        cones.append(info.cone)
        centres.append(np.broadcast_to(info.center, (info.cone.shape[0], 3)))
        owner.append(np.full(info.cone.shape[0], i))
    return np.concatenate(cones), np.concatenate(centres), np.concatenate(owner)


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


def draw_items(sel: Selection, max_sse: float = 2.0, morph: F64 | None = None) -> list[DrawItem]:
    """The renderer's draw list for a selection: each tile's mesh, its texture and the window of
    that texture it covers (a half per level up), its skirt, the screen-space error the GPU
    terrain mode's tessellation may add to the tile's own (``max_sse`` less it, at least a
    tenth of ``max_sse``), and how far it still shows the surface it replaced (``morph``, per
    tile, 0..1; None: 0)."""
    u, v, scale = _windows(sel.x, sel.y, sel.texture_up)
    budget = np.maximum(max_sse - sel.sse, 0.1 * max_sse)
    k = np.zeros(sel.count) if morph is None else morph
    cols = zip(sel.keys, sel.texture_keys, sel.skirt, u, v, scale, budget, k, strict=True)
    items = [
        DrawItem(
            int(key),
            int(t),
            float(sk),
            (float(a), float(b), float(c)),
            sse_budget=float(e),
            morph=float(m),
        )
        for key, t, sk, a, b, c, e, m in cols
    ]
    if not sel.layer_keys.size:
        return items
    # per layer: its key (-1 for none) and its window, as for the terrain's own texture
    lu, lv, lscale = _windows(sel.x, sel.y, sel.layer_up)
    lkeys = np.where(sel.layer_keys == NO_TEXTURE, -1, sel.layer_keys.astype(np.int64))
    per_tile = zip(lkeys.T.tolist(), lu.T.tolist(), lv.T.tolist(), lscale.T.tolist(), strict=True)
    return [
        replace(item, layers=tuple(zip(k, zip(a, b, c, strict=True), strict=True)))
        for item, (k, a, b, c) in zip(items, per_tile, strict=True)
    ]


def _windows(
    x: NDArray[np.int64], y: NDArray[np.int64], up: NDArray[np.int64]
) -> tuple[F64, F64, F64]:
    """The window (offset u, v and scale) of a texture ``up`` levels above each tile (x, y)
    that the tile covers: a half per level."""
    scale: F64 = np.exp2(-up.astype(np.float64))
    u: F64 = ((x & ((1 << up) - 1)) * scale).astype(np.float64)
    v: F64 = ((y & ((1 << up) - 1)) * scale).astype(np.float64)
    return u, v, scale
