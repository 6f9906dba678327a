"""One tile of a build: heights → RTIN mesh within the level's budget → its error → quantized-mesh
and PNG bytes. A tile is made from the data (its heights sampled, its error measured on every
pixel), from its four children (their heights and surfaces; no pixel read above the levels
measured on the pixels), or from the fill where there is no data. Each is a pure function of
the job, the tile and its children, so any executor makes the same bytes.
"""

from __future__ import annotations

import gzip
import io
import math
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from lodscape.geo.frames import WGS84_A
from lodscape.geo.tiles import ORIGIN, Bbox, Tile, bounds, merc_to_lonlat, xy_bounds
from lodscape.imagery import TintImagery
from lodscape.imagery.pyramid import halve_rgba
from lodscape.imagery.sources import ImageryError
from lodscape.store.quantized_mesh import QUANTIZED_MAX, decode, encode, quantize
from lodscape.store.tileset import TIN_GRID, TileRecord
from lodscape.terrain.greedy import barycentric, greedy_mesh, tin_sample_errors
from lodscape.terrain.mesh import grid_coordinates, vertex_normals, without_holes
from lodscape.terrain.rtin import Rtin
from lodscape.terrain.source import FilledSource, HeightSource, open_rasters, parse_fill

__all__ = [
    "Job",
    "Made",
    "level_budget",
    "made_from_children",
    "made_from_data",
    "made_without_data",
    "make_tile",
    "tile_budget",
]


@dataclass(frozen=True, kw_only=True)
class Job:
    """Everything a tile task needs besides its tile; small and picklable."""

    inputs: tuple[str, ...]
    allow_mixed_crs: bool
    tile_size: int
    #: Each tile's mesh keeps within this many of its level's texels of the sampled grid.
    error_texels: float
    texture_zmax: int
    height_range: tuple[float, float]
    #: The source's own sample spacing (EPSG:3857 metres): the truth errors are measured on.
    resolution: float
    #: The finest terrain level; tiles below it (down to ``imagery_zmax``) hold imagery alone.
    zmax: int = 64
    #: Imagery layers baked over the tint, bottom to top, and the finest imagery level.
    imagery: tuple[str, ...] = ()
    imagery_zmax: int = -1
    #: What stands where there is no data (``terrain.source.parse_fill``): "none" leaves it
    #: out of the meshes.
    fill: str = "interpolate"
    #: Heights below it are tinted as water (None: no sea).
    sea_level: float | None = 0.0
    #: The rasters' height band (None: their only one) and an undeclared nodata value.
    band: int | None = None
    nodata: float | None = None
    #: How tiles are meshed (``terrain.greedy.MESHERS``): "rtin" or "greedy".
    mesher: str = "rtin"
    #: The rasters' height unit (``terrain.source.parse_z_units``; None: as they say).
    z_units: str | None = None


_sources: dict[tuple[Any, ...], HeightSource] = {}
_imagery: dict[tuple[str, ...], list[Any]] = {}
_sources_lock = threading.Lock()


def _source(job: Job) -> HeightSource:
    """The job's source, opened once per process (and shared by its threads)."""
    key = (job.inputs, job.allow_mixed_crs, job.band, job.nodata, job.fill, job.z_units)
    with _sources_lock:
        src = _sources.get(key)
        if src is None:
            raw = open_rasters(
                job.inputs,
                allow_mixed_crs=job.allow_mixed_crs,
                band=job.band,
                nodata=job.nodata,
                z_units=job.z_units,
            )
            src = _sources[key] = FilledSource(raw, parse_fill(job.fill))
        return src


#: Metres added to the points without data while meshing with holes: no budget keeps a
#: triangle that spans both, so rims are cut at the grid's resolution.
_RIM = 1.0e7


