"""A city ready to draw (paper 001): objects on the terrain, an R-tree over them, per-leaf meshes
merged by material for each level of detail, and instances of the shared street models.

Made once on the CPU (no GL). Per frame, ``CityModel.frame_lists`` culls the tree's leaves by the
frustum, picks each leaf's level of detail by the pixels its largest object covers, and returns
draw commands: for each material one list of (first index, count) runs of the merged meshes (one
multi-draw-indirect each), and for each model part one list of (first instance, count) runs (one
instanced multi-draw each).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import shapely
from numpy.typing import NDArray
from shapely.geometry import Polygon

from lodscape.city.mesh import MODELS, Frame, Geometry, box_mesh, building_mesh
from lodscape.city.osm import Building, City
from lodscape.city.rtree import DEFAULT_PACKING, RTree, pack
from lodscape.lod.camera import Camera

__all__ = ["LODS", "CityFrame", "CityModel", "CityOptions", "build_city"]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
#: The levels of detail of a building, finest first (the third is "none": not drawn).
LODS = ("full", "box")
#: Ground heights (metres) at (lon, lat) arrays; NaN where the terrain has none.
Ground = Callable[[F64, F64], F64]


#: "auto" occlusion culling: metres above the ground under which the camera is among the walls.
OCCLUSION_BELOW = 10.0


@dataclass(frozen=True)
class CityOptions:
    """How the city is culled and simplified; ``naive`` turns every optimisation off."""

    #: A leaf whose largest object covers at least this many pixels is drawn in full.
    full_px: float = 40.0
    #: Below this it is not drawn at all (between the two: boxes; street objects: none).
    min_px: float = 2.0
    frustum: bool = True
    lod: bool = True
    #: Coherent hierarchical occlusion culling (CHC++): True, False, or "auto": on where it
    #: paid on the benchmark's city (BENCHMARKS.md), a software rasteriser (triangles are what
    #: costs there) with the camera less than ``OCCLUSION_BELOW`` metres above the ground
    #: (walls in the way); off elsewhere, where levels of detail already thin what lies behind
    #: and waiting for the queries costs more than the triangles they save.
    occlusion: bool | str = "auto"
    #: Occlusion queries on the leaves' parents first where every shown leaf of one was hidden
    #: last frame (CHC++'s hierarchy); else on each leaf.
    hierarchical: bool = True
    #: Merged meshes drawn with multi-draw-indirect (else one draw per leaf and material).
    indirect: bool = True
    #: Street objects drawn instanced (else one draw per object).
    instancing: bool = True
    #: CHC++'s query skipping: a leaf seen in the last frame is asked again only every this many
    #: frames (staggered by leaf), and drawn meanwhile.
    revisit: int = 8
    #: A leaf with fewer triangles than this at its level of detail is drawn, never asked: a
    #: query costs about as much as drawing it.
    query_min_triangles: int = 512
    #: Wait for the GPU before and after the city pass and report its time (for benchmarks;
    #: the waits cost a little).
    timed: bool = False
    #: The camera in a uniform buffer written once a frame, the street objects' instances in a
    #: shader storage buffer (OpenGL 4.3 with the draw parameters) instead of plain uniforms per
    #: program and instanced vertex attributes. Off by default: on llvmpipe it cost ~10 % a
    #: frame (storage reads per vertex); not measured on a GPU (BENCHMARKS.md).
    buffers: bool = False
    #: How the scene tree is packed when the city is built here ("hilbert", "str" or
    #: "priority": the Priority R-tree; ``bench/bench_city.py`` compares them).
    packing: str = DEFAULT_PACKING

    @classmethod
    def naive(cls) -> CityOptions:
        return cls(frustum=False, lod=False, occlusion=False, indirect=False, instancing=False)

    @property
    def is_naive(self) -> bool:
        """Every optimisation off: one draw per object (paper 001's baseline)."""
        occl = self.occlusion is True or self.occlusion == "auto"
        return not (self.frustum or self.lod or occl or self.indirect or self.instancing)

    def resolved(self, software: bool, height: float | None) -> CityOptions:
        """These options with "auto" occlusion culling decided for a frame: on for a software
        rasteriser with the camera ``height`` metres (None: unknown) above the ground, under
        ``OCCLUSION_BELOW``."""
        if self.occlusion != "auto":
            return self
        low = height is not None and height < OCCLUSION_BELOW
        return replace(self, occlusion=bool(software and low))


@dataclass(frozen=True, eq=False)
class CityFrame:
    """What one frame draws of the city, before occlusion culling."""

    #: Leaves in view (after frustum culling), nearest first.
    leaves: I64
    #: Level of each of those leaves: 0 full, 1 box, 2 none.
    lod: I64
    culled_frustum: int
    culled_lod: int
    boxes_tested: int


@dataclass(eq=False)
class CityModel:
    frame: Frame
    materials: tuple[str, ...]
    #: Per level of detail and material: merged geometry (absolute indices).
    geometry: dict[tuple[int, str], Geometry]
    #: Per level and material: (L,) first index and count of each leaf's run.
    runs: dict[tuple[int, str], tuple[I64, I64]]
    #: Per object (buildings, then street objects, in leaf order) and material, at full level:
    #: (first index, count) for the naive path.
    object_runs: dict[str, tuple[I64, I64]]
    #: Street objects: per kind, (K, 5) float32 x, y, z, scale, heading (radians), leaf order.
    instances: dict[str, NDArray[np.float32]]
    #: Per kind: (L,) first instance and count of each leaf's run.
    instance_runs: dict[str, tuple[I64, I64]]
    tree: RTree
    #: (L,) the largest object's diameter in each leaf, metres.
    leaf_size: F64
    #: (L,) buildings and street objects per leaf.
    leaf_objects: I64
    buildings: int
    street_objects: int
    report: dict[str, object] = field(default_factory=dict)

    @property
    def objects(self) -> int:
        return self.buildings + self.street_objects

    def triangles(self, lod: int = 0) -> int:
        """Triangles of the whole city at one level (street objects included at level 0)."""
        tri = sum(len(g.triangles) for (k, _), g in self.geometry.items() if k == lod)
        if lod == 0:
            for kind, inst in self.instances.items():
                tri += len(inst) * sum(len(g.triangles) for g in MODELS[kind].values())
        return tri

    @cached_property
    def leaf_triangles(self) -> NDArray[np.int64]:
        """(levels, L) triangles of each leaf at each level of detail, street objects included
        at the full level."""
        out = np.zeros((len(LODS), self.tree.leaves), dtype=np.int64)
        for (lod, _), (_, count) in self.runs.items():
            out[lod] += count // 3
        for kind, (_, count) in self.instance_runs.items():
            out[0] += count * sum(len(g.triangles) for g in MODELS[kind].values())
        return out

    def local_planes(self, camera: Camera) -> F64:
        """The camera's frustum planes in the city's frame."""
        planes = camera.frustum_planes()
        basis = self.frame.basis
        n = planes[:, :3] @ basis.T
        w = planes[:, 3] + planes[:, :3] @ (self.frame.origin - camera.position)
        return np.concatenate([n, w[:, None]], axis=1)

    def local_eye(self, camera: Camera) -> F64:
        eye: F64 = self.frame.basis @ (camera.position - self.frame.origin)
        return eye

    def frame_lists(self, camera: Camera, options: CityOptions) -> CityFrame:
        """Leaves in view and their levels of detail, nearest first."""
        n = self.tree.leaves
        if options.frustum:
            vis, tested = self.tree.cull(self.local_planes(camera))
        else:
            vis, tested = np.ones(n, dtype=bool), 0
        leaves = np.nonzero(vis)[0]
        boxes = self.tree.levels[0][leaves]
        eye = self.local_eye(camera)
        gap = np.maximum(boxes[:, :3] - eye, 0.0) + np.maximum(eye - boxes[:, 3:], 0.0)
        dist = np.linalg.norm(gap, axis=1)
        order = np.argsort(dist, kind="stable")
        leaves, dist = leaves[order], dist[order]
        if options.lod:
            px = camera.screen_size(self.leaf_size[leaves], dist)
            lod = np.where(px >= options.full_px, 0, np.where(px >= options.min_px, 1, 2))
        else:
            lod = np.zeros(len(leaves), dtype=np.int64)
        culled_frustum = int(self.leaf_objects[~vis].sum())
        culled_lod = int(self.leaf_objects[leaves[lod == 2]].sum())
        return CityFrame(leaves, lod.astype(np.int64), culled_frustum, culled_lod, tested)


def _ground_under(ground: Ground, polys: list[Polygon]) -> F64:
    """The lowest terrain height under each footprint (its vertices and centre sampled)."""
    pts = []
    owner = []
    for i, p in enumerate(polys):
        c = np.asarray(p.exterior.coords)
        c = np.vstack([c, [p.representative_point().coords[0]]])
        pts.append(c)
        owner.append(np.full(len(c), i))
    if not pts:
        return np.zeros(0)
    xy = np.concatenate(pts)
    h = np.asarray(ground(xy[:, 0], xy[:, 1]), np.float64)
    h = np.where(np.isfinite(h), h, np.nan)
    out = np.full(len(polys), np.inf)
    np.minimum.at(out, np.concatenate(owner), np.where(np.isnan(h), np.inf, h))
    return np.where(np.isfinite(out), out, 0.0)


def build_city(
    city: City,
    ground: Ground | None = None,
    *,
    frame: Frame | None = None,
    packing: str = DEFAULT_PACKING,
    leaf: int = 16,
) -> CityModel:
    """Place every object on the terrain and build the scene tree and the merged meshes."""
    if frame is None:
        w, s, e, n = city.bounds
        frame = Frame((w + e) / 2.0, (s + n) / 2.0)
    if ground is None:

        def ground(lon: F64, lat: F64) -> F64:
            return np.zeros(np.shape(lon))

    blds = city.buildings
    base_h = _ground_under(ground, [b.footprint for b in blds])
    # footprints in the frame (metres), each building's base on its local up
    boxes = np.zeros((len(blds) + len(city.features), 6))
    size = np.zeros(len(blds) + len(city.features))
    full, boxes_geo = _place_buildings(blds, frame, base_h, boxes, size)
    feats = city.features
    nb = len(blds)
    if feats:
        lon = np.array([f.lon for f in feats])
        lat = np.array([f.lat for f in feats])
        h = np.asarray(ground(lon, lat), np.float64)
        h = np.where(np.isfinite(h), h, 0.0)
        pos = frame.local(lon, lat, h)
        for j, f in enumerate(feats):
            geo = Geometry.join(list(MODELS[f.kind].values()))
            lo, hi = geo.positions.min(axis=0), geo.positions.max(axis=0)
            sc = _scale(f.kind, f.height)
            boxes[nb + j, :3] = pos[j] + lo * sc
            boxes[nb + j, 3:] = pos[j] + hi * sc
            size[nb + j] = float(np.linalg.norm(hi - lo)) * sc
    else:
        pos = np.zeros((0, 3))
    tree = pack(boxes, leaf=leaf, packing=packing)
    order = tree.order
    leaf_of = np.repeat(np.arange(tree.leaves), np.diff(tree.leaf_start))
    materials = sorted({m for g in full + boxes_geo for m in g})
    geometry, runs, object_runs = _merged(tree, (full, boxes_geo), materials, nb)
    instances: dict[str, NDArray[np.float32]] = {}
    instance_runs: dict[str, tuple[I64, I64]] = {}
    rng = np.random.default_rng(0)
    heading = rng.uniform(0.0, 2.0 * np.pi, len(feats))
    kinds = np.array([f.kind for f in feats])
    is_feat = order >= nb
    # street objects in leaf order, and the leaf of each
    in_order, leaf_feat = order[is_feat] - nb, leaf_of[is_feat]
    for kind in sorted(set(kinds.tolist())):
        m = kinds[in_order] == kind
        idx = in_order[m]
        inst = np.zeros((len(idx), 5), np.float32)
        inst[:, :3] = pos[idx]
        inst[:, 3] = [_scale(kind, feats[i].height) for i in idx]
        inst[:, 4] = heading[idx]
        instances[kind] = inst
        cnt = np.bincount(leaf_feat[m], minlength=tree.leaves).astype(np.int64)
        instance_runs[kind] = (np.concatenate([[0], np.cumsum(cnt)[:-1]]).astype(np.int64), cnt)
    leaf_size = np.zeros(tree.leaves)
    np.maximum.at(leaf_size, leaf_of, size[order])
    report = dict(city.report())
    return CityModel(
        frame,
        tuple(materials),
        geometry,
        runs,
        object_runs,
        instances,
        instance_runs,
        tree,
        leaf_size,
        np.diff(tree.leaf_start),
        nb,
        len(feats),
        report,
    )


def _place_buildings(
    blds: Sequence[Building],
    frame: Frame,
    base_h: F64,
    boxes: F64,
    size: F64,
) -> tuple[list[dict[str, Geometry]], list[dict[str, Geometry]]]:
    """Each building's footprint in the frame on its base height: its full mesh and its box
    (by material), its bounds written into ``boxes`` and its size into ``size``."""
    full: list[dict[str, Geometry]] = []
    boxes_geo: list[dict[str, Geometry]] = []
    for i, b in enumerate(blds):
        ext = np.asarray(b.footprint.exterior.coords)
        c = b.footprint.representative_point()
        origin = frame.local(np.array(c.x), np.array(c.y), base_h[i])
        loc = frame.local(ext[:, 0], ext[:, 1], base_h[i])
        holes = [
            frame.local(np.asarray(r.coords)[:, 0], np.asarray(r.coords)[:, 1], base_h[i])[:, :2]
            for r in b.footprint.interiors
        ]
        xy = Polygon(loc[:, :2], holes)
        if not xy.is_valid:
            xy = shapely.make_valid(xy)
            xy = max(getattr(xy, "geoms", [xy]), key=lambda g: g.area)
        z0 = float(origin[2])
        full.append(building_mesh(b, xy, z0))
        boxes_geo.append(box_mesh(b, xy, z0))
        x0, y0, x1, y1 = xy.bounds
        boxes[i] = [x0, y0, z0 + b.min_height, x1, y1, z0 + b.height]
        size[i] = float(np.linalg.norm([x1 - x0, y1 - y0, b.height]))
    return full, boxes_geo


def _merged(
    tree: RTree,
    per_lod: tuple[list[dict[str, Geometry]], list[dict[str, Geometry]]],
    materials: list[str],
    nb: int,
) -> tuple[
    dict[tuple[int, str], Geometry],
    dict[tuple[int, str], tuple[I64, I64]],
    dict[str, tuple[I64, I64]],
]:
    """The buildings' meshes merged per level of detail and material in the tree's leaf
    order, each leaf's run of vertices, and (full detail) each object's."""
    order = tree.order
    leaf_of = np.repeat(np.arange(tree.leaves), np.diff(tree.leaf_start))
    full, boxes_geo = per_lod
    geometry: dict[tuple[int, str], Geometry] = {}
    runs: dict[tuple[int, str], tuple[I64, I64]] = {}
    object_runs: dict[str, tuple[I64, I64]] = {}
    empty = Geometry.join([])
    for lod, per_obj in enumerate((full, boxes_geo)):
        for m in materials:
            parts = [per_obj[o].get(m, empty) if o < nb else empty for o in order]
            counts = np.array([3 * len(p.triangles) for p in parts], dtype=np.int64)
            first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
            geometry[(lod, m)] = Geometry.join(parts)
            lf = np.zeros(tree.leaves, dtype=np.int64)
            lc = np.zeros(tree.leaves, dtype=np.int64)
            np.add.at(lc, leaf_of, counts)
            lf[:] = first[tree.leaf_start[:-1]] if len(first) else 0
            runs[(lod, m)] = (lf, lc)
            if lod == 0:
                object_runs[m] = (first, counts)
    return geometry, runs, object_runs


def _scale(kind: str, height: float | None) -> float:
    """A street object's scale from its tagged height (the model's own height otherwise)."""
    if height is None:
        return 1.0
    own = {"tree": 7.0, "street_lamp": 6.05, "bench": 0.9}[kind]
    return float(np.clip(height / own, 0.3, 5.0))