def level_budget(error_texels: float, tile_size: int, z: int, y: ArrayLike) -> NDArray[np.float64]:
    """Metres of vertical error the meshes of tiles of rows ``y`` of level z may have:
    ``error_texels`` of their texels' ground size (so a level's tiles drawn at the pixel band's
    top stay near ``error_texels`` px)."""
    side = 2.0 * ORIGIN / (1 << z)
    _, lat = merc_to_lonlat(0.0, ORIGIN - (np.asarray(y, np.float64) + 0.5) * side)
    out: NDArray[np.float64] = error_texels * side * np.cos(np.radians(lat)) / tile_size
    return out


def tile_budget(job: Job, z: int, y: int) -> float:
    """``level_budget`` of one tile of a build."""
    return float(level_budget(job.error_texels, job.tile_size, z, y))


def _layers(job: Job) -> list[Any]:
    """The job's imagery layers, opened once per process (failures raise: a build does not
    bake a hole silently)."""
    key = job.imagery
    with _sources_lock:
        layers = _imagery.get(key)
        if layers is None:
            from lodscape.imagery.layers import open_layer

            layers = _imagery[key] = [open_layer(p, i + 1) for i, p in enumerate(key)]
        return layers


def _texture(job: Job, src: HeightSource, z: int, x: int, y: int) -> bytes:
    """The tile's PNG: the tint under the layers, its alpha where the terrain has data (the
    raster's footprint for a nearest fill): a client's base map shows where there is none, and
    lodscape's own renderer draws a fill's ground there (``TilesetProvider.decode``)."""
    kind = parse_fill(job.fill).kind
    rgba = TintImagery(
        src,
        job.height_range,
        tile_size=job.tile_size,
        alpha="covers" if kind == "nearest" else "valid",
        sea_level=job.sea_level,
    ).texture(z, x, y)
    if job.imagery and z <= job.imagery_zmax:
        rgb = rgba[..., :3].astype(np.float32)
        for layer in _layers(job):
            if z > layer.max_zoom:
                continue
            try:
                img = layer.decode(layer.fetch(z, x, y), job.tile_size)
            except ImageryError as exc:
                if exc.kind != "missing":
                    raise
                continue
            if img.shape[0] != job.tile_size:
                continue  # nothing of the layer here
            a = img[..., 3:4].astype(np.float32) / 255.0
            rgb = rgb * (1.0 - a) + img[..., :3].astype(np.float32) * a
        rgba = np.dstack([np.clip(rgb + 0.5, 0, 255).astype(np.uint8), rgba[..., 3]])
    return _png(rgba)


#: Levels above the finest whose tiles' errors are measured on the data's pixels (4^k times
#: a finest tile's), not bounded from their children's: the bound adds up level by level (its
#: children's errors and its distance to their surfaces, where the two partly cancel), so it
#: starts from measured errors a few levels up.
EXACT_LEVELS = 2


@dataclass(frozen=True)
class Made:
    """A finished tile as the level above is made from it: its record, and which points of its
    grid stand on data (None: all of them)."""

    record: TileRecord
    valid: NDArray[np.bool_] | None = None
    #: (TIN_GRID, TIN_GRID) bound of its mesh's error in each grid cell, metres (None: 0),
    #: so a parent adds each child's error where it is, not its worst everywhere.
    errors: NDArray[np.float32] | None = None
    #: (TIN_GRID + 1)² heights its mesh was cut from (None: none kept): the data's samples,
    #: or its children's, smoothed.
    grid: NDArray[np.float32] | None = None


def make_tile(job: Job, z: int, x: int, y: int) -> TileRecord:
    """Tile z/x/y from the data: its heights sampled, its error measured on every pixel."""
    return made_from_data(job, z, x, y).record


def made_from_data(job: Job, z: int, x: int, y: int) -> Made:
    """``make_tile``, with the grid's validity the level above needs."""
    src = _source(job)
    if z > job.zmax:
        if z > job.imagery_zmax:
            # a tile of a finer level than the job knows: its terrain is due, not its imagery
            raise ValueError(f"tile {z}/{x}/{y} is below both the job's terrain and imagery")
        # below the terrain's finest level: the imagery alone
        return Made(TileRecord(z, x, y, imagery=_texture(job, src, z, x, y)))
    xs, ys = grid_coordinates(z, x, y, TIN_GRID)
    side = xs[-1] - xs[0]
    heights, valid = src.sample_grid(xs, ys, side / TIN_GRID)
    got = _surface_tile(job, z, x, y, heights, valid, _on_pixels(src, z, x, y))
    if got is None:
        return Made(TileRecord(z, x, y), valid)
    record, emap = got
    imagery = None
    if z <= max(job.texture_zmax, job.imagery_zmax):
        imagery = _texture(job, src, z, x, y)
    return Made(replace(record, imagery=imagery), None if valid.all() else valid, emap, heights)


def _on_pixels(src: HeightSource, z: int, x: int, y: int) -> _Measured:
    """A tile's error measured on every pixel of the data in it, each in its grid cell."""
    xs, ys = grid_coordinates(z, x, y, TIN_GRID)
    step = (xs[-1] - xs[0]) / TIN_GRID
    box = xy_bounds(Tile(x, y, z))

    def measured(error_at: _ErrorAt, cells: NDArray[np.bool_] | None) -> NDArray[np.float64]:
        emap = np.zeros((TIN_GRID, TIN_GRID))
        for pxm, pym, ph in src.pixels_in(box):
            ci = np.clip(np.floor((pxm - xs[0]) / step).astype(np.int64), 0, TIN_GRID - 1)
            ri = np.clip(np.floor((ys[0] - pym) / step).astype(np.int64), 0, TIN_GRID - 1)
            if cells is not None:
                inside = cells[ri, ci]
                pxm, pym, ph, ci, ri = pxm[inside], pym[inside], ph[inside], ci[inside], ri[inside]
            plon, plat = merc_to_lonlat(pxm, pym)
            np.maximum.at(emap, (ri, ci), error_at(plon, plat, ph.astype(np.float64)))
        return emap

    return measured


#: ``error_at(lon, lat, h)``: each point's |mesh − h| (degrees, metres; 0: in no triangle).
_ErrorAt = Callable[
    [NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]
]
#: ``measured(error_at, cells)``: the (TIN_GRID, TIN_GRID) error bound per grid cell, cells
#: not in ``cells`` (where the data ends) left at 0.
_Measured = Callable[[_ErrorAt, NDArray[np.bool_] | None], NDArray[np.float64]]


def _surface_tile(
    job: Job,
    z: int,
    x: int,
    y: int,
    heights: NDArray[np.float32],
    valid: NDArray[np.bool_],
    measured: _Measured,
) -> tuple[TileRecord, NDArray[np.float32]] | None:
    """A tile's mesh of its grid ``heights`` within its level's budget, encoded, with the error
    ``measured`` gives (against the data's pixels, or the children's surfaces); None where a
    tile with holes has nothing to draw."""
    t = Tile(x, y, z)
    xs, ys = grid_coordinates(z, x, y, TIN_GRID)
    side = xs[-1] - xs[0]
    holes = job.fill == "none"
    if not valid.any() and holes:
        return None
    budget = tile_budget(job, z, y)
    if holes and not valid.all():
        # a triangle that holds data and no data has a huge error: it splits down to the grid,
        # so the mesh's rim follows the data's within a cell; then triangles touching a point
        # without data are left out, and the vertices only they used
        rtin, verts, tris = _mesh(job, np.where(valid, heights, heights + _RIM), budget)
        kept = without_holes(verts, tris, valid)
        if kept is None:
            return None
        verts, tris = kept
    else:
        rtin, verts, tris = _mesh(job, heights, budget)
    vh = heights[verts[:, 1], verts[:, 0]].astype(np.float64)
    b = bounds(t)
    lon_col, _ = merc_to_lonlat(xs, np.zeros_like(xs))
    _, lat_row = merc_to_lonlat(np.zeros_like(ys), ys)
    # the grid's sides exactly on the tile's edges, as the format's edge lists require
    lon_col[0], lon_col[-1], lat_row[0], lat_row[-1] = b.left, b.right, b.top, b.bottom
    lon, lat = lon_col[verts[:, 0]], lat_row[verts[:, 1]]
    normals = vertex_normals(lon, lat, vh, tris)
    rect = (b.left, b.bottom, b.right, b.top)
    data = encode(lon, lat, vh, tris, rect, normals=normals)
    # stored gzipped, as Cesium's servers keep them (and serve them: Content-Encoding: gzip);
    # mtime 0 so the same tile is the same bytes
    stored = gzip.compress(data, compresslevel=6, mtime=0)
    # the error of what is stored (quantized positions and heights)
    hmin, hmax = float(vh.min()), float(vh.max())
    qlon = _dequantize(quantize(lon_col, b.left, b.right), b.left, b.right)
    qlat = _dequantize(quantize(lat_row, b.bottom, b.top), b.bottom, b.top)
    qh = _dequantize(quantize(heights.astype(np.float64), hmin, hmax), hmin, hmax)

    def error_at(
        plon: NDArray[np.float64], plat: NDArray[np.float64], ph: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        out = np.zeros(plon.size)
        if plon.size == 0:
            return out
        if rtin is not None:
            _sample_errors(rtin.errors, budget, qlon, qlat, qh, plon, plat, ph, out)
        else:
            tin_sample_errors(tris, verts, qlon, qlat, qh, plon, plat, ph, out)
        return out

    # where the data ends the mesh ends (none) or drops to the fill (a wall) within the grid
    # cell that straddles the edge: samples in such cells are not the surface's to match
    cells = None
    if job.fill != "nearest" and not valid.all():
        cells = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    emap = measured(error_at, cells)
    error = float(emap.max()) + _sag(tris, verts, side, b)
    return TileRecord(z, x, y, error, hmin, hmax, stored), emap.astype(np.float32)


def made_from_children(job: Job, z: int, x: int, y: int, children: Sequence[Made]) -> Made:
    """Tile z/x/y from its four children (west-north, east-north, west-south, east-south) as
    stored: its grid is their surfaces' heights at its points, and its error bound is its
    mesh's largest distance to their surfaces (at every point and cell centre of their grids,
    where the two piecewise-linear surfaces differ most) plus their own recorded errors. No
    pixel of the data is read, so a coarse tile costs what a fine one does."""
    n = TIN_GRID
    heights = np.zeros((2 * n + 1, 2 * n + 1), np.float32)
    valid = np.zeros((2 * n + 1, 2 * n + 1), bool)
    # per child: its grid points and cell centres with data (EPSG:3857 x, y and the child's
    # height there, and which they are) and its own error bound per cell
    points: list[tuple[Any, ...]] = []
    # near the finest level the error is measured on the data's pixels: no points are needed
    on_pixels = job.zmax - z <= EXACT_LEVELS
    for i, child in enumerate(children):
        dx, dy = i & 1, i >> 1
        r = child.record
        if r.error is None:
            continue
        cz, cx, cy = z + 1, 2 * x + dx, 2 * y + dy
        at, hit, centre, centre_hit = _surface_of(cz, cx, cy, r.terrain)
        ok = hit if child.valid is None else hit & child.valid
        rows, cols = slice(dy * n, dy * n + n + 1), slice(dx * n, dx * n + n + 1)
        own_grid = at if child.grid is None else np.where(hit, child.grid, at)
        heights[rows, cols] = np.where(hit, own_grid, heights[rows, cols])
        valid[rows, cols] |= ok
        if on_pixels:
            continue
        # a centre where all four corners have data
        cells = ok[:-1, :-1] & ok[:-1, 1:] & ok[1:, :-1] & ok[1:, 1:] & centre_hit
        xs, ys = grid_coordinates(cz, cx, cy, n)
        mx, my = (xs[:-1] + xs[1:]) / 2.0, (ys[:-1] + ys[1:]) / 2.0
        gx, gy = np.meshgrid(xs, ys)
        cxm, cym = np.meshgrid(mx, my)
        px = np.concatenate([gx[ok], cxm[cells]])
        py = np.concatenate([gy[ok], cym[cells]])
        ph = np.concatenate([at[ok], centre[cells]]).astype(np.float64)
        own = np.zeros((n, n)) if child.errors is None else child.errors.astype(np.float64)
        points.append((dx, dy, ok, cells, px, py, ph, own))
    grid, gvalid = _halve_grid(heights, valid), valid[::2, ::2].copy()

    def measured(error_at: _ErrorAt, cells: NDArray[np.bool_] | None) -> NDArray[np.float64]:
        # where the two piecewise-linear surfaces differ most within a child's grid cell is at
        # its corners or its centre (every edge of either mesh runs along the grid or its
        # diagonals); a pixel there is within that of the child's surface, which is within the
        # child's own bound for the cell of the data
        fine = np.zeros((2 * n, 2 * n))
        for dx, dy, ok, inner, px, py, ph, own in points:
            plon, plat = merc_to_lonlat(px, py)
            d = error_at(plon, plat, ph)
            corner = np.zeros((n + 1, n + 1))
            mid = np.zeros((n, n))
            corner[ok] = d[: int(ok.sum())]
            mid[inner] = d[int(ok.sum()) :]
            apart = np.maximum.reduce(
                [corner[:-1, :-1], corner[:-1, 1:], corner[1:, :-1], corner[1:, 1:], mid]
            )
            fine[dy * n : dy * n + n, dx * n : dx * n + n] = apart + own
        emap: NDArray[np.float64] = np.maximum.reduce(
            [fine[0::2, 0::2], fine[1::2, 0::2], fine[0::2, 1::2], fine[1::2, 1::2]]
        )
        if cells is not None:
            emap[~cells] = 0.0
        return emap

    if on_pixels:
        # near the finest level, the data's pixels under the tile are few enough to measure on
        got = _surface_tile(job, z, x, y, grid, gvalid, _on_pixels(_source(job), z, x, y))
    else:
        got = _surface_tile(job, z, x, y, grid, gvalid, measured)
    finest = max(job.texture_zmax, job.imagery_zmax)
    imagery = None
    if z < finest:
        imagery = _downsample([c.record.imagery for c in children], job.tile_size)
    elif z == finest:
        # the finest imagery level: its texels about as fine as the data's pixels
        imagery = _texture(job, _source(job), z, x, y)
    if got is None:
        return Made(TileRecord(z, x, y, imagery=imagery), gvalid)
    record, emap = got
    return Made(replace(record, imagery=imagery), None if gvalid.all() else gvalid, emap, grid)


def _halve_grid(fine: NDArray[np.float32], valid: NDArray[np.bool_]) -> NDArray[np.float32]:
    """A (2n + 1)² grid of heights to (n + 1)²: each point the [1 2 1]² mean of the points
    with data around it (as a coarser level's samples are means of the data's pixels), along
    the edges the [1 2 1] mean of the edge's own points (which the neighbouring tile has
    too, so both give the edge the same heights), the corners as they are."""
    w = valid.astype(np.float64)
    v = np.where(valid, fine, 0.0).astype(np.float64)

    def smooth(a: NDArray[np.float64], axis: int) -> NDArray[np.float64]:
        out = 2.0 * a
        if axis == 0:
            out[1:-1] += a[:-2] + a[2:]
        else:
            out[:, 1:-1] += a[:, :-2] + a[:, 2:]
        return out

    # the interior: separable in both directions
    sw, sv = smooth(smooth(w, 0), 1), smooth(smooth(v, 0), 1)
    # the edges: along themselves only
    for axis, index in ((1, 0), (1, -1), (0, 0), (0, -1)):
        line_w = smooth(w, axis)
        line_v = smooth(v, axis)
        if axis == 1:
            sw[index, :], sv[index, :] = line_w[index, :], line_v[index, :]
        else:
            sw[:, index], sv[:, index] = line_w[:, index], line_v[:, index]
    for i in (0, -1):
        for j in (0, -1):
            sw[i, j], sv[i, j] = w[i, j], v[i, j]
    mean = np.where(sw > 0.0, sv / np.maximum(sw, 1e-12), fine)
    out: NDArray[np.float32] = mean[::2, ::2].astype(np.float32)
    return out


def made_without_data(job: Job, z: int, x: int, y: int) -> Made:
    """Tile z/x/y where there is no data: the fill's surface and tint, no pixel read (a child
    outside the data's footprint, or a block the plan found empty)."""
    src = _Unread(_source(job))
    xs, ys = grid_coordinates(z, x, y, TIN_GRID)
    gx, gy = np.meshgrid(xs, ys)
    heights, valid = src.sample_nodata(gx, gy)
    got = _surface_tile(job, z, x, y, heights, valid, lambda _e, _c: np.zeros((1, 1)))
    imagery = None
    if z <= max(job.texture_zmax, job.imagery_zmax):
        imagery = _texture(job, src, z, x, y)  # type: ignore[arg-type]
    if got is None:
        return Made(TileRecord(z, x, y, imagery=imagery), valid)
    return Made(replace(got[0], imagery=imagery), valid)


class _Unread:
    """A source's view that never reads a pixel: every point is without data (its fill)."""

    def __init__(self, source: HeightSource) -> None:
        self.source = source
        self.name = source.name
        self.crs_wkt = source.crs_wkt
        self.bounds_merc = source.bounds_merc
        self.resolution_merc = source.resolution_merc

    def sample_nodata(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        out: tuple[NDArray[np.float32], NDArray[np.bool_]]
        out = self.source.sample_nodata(xm, ym)  # type: ignore[attr-defined]
        return out

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        return self.sample_nodata(xm, ym)

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        rows, cols = shape
        left, bottom, right, top = (float(v) for v in bounds)
        xv = left + np.arange(cols) * (right - left) / (cols - 1)
        yv = top - np.arange(rows) * (top - bottom) / (rows - 1)
        xv[-1], yv[-1] = right, bottom
        return self.sample_nodata(*np.meshgrid(xv, yv))

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        return self.source.covers(xm, ym)


def _surface_of(
    z: int, x: int, y: int, stored: bytes
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.float32], NDArray[np.bool_]]:
    """A stored tile's surface at its (TIN_GRID + 1)² grid points and its TIN_GRID² cell
    centres, as a client draws it (quantized positions and heights), and where it has one."""
    qm = decode(stored)
    b = bounds(Tile(x, y, z))
    xs, ys = grid_coordinates(z, x, y, TIN_GRID)
    lon_col, _ = merc_to_lonlat(xs, np.zeros_like(xs))
    _, lat_row = merc_to_lonlat(np.zeros_like(ys), ys)
    lon_col[0], lon_col[-1], lat_row[0], lat_row[-1] = b.left, b.right, b.top, b.bottom
    gu = quantize(lon_col, b.left, b.right).astype(np.float64)
    gv = quantize(lat_row, b.bottom, b.top).astype(np.float64)
    _, _, vh = qm.positions(b.left, b.bottom, b.right, b.top)
    vu, vv = qm.u.astype(np.float64), qm.v.astype(np.float64)
    # every vertex sits on a grid point: its column and row
    col = np.searchsorted(gu, vu)
    row = (gv.size - 1) - np.searchsorted(gv[::-1], vv)
    if not (
        np.array_equal(gu[np.clip(col, 0, gu.size - 1)], vu)
        and np.array_equal(gv[np.clip(row, 0, gv.size - 1)], vv)
    ):
        raise ValueError(f"tile {z}/{x}/{y}: a vertex off its grid")
    n = TIN_GRID
    at = np.zeros((n + 1, n + 1), np.float64)
    hit = np.zeros((n + 1, n + 1), bool)
    centre = np.zeros((n, n), np.float64)
    centre_hit = np.zeros((n, n), bool)
    _rasterize(
        qm.triangles.astype(np.int64),
        col.astype(np.int64),
        row.astype(np.int64),
        vu,
        vv,
        vh,
        gu,
        gv,
        at,
        hit,
        centre,
        centre_hit,
    )
    return at.astype(np.float32), hit, centre.astype(np.float32), centre_hit


@numba.njit(cache=True, nogil=True)  # type: ignore[misc]
def _rasterize(
    tris: NDArray[np.int64],
    col: NDArray[np.int64],
    row: NDArray[np.int64],
    vu: NDArray[np.float64],
    vv: NDArray[np.float64],
    vh: NDArray[np.float64],
    gu: NDArray[np.float64],
    gv: NDArray[np.float64],
    at: NDArray[np.float64],
    hit: NDArray[np.bool_],
    centre: NDArray[np.float64],
    centre_hit: NDArray[np.bool_],
) -> None:
    """The mesh's heights at the grid points and cell centres its triangles cover (each
    triangle's box of the grid, by barycentric weights in the quantized u, v)."""
    eps = -1e-9
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        c0 = min(col[a], col[b], col[c])
        c1 = max(col[a], col[b], col[c])
        r0 = min(row[a], row[b], row[c])
        r1 = max(row[a], row[b], row[c])
        for r in range(r0, r1 + 1):
            for k in range(c0, c1 + 1):
                for mid in range(2):
                    if mid == 1 and (r == r1 or k == c1):
                        continue
                    if mid == 0:
                        if hit[r, k]:
                            continue
                        pu, pv = gu[k], gv[r]
                    else:
                        if centre_hit[r, k]:
                            continue
                        pu, pv = 0.5 * (gu[k] + gu[k + 1]), 0.5 * (gv[r] + gv[r + 1])
                    ok, w0, w1 = barycentric(vu[a], vv[a], vu[b], vv[b], vu[c], vv[c], pu, pv)
                    if not ok:
                        continue
                    w2 = 1.0 - w0 - w1
                    if w0 < eps or w1 < eps or w2 < eps:
                        continue
                    v = w0 * vh[a] + w1 * vh[b] + w2 * vh[c]
                    if mid == 0:
                        at[r, k] = v
                        hit[r, k] = True
                    else:
                        centre[r, k] = v
                        centre_hit[r, k] = True


def _downsample(images: Sequence[bytes | None], size: int) -> bytes | None:
    """A parent's PNG from its four children's (west-north, east-north, west-south,
    east-south): each texel the alpha-weighted mean of the four beneath it (their plain mean
    where all four are transparent: the fill's tint, which lodscape draws there)."""
    if all(i is None for i in images):
        return None
    from PIL import Image

    big = np.zeros((2 * size, 2 * size, 4), np.float64)
    for i, data in enumerate(images):
        if data is None:
            continue
        img = np.asarray(Image.open(io.BytesIO(data)).convert("RGBA"), np.float64)
        if img.shape[:2] != (size, size):
            raise ValueError(f"a child's imagery is {img.shape[1]}×{img.shape[0]}, not {size}")
        dx, dy = i & 1, i >> 1
        big[dy * size : (dy + 1) * size, dx * size : (dx + 1) * size] = img
    return _png(halve_rgba(big))


def _mesh(
    job: Job, heights: NDArray[np.floating], budget: float
) -> tuple[Rtin | None, NDArray[np.int32], NDArray[np.int32]]:
    """A tile's mesh within ``budget`` by the job's mesher, with RTIN's error pyramid (which
    locates samples faster than a search) when RTIN cut it."""
    if job.mesher == "greedy":
        verts, tris = greedy_mesh(heights, budget)
        return None, verts, tris
    rtin = Rtin(heights)
    verts, tris = rtin.mesh(budget)
    return rtin, verts, tris


def _dequantize(q: NDArray[np.uint16], lo: float, hi: float) -> NDArray[np.float64]:
    """What a decoder reads back: lo + (hi − lo)·q/32767, as ``QuantizedMesh.positions``."""
    out: NDArray[np.float64] = lo + (hi - lo) * (q.astype(np.float64) * (1.0 / QUANTIZED_MAX))
    return out


def _sag(tris: NDArray[np.int32], verts: NDArray[np.int32], side: float, b: Bbox) -> float:
    """How far the longest edge's straight chord sags below the curved Earth: L²/(8R)."""
    p = verts.astype(np.float64)
    t = tris.astype(np.int64)
    longest = max(float(np.hypot(*(p[t[:, i]] - p[t[:, (i + 1) % 3]]).T).max()) for i in range(3))
    ground = longest / TIN_GRID * side * math.cos(math.radians(min(abs(b.bottom), abs(b.top))))
    return ground * ground / (8.0 * WGS84_A)


@numba.njit(cache=True, nogil=True)  # type: ignore[misc]
def _sample_error(
    err: NDArray[np.float64],
    budget: float,
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    h: NDArray[np.float64],
    plon: NDArray[np.float64],
    plat: NDArray[np.float64],
    ph: NDArray[np.float64],
) -> float:
    """``_sample_errors``' largest."""
    out = np.zeros(plon.size)
    return _sample_errors(err, budget, lon, lat, h, plon, plat, ph, out)


@numba.njit(cache=True, nogil=True)  # type: ignore[misc]
def _sample_errors(
    err: NDArray[np.float64],
    budget: float,
    lon: NDArray[np.float64],
    lat: NDArray[np.float64],
    h: NDArray[np.float64],
    plon: NDArray[np.float64],
    plat: NDArray[np.float64],
    ph: NDArray[np.float64],
    out: NDArray[np.float64],
) -> float:
    """The largest |mesh − sample| over the samples: each point is located by descending the
    RTIN exactly as its mesh was cut (the same split test), in the tile's lon/lat, where the
    format interpolates; grid vertex (col, row) sits at (lon[col], lat[row]), height h[row, col];
    each point's |mesh − sample| is written to ``out`` (0: in no triangle)."""
    last = lon.size - 1
    worst = 0.0
    for k in range(plon.size):
        px, py = plon[k], plat[k]
        # two roots on the diagonal from the north-west corner to the south-east one
        ax, ay, bx, by, cx, cy = 0, 0, last, last, last, 0
        s_p = _side(lon[0], lat[0], lon[last], lat[last], px, py)
        s_c = _side(lon[0], lat[0], lon[last], lat[last], lon[last], lat[0])
        if s_p * s_c < 0.0:
            ax, ay, bx, by, cx, cy = last, last, 0, 0, 0, last
        while True:
            mx = (ax + bx) >> 1
            my = (ay + by) >> 1
            if not (abs(ax - cx) + abs(ay - cy) > 1 and err[my, mx] > budget):
                break
            # children (c, a, m) and (b, c, m): the point is in the one on its side of c–m
            s_p = _side(lon[cx], lat[cy], lon[mx], lat[my], px, py)
            s_a = _side(lon[cx], lat[cy], lon[mx], lat[my], lon[ax], lat[ay])
            if s_p * s_a >= 0.0:
                ax, ay, bx, by, cx, cy = cx, cy, ax, ay, mx, my
            else:
                ax, ay, bx, by, cx, cy = bx, by, cx, cy, mx, my
        ok, w0, w1 = barycentric(lon[ax], lat[ay], lon[bx], lat[by], lon[cx], lat[cy], px, py)
        if not ok:
            continue
        v = w0 * h[ay, ax] + w1 * h[by, bx] + (1.0 - w0 - w1) * h[cy, cx]
        e = abs(v - ph[k])
        out[k] = e
        if e > worst:
            worst = e
    return worst


@numba.njit(cache=True, inline="always")  # type: ignore[misc]
def _side(x0: float, y0: float, x1: float, y1: float, px: float, py: float) -> float:
    return (x1 - x0) * (py - y0) - (y1 - y0) * (px - x0)


def _png(rgba: NDArray[np.uint8]) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgba).save(buf, format="PNG", compress_level=6)
    return buf.getvalue()
