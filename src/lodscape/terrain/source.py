"""Height sources: heights at Web Mercator points from a GDAL raster or a numpy array, any CRS.

A source answers ``sample(xm, ym, spacing)``: bilinear heights at EPSG:3857 points, read from the
resolution that fits ``spacing`` (the spacing of the caller's grid) so coarse grids do not alias:
level k of the source is 2^k × 2^k pixels per sample, the file's own overview where it has one of
that factor, otherwise a block mean over pixel blocks aligned to the source's global pixel grid.
A point's height depends only on the point and ``spacing``, never on which call or window asked,
so adjacent tiles get bit-identical shared edges.

Points without data (nodata, NaN, masked, outside the raster) come back with ``valid`` False and a
height filled from a coarse, hole-filled overview of the whole raster built once at open, so
callers never see nodata values, NaN or spikes to 0. Heights come out in metres: a band's scale
and offset are applied, and heights in feet are converted, their unit taken from (first found) the
caller's ``z_units``, the band's unit metadata, a compound CRS's vertical axis, or a projected
CRS's horizontal unit where the file says nothing else (``RasterSource.z_note`` says which).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, Self

import numpy as np
import rasterio
from numpy.typing import ArrayLike, NDArray
from pyproj import CRS, Transformer
from rasterio.errors import NotGeoreferencedWarning
from rasterio.transform import Affine
from rasterio.windows import Window

from lodscape._cache import user_cache
from lodscape.errors import SourceError
from lodscape.geo.tiles import MAX_LAT, ORIGIN, Bbox, lonlat_to_merc

__all__ = [
    "COARSE_SIZE",
    "GCP_TOLERANCE",
    "HEIGHT_LIMITS",
    "ArraySource",
    "Fill",
    "FilledSource",
    "HeightSource",
    "MosaicSource",
    "RasterSource",
    "gcp_fit",
    "gcp_placement",
    "open_rasters",
    "parse_fill",
    "parse_z_units",
    "pixel_share",
    "raster_notes",
    "rasters_of",
    "sea_note",
]

#: Longest side (pixels) of the hole-filled whole-raster overview that fills invalid points.
COARSE_SIZE = 1024
#: Heights (metres) a DEM's valid pixels may have: below the deepest sea floor (−10,994 m) or
#: above the highest summit (8,849 m) with a margin, a value is a nodata marker nobody declared
#: (−3.4e38, ±1e30, 32767…), and the DEM is refused rather than drawn as a spike.
HEIGHT_LIMITS = (-12000.0, 9000.0)
#: Points per edge when projecting the footprint (edges curve in Web Mercator).
_EDGE_POINTS = 64
#: Lattice step (points) and tolerance (pixels) of ``sample_grid``'s interpolated projection.
_LATTICE = 16
_LATTICE_TOL = 1e-3
#: Level-0 pixels read per strip while building the coarse overview (bounds memory at open).
_STRIP_PIXELS = 1 << 21

F64 = NDArray[np.float64]
B = NDArray[np.bool_]

#: Metres per unit of the height units a DEM may be in, by the names files and users give them.
_Z_UNITS = {
    "m": 1.0,
    "metre": 1.0,
    "metres": 1.0,
    "meter": 1.0,
    "meters": 1.0,
    "ft": 0.3048,
    "foot": 0.3048,
    "feet": 0.3048,
    "international foot": 0.3048,
    "international feet": 0.3048,
    "us-ft": 1200.0 / 3937.0,
    "us_ft": 1200.0 / 3937.0,
    "usft": 1200.0 / 3937.0,
    "ftus": 1200.0 / 3937.0,
    "us survey foot": 1200.0 / 3937.0,
    "us survey feet": 1200.0 / 3937.0,
    "us_survey_foot": 1200.0 / 3937.0,
    "foot_us": 1200.0 / 3937.0,
}


def parse_z_units(text: str) -> float:
    """Metres per height unit: ``m``, ``ft`` (international), ``us-ft`` (US survey), or a
    positive number of metres per unit."""
    key = " ".join(text.strip().lower().replace("-", " ").split()).replace(" ", "-")
    for name, factor in _Z_UNITS.items():
        if key == name.replace(" ", "-").replace("_", "-"):
            return factor
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if math.isfinite(value) and value > 0.0:
        return value
    raise SourceError(
        f"--z-units must be m, ft, us-ft or metres per unit (e.g. 0.3048), got {text!r}"
    )


def _unit_name(factor: float) -> str:
    if factor == 1.0:
        return "metres"
    if abs(factor - 0.3048) < 1e-9:
        return "feet"
    if abs(factor - 1200.0 / 3937.0) < 1e-9:
        return "US survey feet"
    return f"units of {factor:g} m"


def _z_units(ds: Any, band: int, crs: CRS) -> tuple[float, str | None]:
    """Metres per height unit of a raster's band, and where that was read (None: nothing says,
    metres assumed)."""
    unit = (ds.units[band - 1] if ds.units else None) or ""
    if unit.strip():
        try:
            return parse_z_units(unit), f"the band's unit {unit!r}"
        except SourceError:
            pass  # a unit we do not know (a description, "elevation"…) says nothing
    if crs.is_compound:
        for sub in crs.sub_crs_list:
            if sub.is_vertical and sub.axis_info:
                axis = sub.axis_info[0]
                return float(axis.unit_conversion_factor), f"the vertical CRS {sub.name!r}"
    if crs.is_projected and crs.axis_info:
        factor = float(crs.axis_info[0].unit_conversion_factor)
        if factor != 1.0:
            return factor, f"the CRS's horizontal unit ({crs.axis_info[0].unit_name})"
    return 1.0, None


class HeightSource(Protocol):
    """Heights (metres) at Web Mercator points, with a validity mask; see the module docstring."""

    #: For messages: the file path, or "array".
    name: str
    #: The source CRS as WKT (provenance).
    crs_wkt: str
    #: Footprint of the data in EPSG:3857 metres, latitude clamped to ±MAX_LAT.
    bounds_merc: Bbox
    #: Native sample spacing in EPSG:3857 metres at the data's centre (the finer of x and y).
    resolution_merc: float

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...

    def sample_grid(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]: ...

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]: ...

    def pixels_in(self, box: Bbox) -> Iterator[tuple[F64, F64, F64]]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class _Turn:
    """How a geographic raster's longitudes sit against -180..180°: ``shift`` degrees away by
    whole turns (360 for one stored as 190..196°, the -170..-164° of data kept in 0..360°), or
    all the way round from ``west`` (a whole world in 0..360°, or -180..180° with a pixel's
    overlap): a longitude is then read at its first turn from ``west``."""

    shift: float = 0.0
    west: float | None = None

    def __bool__(self) -> bool:
        return self.shift != 0.0 or self.west is not None


def _turn(crs: CRS, transform: Affine, shape: tuple[int, int]) -> _Turn:
    """The ``_Turn`` of a raster of this CRS, transform and shape (none: not geographic, or
    within -180..180°)."""
    if not crs.is_geographic:
        return _Turn()
    h, w = shape
    t = transform
    xs = [float(t.a * c + t.b * r + t.c) for c in (0, w) for r in (0, h)]
    west, east = min(xs), max(xs)
    eps = 1e-9
    if west >= -180.0 - eps and east <= 180.0 + eps:
        return _Turn()
    if east - west >= 360.0 - eps:
        return _Turn(west=west)
    if west < 180.0 and east > -180.0:
        return _Turn()
    return _Turn(shift=360.0 * math.floor((west + 180.0) / 360.0))


class _Turned:
    """A pyproj transformer to or from a raster's geographic CRS (``into``: towards it) whose
    longitudes are turned (``_Turn``): the raster's side of it shifted or wrapped so."""

    def __init__(self, t: Transformer, turn: _Turn, into: bool) -> None:
        self.t, self.turn, self.into = t, turn, into

    def transform(self, x: ArrayLike, y: ArrayLike) -> tuple[Any, Any]:
        turn = self.turn
        if self.into:
            xs, ys = self.t.transform(x, y)
            xs = np.asarray(xs, np.float64)
            if turn.west is not None:
                return turn.west + np.mod(xs - turn.west, 360.0), ys
            return xs + turn.shift, ys
        x = np.asarray(x, np.float64)
        x = np.mod(x + 180.0, 360.0) - 180.0 if turn.west is not None else x - turn.shift
        out: tuple[Any, Any] = self.t.transform(x, y)
        return out


@dataclass(frozen=True)
class _Level:
    """One resolution of the source: 2^k level-0 pixels per pixel (sx, sy exactly for overviews)."""

    k: int
    height: int
    width: int
    sx: float
    sy: float
    #: Index of the file's own overview, or None for level 0 / an aligned block mean.
    overview: int | None


def _one_line(exc: BaseException) -> str:
    """The first line of the innermost message in an exception's chain, for SourceErrors."""
    # rasterio wraps GDAL's specific error in "Read failed. See previous exception for details."
    seen: list[BaseException] = []
    cur: BaseException | None = exc
    for _ in range(10):  # a bounded walk: chains can loop
        if cur is None:
            break
        if str(cur).strip():
            seen.append(cur)
        cur = cur.__cause__ or cur.__context__
    lines = [ln.strip() for ln in str(seen[-1] if seen else exc).splitlines() if ln.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _harmonic_fill(mean: F64, valid: B, holes: B) -> F64:
    """Heights for the ``holes`` cells solving Laplace's equation with the valid cells around
    them as the boundary: smooth, and bounded by the rim (no pit, no bump)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import spsolve

    rows, cols = np.nonzero(holes)
    n = rows.size
    index = np.full(holes.shape, -1, np.int64)
    index[rows, cols] = np.arange(n)
    hh, ww = holes.shape
    diag = np.zeros(n)
    rhs = np.zeros(n)
    ai, aj = [np.arange(n)], [np.arange(n)]
    vals: list[F64] = []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        r, c = rows + dr, cols + dc
        on = (r >= 0) & (r < hh) & (c >= 0) & (c < ww)
        r, c, me = r[on], c[on], np.flatnonzero(on)
        diag[me] += 1.0
        known = valid[r, c]
        rhs[me[known]] += mean[r[known], c[known]]
        unknown = index[r, c] >= 0
        ai.append(me[unknown])
        aj.append(index[r[unknown], c[unknown]])
        vals.append(np.full(int(unknown.sum()), -1.0))
    matrix = coo_matrix(
        (np.concatenate([diag, *vals]), (np.concatenate(ai), np.concatenate(aj))), shape=(n, n)
    ).tocsc()
    out: F64 = np.asarray(spsolve(matrix, rhs), np.float64)
    return out


def _halve(a: F64) -> F64:
    """Sums of 2×2 blocks (odd edges padded with zeros): one aligned step coarser."""
    h, w = a.shape
    if h % 2 or w % 2:
        a = np.pad(a, ((0, h % 2), (0, w % 2)))
    # a fixed element-wise order, so a block's sum never depends on the window it was read in
    return a[0::2, 0::2] + a[0::2, 1::2] + a[1::2, 0::2] + a[1::2, 1::2]


def _lattice_interp(
    values: F64,
    ci: NDArray[np.intp],
    ri: NDArray[np.intp],
    cols: NDArray[np.intp],
    rows: NDArray[np.intp],
) -> F64:
    """Bilinear interpolation of lattice ``values`` (at grid rows ``ri`` × columns ``ci``) at the
    grid's rows ``rows`` × columns ``cols``: two separable passes, not a gather per point."""
    k = np.clip(np.searchsorted(ci, cols, side="right") - 1, 0, ci.size - 2)
    t = (cols - ci[k]) / (ci[k + 1] - ci[k])
    across = values[:, k] * (1.0 - t) + values[:, k + 1] * t
    m = np.clip(np.searchsorted(ri, rows, side="right") - 1, 0, ri.size - 2)
    s = ((rows - ri[m]) / (ri[m + 1] - ri[m]))[:, None]
    out: F64 = across[m] * (1.0 - s) + across[m + 1] * s
    return out


def _bilinear(vals: F64, ok: B, u: F64, v: F64) -> tuple[F64, B]:
    """Bilinear values at pixel-centre coordinates (u column, v row) clamped into the array."""
    h, w = vals.shape
    u = np.clip(u, 0.0, w - 1.0)
    v = np.clip(v, 0.0, h - 1.0)
    j = np.minimum(np.floor(u).astype(np.intp), w - 2)
    i = np.minimum(np.floor(v).astype(np.intp), h - 2)
    fu = u - j
    fv = v - i
    gu = 1.0 - fu
    gv = 1.0 - fv
    out = gv * (gu * vals[i, j] + fu * vals[i, j + 1]) + fv * (
        gu * vals[i + 1, j] + fu * vals[i + 1, j + 1]
    )
    # a pixel with zero weight does not contribute, so its nodata does not invalidate the point
    good = (
        (ok[i, j] | (fu >= 1.0) | (fv >= 1.0))
        & (ok[i, j + 1] | (fu <= 0.0) | (fv >= 1.0))
        & (ok[i + 1, j] | (fu >= 1.0) | (fv <= 0.0))
        & (ok[i + 1, j + 1] | (fu <= 0.0) | (fv <= 0.0))
    )
    return out, good


class _GridSource:
    """Shared sampling over a north-up or rotated pixel grid; subclasses only read windows."""

    name: str
    crs_wkt: str
    bounds_merc: Bbox
    resolution_merc: float
    #: (rows, cols) of the full-resolution grid.
    shape: tuple[int, int]
    #: Affine transform of pixel edges (col, row) to source CRS coordinates.
    transform: Affine
    _closed: bool

    def _setup(
        self,
        name: str,
        crs: CRS,
        transform: Affine,
        shape: tuple[int, int],
        overviews: Sequence[tuple[int, int, int]] = (),
    ) -> None:
        """Validate georeferencing, project the footprint and build the coarse fill overview.

        ``overviews`` lists the file's own overviews as (index, rows, cols).
        """
        self.name = name
        self.crs_wkt = crs.to_wkt()
        self.shape = shape
        self.transform = transform
        self._crs = crs
        self._local = threading.local()
        h, w = shape
        coeffs = (transform.a, transform.b, transform.c, transform.d, transform.e, transform.f)
        if not all(math.isfinite(c) for c in coeffs) or transform.determinant == 0.0:
            raise SourceError(
                f"{name}: geotransform {coeffs} is not invertible; fix the georeferencing"
            )
        self._inv = ~transform
        self._turn = _turn(crs, transform, shape)
        self._kmax = (min(h, w) - 1).bit_length() - 1  # coarsest level still 2×2 pixels
        self._native: dict[int, _Level] = {}
        for index, oh, ow in overviews:
            fx, fy = w / ow, h / oh
            k = round(math.log2(fx)) if fx > 0 else -1
            # only overviews at an exact power-of-two factor stand in for a level
            exact = round(fx) == 1 << k and round(fy) == 1 << k
            if 1 <= k <= self._kmax and exact and k not in self._native and min(oh, ow) >= 2:
                self._native[k] = _Level(k, oh, ow, fx, fy, index)
        self._levels: dict[int, _Level] = {}
        self.bounds_merc = self._footprint()
        self.resolution_merc = self._resolution()
        self._build_coarse()

    # --- projections ----------------------------------------------------------------------

    def _transformer(self, key: str) -> Transformer:
        """A per-thread pyproj Transformer: "to_src" (EPSG:3857 → source), "to_merc", "to_ll"."""
        cache: dict[str, Transformer] | None = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = {}
        t = cache.get(key)
        if t is None:
            merc, ll = CRS.from_epsg(3857), CRS.from_epsg(4326)
            src, dst = {"to_src": (merc, self._crs), "to_merc": (self._crs, merc)}.get(
                key, (self._crs, ll)
            )
            t = Transformer.from_crs(src, dst, always_xy=True)
            if self._turn:
                t = _Turned(t, self._turn, key == "to_src")  # type: ignore[assignment]
            cache[key] = t
        return t

    def _footprint(self) -> Bbox:
        """EPSG:3857 bbox of the raster's densified edges, latitude clamped to ±MAX_LAT."""
        h, w = self.shape
        t = np.linspace(0.0, 1.0, _EDGE_POINTS + 1)
        cols = np.concatenate([t * w, np.full_like(t, w), (1.0 - t) * w, np.zeros_like(t)])
        rows = np.concatenate([np.zeros_like(t), t * h, np.full_like(t, h), (1.0 - t) * h])
        a = self.transform
        xs = a.a * cols + a.b * rows + a.c
        ys = a.d * cols + a.e * rows + a.f
        if self._crs.is_geographic and (np.abs(xs).max() > 540.0 or np.abs(ys).max() > 90.5):
            # degrees that are not: metres (UTM, a national grid) labelled with a lon/lat CRS
            raise SourceError(
                f"{self.name}: its coordinates ({xs.min():.6g}..{xs.max():.6g}, "
                f"{ys.min():.6g}..{ys.max():.6g}) are outside {_crs_name(self.crs_wkt)}'s valid "
                "range (longitude -180..180°, latitude -90..90°): the CRS is probably wrong; "
                "fix it (e.g. gdal_edit.py -a_srs EPSG:326NN)"
            )
        lon, lat = (np.asarray(v) for v in self._transformer("to_ll").transform(xs, ys))
        finite = np.isfinite(lon) & np.isfinite(lat)
        if not finite.any():
            raise SourceError(f"{self.name}: footprint cannot be projected to longitude/latitude")
        lo, hi = float(lat[finite].min()), float(lat[finite].max())
        # round the edges, longitudes unwrapped: back where they began, the data does not hold a
        # pole, and if they left -180..180 on the way, it straddles the antimeridian (a raster
        # all the way round, read from its first turn, spans the world instead)
        ring = np.degrees(np.unwrap(np.radians(lon[finite])))
        crossing = ring.min() < -180.0 or ring.max() > 180.0
        if self._turn.west is None and abs(ring[-1] - ring[0]) < 180.0 and crossing:
            west, east = float(ring.min()), float(ring.max())
            raise SourceError(
                f"{self.name}: the data crosses the antimeridian (its longitudes run "
                f"{west:.4f}° to {east:.4f}°), which Web Mercator tiles cannot span; split it at "
                "180° (e.g. gdalwarp -te) and use the two halves"
            )
        if lo >= MAX_LAT or hi <= -MAX_LAT:
            raise SourceError(
                f"{self.name}: data lies entirely outside Web Mercator's latitude range "
                f"(±{MAX_LAT:.4f}°; data spans {lo:.4f}° to {hi:.4f}°)"
            )
        xm, ym = (np.asarray(v) for v in self._transformer("to_merc").transform(xs, ys))
        # polar points overflow the projection: clamp to the square, or go through lon/lat
        bad = ~(np.isfinite(xm) & np.isfinite(ym))
        if bad.any():
            xm2, ym2 = lonlat_to_merc(lon[bad], lat[bad])
            xm, ym = xm.copy(), ym.copy()
            xm[bad], ym[bad] = xm2, ym2
        xm, ym = xm[finite], np.clip(ym[finite], -ORIGIN, ORIGIN)
        if self._turn.west is not None:
            return Bbox(-ORIGIN, float(ym.min()), ORIGIN, float(ym.max()))
        return Bbox(float(xm.min()), float(ym.min()), float(xm.max()), float(ym.max()))

    def _resolution(self) -> float:
        """Native pixel steps projected to EPSG:3857 at the footprint's centre; the finer one."""
        b = self.bounds_merc
        cx, cy = (b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0
        sx, sy = self._transformer("to_src").transform(cx, cy)
        a = self.transform
        xs = np.array([sx, sx + a.a, sx + a.b])
        ys = np.array([sy, sy + a.d, sy + a.e])
        xm, ym = (np.asarray(v) for v in self._transformer("to_merc").transform(xs, ys))
        steps = np.hypot(xm[1:] - xm[0], ym[1:] - ym[0])
        res = float(steps.min())
        if not (math.isfinite(res) and res > 0.0):
            raise SourceError(f"{self.name}: cannot work out the pixel size in Web Mercator")
        return res

    def _pixel_coords(self, xm: F64, ym: F64) -> tuple[F64, F64, B]:
        """Level-0 pixel-edge coordinates (col, row) of EPSG:3857 points, and which are inside."""
        xs, ys = self._transformer("to_src").transform(xm, ym)
        xs, ys = np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float64)
        inv = self._inv
        # a point the source's CRS cannot hold (far outside a UTM zone: infinite) is outside it
        # (NaN), not a warning (inf × a zero term)
        with np.errstate(invalid="ignore"):
            col = inv.a * xs + inv.b * ys + inv.c
            row = inv.d * xs + inv.e * ys + inv.f
        return col, row, self._inside(col, row)

    def _grid_pixel_coords(self, xs: F64, ys: F64) -> tuple[F64, F64, B]:
        """``_pixel_coords`` of the grid xs × ys (rows ys), projecting exactly only a lattice of
        every ``step``-th point and the grid's four edges, interpolating between, with ``step``
        halved until the interpolation stays within _LATTICE_TOL pixels at every lattice cell's
        centre. The edges are exact so that grids sharing one (neighbouring tiles) agree on it
        to the bit, whatever step each chose."""
        w, h = xs.size, ys.size
        step = _LATTICE
        while step > 1 and min(w, h) > 2 * step:
            ci = np.unique(np.r_[np.arange(0, w, step), w - 1])
            ri = np.unique(np.r_[np.arange(0, h, step), h - 1])
            lc, lr, _ = self._pixel_coords(*np.meshgrid(xs[ci], ys[ri]))
            jm, im = (ci[:-1] + ci[1:]) // 2, (ri[:-1] + ri[1:]) // 2
            ec, er, _ = self._pixel_coords(*np.meshgrid(xs[jm], ys[im]))
            err = max(
                float(np.abs(_lattice_interp(lc, ci, ri, jm, im) - ec).max()),
                float(np.abs(_lattice_interp(lr, ci, ri, jm, im) - er).max()),
            )
            if err <= _LATTICE_TOL:  # NaN (a point off the projection's domain) is not
                jj, ii = np.arange(w), np.arange(h)
                col = _lattice_interp(lc, ci, ri, jj, ii)
                row = _lattice_interp(lr, ci, ri, jj, ii)
                # the edges exactly: rows 0 and h-1, columns 0 and w-1
                ex = np.concatenate([xs, xs, np.full(h, xs[0]), np.full(h, xs[-1])])
                ey = np.concatenate([np.full(w, ys[0]), np.full(w, ys[-1]), ys, ys])
                bc, br, _ = self._pixel_coords(ex, ey)
                col[0], col[-1], col[:, 0], col[:, -1] = np.split(bc, [w, 2 * w, 2 * w + h])
                row[0], row[-1], row[:, 0], row[:, -1] = np.split(br, [w, 2 * w, 2 * w + h])
                return col, row, self._inside(col, row)
            step //= 2
        return self._pixel_coords(*np.meshgrid(xs, ys))

    def _inside(self, col: F64, row: F64) -> B:
        h, w = self.shape
        # a hair of slack: footprint edges come back a few ulps outside after two projections
        eps = 1e-6
        inside: B = (col >= -eps) & (col <= w + eps) & (row >= -eps) & (row <= h + eps)  # not NaN
        return inside

    # --- levels -------------------------------------------------------------------------

    def _build_coarse(self) -> None:
        """Aligned block means of the whole raster at ≤ COARSE_SIZE px, and a hole-filled copy:
        from the finest overview no finer than that where there is one (the file's own or the
        sidecar's: opening never reads the full resolution), else from every pixel."""
        h, w = self.shape
        m = 0
        while max(-(-h // (1 << m)), -(-w // (1 << m))) > COARSE_SIZE:
            m += 1
        f = 1 << m
        k = max((k for k in self._native if k <= m), default=0)
        lv = self._native.get(k)
        rh, rw = (h, w) if lv is None else (lv.height, lv.width)
        g = 1 << (m - k)  # level pixels per coarse cell
        # each overview pixel stands for 4^k of the raster's (those at the far edges for fewer)
        weight = float(1 << (2 * k))
        strip = g * max(1, _STRIP_PIXELS // (rw * g))  # a multiple of the block, so strips align
        sums, counts = [], []
        lo, hi = math.inf, -math.inf
        for r0 in range(0, rh, strip):
            vals, ok = self._read_raw(
                None if lv is None else lv.overview, r0, min(r0 + strip, rh), 0, rw
            )
            if ok.any():
                lo, hi = min(lo, float(vals[ok].min())), max(hi, float(vals[ok].max()))
            s, n = vals * weight, ok.astype(np.float64) * weight
            for _ in range(m - k):
                s, n = _halve(s), _halve(n)
            sums.append(s)
            counts.append(n)
        if lv is not None:
            # an overview's means hide single absurd pixels: the file's own statistics, if any
            stats = self._stated_range()
            if stats is not None:
                lo, hi = min(lo, stats[0]), max(hi, stats[1])
        self._m = m
        self._sum = np.concatenate(sums, axis=0)
        self._count = np.concatenate(counts, axis=0)
        valid = self._count > 0.0
        if not valid.any():
            raise SourceError(f"{self.name}: every pixel is nodata")
        self._check_heights(lo, hi)
        #: The lowest and highest valid height of the data (metres).
        self.data_range = (lo, hi)
        coarse = self._sum / np.maximum(self._count, 1.0)
        if not valid.all():
            # nearest valid pixel: fills holes and nodata margins without inventing heights
            from scipy.ndimage import distance_transform_edt  # (scipy.ndimage: 0.2 s to import)

            idx = distance_transform_edt(~valid, return_distances=False, return_indices=True)
            coarse = coarse[idx[0], idx[1]]
        # bilinear sampling needs 2 pixels a side: a 1-pixel-thin overview repeats its edge
        self._coarse = np.pad(coarse, ((0, coarse.shape[0] < 2), (0, coarse.shape[1] < 2)), "edge")
        self._coarse_ok = np.ones(self._coarse.shape, dtype=bool)
        # the block-mean geometry even where the file has an overview of this factor
        ch, cw = self._coarse.shape
        self._coarse_level = _Level(m, ch, cw, float(f), float(f), None)
        self._voids: tuple[NDArray[np.float64], B] | None = None
        self._seas: dict[float, B] = {}
        #: A summed-area table of the coarse cells with data (``has_data``), made when asked.
        self._data_table: NDArray[np.int64] | None = None

    def _stated_range(self) -> tuple[float, float] | None:
        """The band's minimum and maximum as its metadata states them (GDAL's statistics), in
        metres; None where it states none."""
        return None

    def _void_grid(self) -> tuple[NDArray[np.float64], B]:
        """The coarse grid with its voids inside the data filled from their rims (a harmonic
        fill: every filled height lies between its rim's lowest and highest, as gdal_fillnodata
        keeps to), and which cells lie inside the data: not on a void that reaches the raster's
        edge (a nodata collar, the world outside)."""
        if self._voids is not None:
            return self._voids
        valid = self._count > 0.0
        mean = self._sum / np.maximum(self._count, 1.0)
        if valid.all():
            # nothing to find (most DEMs): no SciPy to import on the way to the first picture
            inside = np.ones(valid.shape, bool)
        else:
            from scipy.ndimage import label

            labels, _ = label(~valid)
            edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
            inside = ~np.isin(labels, edge[edge > 0])
        holes = inside & ~valid
        filled = mean.copy()
        if holes.any():
            filled[holes] = _harmonic_fill(mean, valid, holes)
        # bilinear sampling needs 2 cells a side, as the coarse overview's
        pad = ((0, filled.shape[0] < 2), (0, filled.shape[1] < 2))
        self._voids = (np.pad(filled, pad, "edge"), np.pad(inside, pad, "edge"))
        return self._voids

    def _sea_grid(self, level: float) -> B:
        """Coarse cells of the sea a DEM stores as exactly ``level`` (SRTM's 0 m): cells of
        that height alone, joined to the raster's edge or to the world outside the data by
        others of it (a level lake inland is left land)."""
        got = self._seas.get(level)
        if got is not None:
            return got
        valid = self._count > 0.0
        mean = self._sum / np.maximum(self._count, 1.0)
        flat = valid & (mean == level)
        sea = flat  # no cell at exactly that height: no sea (and no SciPy to import)
        if flat.any():
            from scipy.ndimage import label

            _, inside = self._void_grid()
            ch, cw = self._count.shape
            outside = ~inside[:ch, :cw]
            labels, _ = label(flat | outside)
            edge = np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])
            touching = np.unique(np.concatenate([edge, labels[outside]]))
            sea = flat & np.isin(labels, touching[touching > 0])
        pad = ((0, sea.shape[0] < 2), (0, sea.shape[1] < 2))
        self._seas[level] = got = np.pad(sea, pad, "edge")
        return got

    def sea_share(self, level: float) -> float:
        """The share of the raster's pixels (0..1) in the sea it stores as exactly ``level``."""
        sea = self._sea_grid(level)
        ch, cw = self._count.shape
        return float(self._count[sea[:ch, :cw]].sum()) / float(self.shape[0] * self.shape[1])

    def sea_at(self, xm: ArrayLike, ym: ArrayLike, level: float) -> B:
        """Which EPSG:3857 points lie in the sea the raster stores as exactly ``level``."""
        sea = self._sea_grid(level)
        shape, _, _, on, i, j = self._coarse_cells(xm, ym, sea.shape)
        out: B = (on & sea[i, j]).reshape(shape)
        return out

    def _coarse_cells(
        self, xm: ArrayLike, ym: ArrayLike, cells: tuple[int, ...]
    ) -> tuple[tuple[int, ...], F64, F64, B, NDArray[np.int64], NDArray[np.int64]]:
        """EPSG:3857 points (broadcast, flattened) on the coarse grid: their shape, pixel column
        and row clamped to the raster, whether they fall on it, and the coarse cell (row,
        column) of ``cells`` each lies in."""
        xb, yb = np.broadcast_arrays(
            np.asarray(xm, dtype=np.float64), np.asarray(ym, dtype=np.float64)
        )
        col, row, on = self._pixel_coords(xb.ravel(), yb.ravel())
        h, w = self.shape
        lv = self._coarse_level
        col = np.clip(np.nan_to_num(col), 0.0, float(w))
        row = np.clip(np.nan_to_num(row), 0.0, float(h))
        i = np.clip(np.floor(row / lv.sy).astype(np.int64), 0, cells[0] - 1)
        j = np.clip(np.floor(col / lv.sx).astype(np.int64), 0, cells[1] - 1)
        return xb.shape, col, row, on, i, j

    @property
    def void_share(self) -> float:
        """The share of the raster's pixels (0..1) without data inside the data's footprint:
        voids that ``interpolate`` fills from their rims (the rest is the world outside)."""
        _, inside = self._void_grid()
        h, w = self.shape
        f = 1 << self._m
        rows = np.minimum(f, h - np.arange(self._count.shape[0]) * f)
        cols = np.minimum(f, w - np.arange(self._count.shape[1]) * f)
        # (counts from an overview may overstate the raster's last row and column of cells)
        missing = np.maximum(rows[:, None] * cols[None, :] - self._count, 0.0)
        # a partly valid cell beside the world outside holds the collar's edge, not a void
        ch, cw = self._count.shape
        from scipy.ndimage import binary_dilation

        near_out = ~binary_dilation(~inside[:ch, :cw], np.ones((3, 3), bool), border_value=1)
        return float(missing[inside[:ch, :cw] & near_out].sum()) / float(h * w)

    def void_fill(self, xm: ArrayLike, ym: ArrayLike) -> tuple[NDArray[np.float32], B]:
        """Heights of the voids inside the data, filled from their rims, at EPSG:3857 points,
        and which points lie inside the data (False: outside the raster, or on a void that
        reaches its edge)."""
        filled, inside = self._void_grid()
        shape, col, row, on, i, j = self._coarse_cells(xm, ym, inside.shape)
        lv = self._coarse_level
        out, _ = _bilinear(
            filled, np.ones(filled.shape, bool), col / lv.sx - 0.5, row / lv.sy - 0.5
        )
        ok = on & inside[i, j]
        return out.astype(np.float32).reshape(shape), ok.reshape(shape)

    @property
    def valid_share(self) -> float:
        """The share of the raster's pixels that hold data (0..1)."""
        h, w = self.shape
        return min(1.0, float(self._count.sum()) / float(h * w))

    def _check_heights(self, lo: float, hi: float) -> None:
        """Refuse heights no terrain has: an undeclared nodata value, or not metres."""
        low, high = HEIGHT_LIMITS
        if lo >= low and hi <= high:
            return
        bad = lo if lo < low else hi
        raise SourceError(
            f"{self.name}: height {bad:.6g} is outside {low:.0f}..{high:.0f} m: an undeclared "
            f"nodata value (declare it with --nodata {bad:.6g}) or heights not in metres"
        )

    def _level(self, k: int) -> _Level:
        """Level k: the file's own overview of factor 2^k, else the aligned 2^k block mean."""
        lv = self._levels.get(k)
        if lv is None:
            lv = self._native.get(k)
            if lv is None:
                h, w = self.shape
                f = 1 << k
                lv = _Level(k, -(-h // f), -(-w // f), float(f), float(f), None)
            self._levels[k] = lv
        return lv

    def _level_for(self, spacing: float) -> _Level:
        """The level whose pixels fit a sampling grid of ``spacing`` EPSG:3857 metres."""
        ratio = spacing / self.resolution_merc
        if not ratio >= 2.0:  # NaN included
            k = 0
        elif math.isinf(ratio):
            k = self._kmax
        else:
            k = math.floor(math.log2(ratio))
        return self._level(min(k, self._kmax))

    def _window(self, lv: _Level, i0: int, i1: int, j0: int, j1: int) -> tuple[F64, B]:
        """Values (0 where invalid) and validity of level pixels [i0:i1, j0:j1]."""
        if lv.overview is not None:
            return self._read_raw(lv.overview, i0, i1, j0, j1)
        k, m = lv.k, self._m
        if k >= m:
            # from the cached level m, by the same 2×2 steps a full read would take
            g = 1 << (k - m)
            hm, wm = self._sum.shape
            rows, cols = slice(i0 * g, min(i1 * g, hm)), slice(j0 * g, min(j1 * g, wm))
            s, n = self._sum[rows, cols], self._count[rows, cols]
            steps = k - m
        else:
            h, w = self.shape
            f = 1 << k
            s, ok = self._read_raw(None, i0 * f, min(i1 * f, h), j0 * f, min(j1 * f, w))
            if k == 0:
                return s, ok
            n = ok.astype(np.float64)
            steps = k
        for _ in range(steps):
            s, n = _halve(s), _halve(n)
        return s / np.maximum(n, 1.0), n > 0.0

    def _read_raw(self, overview: int | None, r0: int, r1: int, c0: int, c1: int) -> tuple[F64, B]:
        """Heights (metres, 0 where invalid) and validity of pixels [r0:r1, c0:c1] of a level."""
        raise NotImplementedError

    # --- public API -----------------------------------------------------------------------

    def sample(
        self, xm: ArrayLike, ym: ArrayLike, spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Bilinear heights at EPSG:3857 points (any shape), read at the level for ``spacing``."""
        xb, yb = np.broadcast_arrays(
            np.asarray(xm, dtype=np.float64), np.asarray(ym, dtype=np.float64)
        )
        if self._closed:
            raise SourceError(f"{self.name}: source is closed")
        col, row, inside = self._pixel_coords(xb.ravel(), yb.ravel())
        h, valid = self._sample_pixels(col, row, inside, spacing)
        return h.reshape(xb.shape), valid.reshape(xb.shape)

    def sample_grid(
        self, xs: ArrayLike, ys: ArrayLike, spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """``sample`` on the grid of columns ``xs`` and rows ``ys``, (len(ys), len(xs)): the
        projection is exact on a lattice and the grid's edges and interpolated between, off by
        at most 1/1000 of a pixel inside (so a height by at most that share of a pixel's rise).
        A 256² texture's grid projects about 1,600 points instead of 66,000 (12 ms of pyproj
        each on the development machine)."""
        if self._closed:
            raise SourceError(f"{self.name}: source is closed")
        xs = np.asarray(xs, dtype=np.float64).ravel()
        ys = np.asarray(ys, dtype=np.float64).ravel()
        col, row, inside = self._grid_pixel_coords(xs, ys)
        h, valid = self._sample_pixels(col.ravel(), row.ravel(), inside.ravel(), spacing)
        return h.reshape(ys.size, xs.size), valid.reshape(ys.size, xs.size)

    def _sample_pixels(
        self, col: F64, row: F64, inside: B, spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        heights = np.zeros(col.shape, dtype=np.float64)
        valid = np.zeros(col.shape, dtype=bool)
        idx = np.flatnonzero(inside)
        if idx.size:
            lv = self._level_for(float(spacing))
            u = np.clip(col[idx] / lv.sx - 0.5, 0.0, lv.width - 1.0)
            v = np.clip(row[idx] / lv.sy - 0.5, 0.0, lv.height - 1.0)
            # the smallest window holding every point's 2×2 neighbourhood
            j0 = min(int(np.floor(u.min())), lv.width - 2)
            i0 = min(int(np.floor(v.min())), lv.height - 2)
            j1 = min(int(np.floor(u.max())) + 2, lv.width)
            i1 = min(int(np.floor(v.max())) + 2, lv.height)
            vals, ok = self._window(lv, i0, i1, j0, j1)
            heights[idx], valid[idx] = _bilinear(vals, ok, u - j0, v - i0)
        bad = np.flatnonzero(~valid)
        if bad.size:
            heights[bad] = self._fill(col[bad], row[bad])
        return heights.astype(np.float32), valid

    def pixels_in(self, box: Bbox) -> Iterator[tuple[F64, F64, F64]]:
        """The data's own samples inside an EPSG:3857 box: (x, y, height) of every valid pixel
        centre, in chunks of rows (so a box over the whole raster never loads it at once)."""
        t = np.linspace(0.0, 1.0, 33)
        ex = np.concatenate(
            [
                box.left + t * (box.right - box.left),
                np.full(33, box.right),
                box.left + t * (box.right - box.left),
                np.full(33, box.left),
            ]
        )
        ey = np.concatenate(
            [
                np.full(33, box.top),
                box.bottom + t * (box.top - box.bottom),
                np.full(33, box.bottom),
                box.bottom + t * (box.top - box.bottom),
            ]
        )
        col, row, _ = self._pixel_coords(ex, ey)
        good = np.isfinite(col) & np.isfinite(row)
        if not good.any():
            return
        h, w = self.shape
        # the projected box's edges bound it only up to their curvature: one pixel of slack
        c0 = max(int(np.floor(col[good].min())) - 1, 0)
        c1 = min(int(np.ceil(col[good].max())) + 1, w)
        r0 = max(int(np.floor(row[good].min())) - 1, 0)
        r1 = min(int(np.ceil(row[good].max())) + 1, h)
        if c0 >= c1 or r0 >= r1:
            return
        step = max(1, _STRIP_PIXELS // 8 // (c1 - c0))
        a = self.transform
        for ra in range(r0, r1, step):
            rb = min(ra + step, r1)
            vals, ok = self._read_raw(None, ra, rb, c0, c1)
            cc, rr = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(ra, rb) + 0.5)
            cc, rr, v = cc[ok], rr[ok], vals[ok]
            xs = a.a * cc + a.b * rr + a.c
            ys = a.d * cc + a.e * rr + a.f
            xm, ym = (np.asarray(q) for q in self._transformer("to_merc").transform(xs, ys))
            inside = (xm >= box.left) & (xm <= box.right) & (ym >= box.bottom) & (ym <= box.top)
            if inside.any():
                yield xm[inside], ym[inside], v[inside]

    def sample_nodata(
        self, xm: ArrayLike, ym: ArrayLike
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """What ``sample`` gives at points where there is no data, without reading a pixel:
        the coarse hole-filled overview's heights, and no point valid."""
        xb, yb = np.broadcast_arrays(
            np.asarray(xm, dtype=np.float64), np.asarray(ym, dtype=np.float64)
        )
        col, row, _ = self._pixel_coords(xb.ravel(), yb.ravel())
        h = self._fill(col, row).astype(np.float32).reshape(xb.shape)
        return h, np.zeros(xb.shape, dtype=bool)

    def has_data(self, left: ArrayLike, bottom: ArrayLike, right: ArrayLike, top: ArrayLike) -> B:
        """Which EPSG:3857 boxes may hold a valid pixel, from the coarse overview made on
        opening (no pixel read): each box's extent in the raster's pixels (a 5×5 lattice of it
        projected, grown by a coarse cell for the edges' curvature) holds a cell with data
        (a summed-area table of the cells, so a box costs the same whatever its size)."""
        lo, bo, ri, to = (
            np.atleast_1d(np.asarray(v, np.float64)) for v in (left, bottom, right, top)
        )
        table = self._data_table
        if table is None:
            has = (self._count > 0.0).astype(np.int64)
            table = self._data_table = np.pad(has.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
        f = np.linspace(0.0, 1.0, 5)
        px = lo[:, None, None] + f[None, None, :] * (ri - lo)[:, None, None]
        py = bo[:, None, None] + f[None, :, None] * (to - bo)[:, None, None]
        pxb, pyb = np.broadcast_arrays(px, py)
        col, row, _ = self._pixel_coords(pxb.ravel(), pyb.ravel())
        col, row = col.reshape(lo.size, -1), row.reshape(lo.size, -1)
        lv = self._coarse_level
        ch, cw = self._count.shape
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a box wholly off the projection
            j0 = np.floor(np.nanmin(col, axis=1) / lv.sx) - 1
            j1 = np.floor(np.nanmax(col, axis=1) / lv.sx) + 2
            i0 = np.floor(np.nanmin(row, axis=1) / lv.sy) - 1
            i1 = np.floor(np.nanmax(row, axis=1) / lv.sy) + 2
        ok = np.isfinite(j0) & np.isfinite(j1) & np.isfinite(i0) & np.isfinite(i1)
        j0, j1 = (np.clip(np.nan_to_num(v), 0, cw).astype(np.int64) for v in (j0, j1))
        i0, i1 = (np.clip(np.nan_to_num(v), 0, ch).astype(np.int64) for v in (i0, i1))
        inside = table[i1, j1] - table[i0, j1] - table[i1, j0] + table[i0, j0]
        out: B = ok & (j1 > j0) & (i1 > i0) & (inside > 0)
        return out

    def covers(self, xm: ArrayLike, ym: ArrayLike) -> NDArray[np.bool_]:
        """Which EPSG:3857 points (broadcast together) fall on the raster, nodata holes included."""
        xb, yb = np.broadcast_arrays(
            np.asarray(xm, dtype=np.float64), np.asarray(ym, dtype=np.float64)
        )
        _, _, inside = self._pixel_coords(xb.ravel(), yb.ravel())
        return inside.reshape(xb.shape)

    def _fill(self, col: F64, row: F64) -> F64:
        """Heights of the coarse hole-filled overview, clamped to the raster (edges extended)."""
        h, w = self.shape
        lv = self._coarse_level
        col = np.clip(np.nan_to_num(col), 0.0, float(w))
        row = np.clip(np.nan_to_num(row), 0.0, float(h))
        out, _ = _bilinear(self._coarse, self._coarse_ok, col / lv.sx - 0.5, row / lv.sy - 0.5)
        return out

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """Heights on the vertices of a (rows, cols) grid spanning ``bounds`` (row 0 north)."""
        rows, cols = shape
        if rows < 2 or cols < 2:
            raise ValueError(f"Expected a grid of at least 2×2 vertices, got {rows}×{cols}")
        left, bottom, right, top = (float(v) for v in bounds)
        x = left + np.arange(cols) * (right - left) / (cols - 1)
        y = top - np.arange(rows) * (top - bottom) / (rows - 1)
        # the far edges exactly, so neighbouring windows share bit-equal edge coordinates
        x[-1], y[-1] = right, bottom
        return self.sample_grid(x, y, (right - left) / (cols - 1))

    def close(self) -> None:
        """Release the data; further samples raise SourceError."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        h, w = self.shape
        return f"{type(self).__name__}({self.name!r}, {w}×{h} px, {self.resolution_merc:.3g} m)"


class RasterSource(_GridSource):
    """One band of any GDAL raster read through rasterio, in any CRS; heights in metres."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        band: int | None = None,
        nodata: float | None = None,
        z_units: str | None = None,
    ) -> None:
        self.path = os.fspath(path)
        self._z_units = z_units
        name = self.path
        self._lock = threading.Lock()
        self._closed = False
        self._band = 1 if band is None else band
        self._nodata = nodata
        self._overview_ds: list[Any] = []
        try:
            with warnings.catch_warnings():
                # a raster without georeferencing is reported below, as a SourceError
                warnings.simplefilter("ignore", NotGeoreferencedWarning)
                self._ds: Any = rasterio.open(self.path)
        except Exception as exc:  # rasterio/GDAL raise several unrelated classes here
            if not self.path.startswith("/vsi") and not os.path.exists(self.path):
                raise SourceError(f"{name}: no such file") from None
            # the message names the file, as the error's start does already
            reason = re.sub(r"^.*?'" + re.escape(self.path) + r"'\s*", "", _one_line(exc))
            raise SourceError(f"{name}: not a raster that GDAL can read ({reason})") from None
        try:
            self._init_dataset(name, band)
        except BaseException:
            self.close()
            raise

    def _init_dataset(self, name: str, asked: int | None) -> None:
        ds = self._ds
        band = self._band
        if asked is None and ds.count > 1:
            # an alpha band beside one height band is a mask, not a second choice
            kinds = [str(getattr(c, "name", c)).lower() for c in ds.colorinterp]
            heights = [i + 1 for i, k in enumerate(kinds) if k != "alpha"]
            if len(heights) != 1:
                raise SourceError(
                    f"{name}: has {ds.count} bands; a DEM is one band of heights: pick it with "
                    "--band N"
                )
            band = self._band = heights[0]
        if not 1 <= band <= ds.count:
            raise SourceError(f"{name}: band {band} does not exist (the raster has {ds.count})")
        dtype = np.dtype(ds.dtypes[band - 1])
        if dtype.kind not in "iuf":
            raise SourceError(f"{name}: band {band} holds {dtype} values; need integers or floats")
        if ds.width < 2 or ds.height < 2:
            raise SourceError(f"{name}: raster is {ds.width}×{ds.height} pixels; need at least 2×2")
        #: One line on where the CRS came from, where the file does not state one (None).
        self.crs_note: str | None = None
        transform, stated = ds.transform, ds.crs
        gcps, gcp_crs = ds.gcps if stated is None else ([], None)
        if gcps and gcp_crs is not None:
            # ground control points alone: read on their affine fit where it holds them all
            # (what gdalwarp's first order makes of them), else warped first
            transform, self.crs_note = gcp_placement(name, gcps, gcp_crs)
            stated = gcp_crs
        if stated is not None:
            try:
                crs = CRS.from_wkt(stated.to_wkt())
            except Exception as exc:  # pyproj's CRSError, or rasterio's on export
                raise SourceError(f"{name}: unusable CRS ({_one_line(exc)})") from None
        elif ds.rpcs is not None:
            raise SourceError(
                f"{name}: georeferenced by rational polynomial coefficients (RPCs) alone; "
                f"orthorectify it onto a grid first (e.g. gdalwarp -rpc -t_srs EPSG:4326 {name} "
                "ortho.tif)"
            )
        elif not _cf_lonlat(ds.tags()):
            # gdal_edit.py changes a GeoTIFF in place; other formats are copied to one
            stem = os.path.splitext(os.path.basename(name))[0]
            fix = (
                f"gdal_edit.py -a_srs EPSG:4326 {name}"
                if ds.driver == "GTiff"
                else f"gdal_translate -a_srs EPSG:4326 {name} {stem}.tif"
            )
            raise SourceError(f"{name}: raster has no CRS; georeference it first (e.g. {fix})")
        else:
            # CF's coordinates named longitude and latitude in degrees: WGS 84's, as CF says
            # where no grid mapping is given (QGIS and xarray read them so)
            crs = CRS.from_epsg(4326)
            self.crs_note = (
                f"{name}: no CRS stated; its coordinates are longitude and latitude in degrees "
                "(CF's degrees_east and degrees_north): read as WGS 84 (EPSG:4326)"
            )
        self._scale = float(ds.scales[band - 1] if ds.scales else 1.0)
        self._offset = float(ds.offsets[band - 1] if ds.offsets else 0.0)
        said: str | None = "--z-units"
        if self._z_units is not None:
            factor = parse_z_units(self._z_units)
        else:
            factor, said = _z_units(ds, band, crs)
        #: Metres per unit of the band's heights (after its scale and offset).
        self.z_factor = factor
        #: One line on where the height unit came from, where it is not plain metres (None).
        self.z_note: str | None = None
        if factor != 1.0 and self._z_units is None:
            self.z_note = (
                f"{name}: heights read as {_unit_name(factor)} (from {said}) and converted to "
                "metres; give --z-units m if they are metres"
            )
        self._scale *= factor
        self._offset *= factor
        overviews = []
        where = self.path
        if not ds.overviews(band) and max(ds.width, ds.height) > SIDECAR_MIN_SIZE:
            # no overviews of its own: coarse levels would read every pixel under them
            where = sidecar_overviews(self.path, ds, band, self._nodata) or self.path
        if where == self.path:
            count = len(ds.overviews(band))
        else:
            with rasterio.open(where) as sidecar:
                count = len(sidecar.overviews(1))
        for index in range(count):
            try:
                ov = rasterio.open(where, overview_level=index)
            except Exception:  # an overview GDAL cannot open is simply not used
                continue
            self._overview_ds.append(ov)
            overviews.append((len(self._overview_ds) - 1, ov.height, ov.width))
        #: The sidecar VRT whose overviews are read (None: the file's own, if any).
        self.sidecar = None if where == self.path else where
        self._overview_band = band if where == self.path else 1
        self._setup(name, crs, transform, (ds.height, ds.width), overviews)

    def _stated_range(self) -> tuple[float, float] | None:
        try:
            tags = self._ds.tags(self._band)
            lo, hi = float(tags["STATISTICS_MINIMUM"]), float(tags["STATISTICS_MAXIMUM"])
        except (KeyError, ValueError, TypeError):
            return None
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return None
        a, b = lo * self._scale + self._offset, hi * self._scale + self._offset
        nd = self._nodata if self._nodata is not None else self._ds.nodatavals[self._band - 1]
        if nd is not None and float(nd) in (lo, hi):
            return None  # statistics that counted the nodata value
        return min(a, b), max(a, b)

    def _read_raw(self, overview: int | None, r0: int, r1: int, c0: int, c1: int) -> tuple[F64, B]:
        """Heights (metres, 0 where invalid) and validity of pixels [r0:r1, c0:c1] of a level."""
        window = Window(c0, r0, c1 - c0, r1 - r0)
        with self._lock:
            if self._closed:
                raise SourceError(f"{self.name}: source is closed")
            ds = self._ds if overview is None else self._overview_ds[overview]
            band = self._band if overview is None else self._overview_band
            try:
                data = ds.read(band, window=window, masked=True)
            except Exception as exc:  # GDAL errors surface as several rasterio classes
                raise SourceError(f"{self.name}: read failed: {_one_line(exc)}") from None
        raw = np.ma.getdata(data)
        vals = raw.astype(np.float64)
        ok = ~np.ma.getmaskarray(data)
        if self._nodata is not None:
            # compared in the file's own type: -3.4e38 is not exactly a float32
            nd = np.float64(self._nodata)
            ok &= (raw != raw.dtype.type(nd)) if raw.dtype.kind == "f" else (vals != nd)
        if self._scale != 1.0 or self._offset != 0.0:
            vals = vals * self._scale + self._offset
        ok &= np.isfinite(vals)
        vals[~ok] = 0.0
        return vals, ok

    @property
    def notes(self) -> list[str]:
        """What the file left unsaid and was read as (its CRS, its height unit): one line each,
        for the app to say once on stderr."""
        return [n for n in (self.crs_note, self.z_note) if n is not None]

    def close(self) -> None:
        """Close the dataset and its overviews; further samples raise SourceError."""
        with self._lock:
            self._closed = True
            for ds in [getattr(self, "_ds", None), *self._overview_ds]:
                if ds is not None:
                    ds.close()
            self._overview_ds = []


#: Rasters wider or taller than this without overviews of their own get sidecar overviews.
SIDECAR_MIN_SIZE = 4096

_GDAL_TYPES = {
    "uint8": "Byte",
    "int8": "Int8",
    "uint16": "UInt16",
    "int16": "Int16",
    "uint32": "UInt32",
    "int32": "Int32",
    "float32": "Float32",
    "float64": "Float64",
}


def overview_cache() -> str:
    """Where sidecar overviews are kept: ``overviews`` in lodscape's cache folder."""
    return str(user_cache() / "overviews")


def sidecar_overviews(path: str, ds: Any, band: int, nodata: float | None) -> str | None:
    """Overviews (averages, factors 2, 4, … down to 256 pixels) of a raster that has none,
    built once as ``gdaladdo`` would, but beside a VRT of the band in the overview cache, so
    the user's folder is never written to; the VRT's path (None where they cannot be built:
    the raster is read without them, as before)."""
    import hashlib
    import html

    from rasterio.enums import Resampling

    try:
        st = os.stat(path)
    except OSError:
        return None  # not a plain file (/vsi…): read as it is
    full = os.path.abspath(path)
    key = hashlib.sha1(
        f"{full}|{st.st_size}|{st.st_mtime_ns}|{band}|{nodata}".encode()
    ).hexdigest()[:16]
    folder = overview_cache()
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", os.path.basename(path))[:60]
    vrt = os.path.join(folder, f"{stem}-{key}.vrt")
    if os.path.exists(vrt) and os.path.exists(vrt + ".ovr"):
        return vrt
    dtype = _GDAL_TYPES.get(str(ds.dtypes[band - 1]))
    if dtype is None:
        return None
    nd = nodata if nodata is not None else ds.nodatavals[band - 1]
    nd_xml = "" if nd is None else f"<NoDataValue>{float(nd)!r}</NoDataValue>"
    t = ds.transform
    doc = (
        f'<VRTDataset rasterXSize="{ds.width}" rasterYSize="{ds.height}">'
        f"<SRS>{html.escape(ds.crs.to_wkt())}</SRS>"
        f"<GeoTransform>{t.c!r}, {t.a!r}, {t.b!r}, {t.f!r}, {t.d!r}, {t.e!r}</GeoTransform>"
        f'<VRTRasterBand dataType="{dtype}" band="1">{nd_xml}<SimpleSource>'
        f'<SourceFilename relativeToVRT="0">{html.escape(full)}</SourceFilename>'
        f"<SourceBand>{band}</SourceBand></SimpleSource></VRTRasterBand></VRTDataset>"
    )
    factors = []
    f = 2
    while max(ds.width, ds.height) / f >= 256:
        factors.append(f)
        f *= 2
    tmp = os.path.join(folder, f".{stem}-{key}.{os.getpid()}.vrt")
    try:
        os.makedirs(folder, exist_ok=True)
        with open(tmp, "w") as out:
            out.write(doc)
        with rasterio.Env(COMPRESS_OVERVIEW="DEFLATE"), rasterio.open(tmp, "r+") as v:
            v.build_overviews(factors, Resampling.average)
        os.replace(tmp + ".ovr", vrt + ".ovr")
        os.replace(tmp, vrt)
    except Exception:  # no space, a read-only cache, a GDAL that cannot: read without them
        for leftover in (tmp, tmp + ".ovr"):
            with contextlib.suppress(OSError):
                os.unlink(leftover)
        return None
    return vrt


class ArraySource(_GridSource):
    """In-memory heights (metres, row 0 at the transform's origin) with an affine transform."""

    def __init__(
        self,
        heights: ArrayLike,
        transform: Affine | Sequence[float],
        crs: Any = "EPSG:3857",
        nodata: float | None = None,
    ) -> None:
        name = "array"
        a = np.asarray(heights)
        if a.ndim != 2 or a.dtype.kind not in "iuf":
            raise SourceError(
                f"{name}: expected a 2-D array of integers or floats, got {a.dtype} {a.shape}"
            )
        if a.shape[0] < 2 or a.shape[1] < 2:
            raise SourceError(
                f"{name}: raster is {a.shape[1]}×{a.shape[0]} pixels; need at least 2×2"
            )
        if not isinstance(transform, Affine):
            transform = Affine(*(float(v) for v in list(transform)[:6]))
        try:
            crs_obj = CRS.from_user_input(crs)
        except Exception as exc:  # pyproj's CRSError on anything it cannot parse
            raise SourceError(f"{name}: unusable CRS {crs!r} ({_one_line(exc)})") from None
        vals = a.astype(np.float64)  # a copy: later edits to the caller's array do not leak in
        ok = np.isfinite(vals)
        if nodata is not None:
            ok &= vals != nodata
        vals[~ok] = 0.0
        self._values, self._ok = vals, ok
        self._closed = False
        self._setup(name, crs_obj, transform, (a.shape[0], a.shape[1]))

    def _read_raw(self, overview: int | None, r0: int, r1: int, c0: int, c1: int) -> tuple[F64, B]:
        """Heights (0 where invalid) and validity of pixels [r0:r1, c0:c1]."""
        if self._closed:
            raise SourceError(f"{self.name}: source is closed")
        return self._values[r0:r1, c0:c1], self._ok[r0:r1, c0:c1]

    def close(self) -> None:
        """Mark the source closed; further samples raise SourceError."""
        self._closed = True


class MosaicSource:
    """Several height sources as one, each point from the finest source with data there.

    Sources in different CRSs are each reprojected on the fly; ``open_rasters`` refuses them
    unless asked, as gdalbuildvrt does, since mixing them is more often a mistake than a plan.
    """

    def __init__(self, sources: Sequence[HeightSource]) -> None:
        if not sources:
            raise SourceError("no height sources to mosaic")
        # finest first: where sources overlap, the more detailed one wins
        self.sources = sorted(sources, key=lambda s: s.resolution_merc)
        names = [s.name for s in sources]
        self.name = names[0] if len(names) == 1 else f"{names[0]} (+{len(names) - 1} more)"
        self.crs_wkt = self.sources[0].crs_wkt
        boxes = np.array([tuple(s.bounds_merc) for s in self.sources])
        self.bounds_merc = Bbox(
            float(boxes[:, 0].min()),
            float(boxes[:, 1].min()),
            float(boxes[:, 2].max()),
            float(boxes[:, 3].max()),
        )
        self.resolution_merc = float(self.sources[0].resolution_merc)
        # the lowest and highest valid height of them all, where each knows its own (a
        # raster's overview does): sources far apart leave a sample over their joint box
        # nothing to find
        known = [getattr(s, "data_range", None) for s in self.sources]
        if all(r is not None for r in known):
            #: The lowest and highest valid height of the data (metres).
            self.data_range = (min(r[0] for r in known), max(r[1] for r in known))  # type: ignore[index]

    def _combine(
        self, parts: Sequence[tuple[NDArray[np.float32], NDArray[np.bool_]]]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        h, valid = parts[0][0].copy(), parts[0][1].copy()
        for hk, vk in parts[1:]:
            take = vk & ~valid
            h[take] = hk[take]
            valid |= vk
        return h, valid

    def sample(
        self, xm: ArrayLike, ym: ArrayLike, spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        return self._combine([s.sample(xm, ym, spacing) for s in self.sources])  # type: ignore[arg-type]

    def sample_grid(
        self, xs: ArrayLike, ys: ArrayLike, spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        return self._combine([s.sample_grid(xs, ys, spacing) for s in self.sources])  # type: ignore[arg-type]

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        return self._combine([s.read(bounds, shape) for s in self.sources])

    def pixels_in(self, box: Bbox) -> Iterator[tuple[F64, F64, F64]]:
        """Each source's samples where no finer source has data (what ``sample`` reads)."""
        for i, src in enumerate(self.sources):
            for xm, ym, h in src.pixels_in(box):
                keep = np.ones(xm.size, dtype=bool)
                for finer in self.sources[:i]:
                    _, valid = finer.sample(xm, ym, finer.resolution_merc)
                    keep &= ~valid
                if keep.any():
                    yield xm[keep], ym[keep], h[keep]

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        out = self.sources[0].covers(xm, ym)
        for s in self.sources[1:]:
            out = out | s.covers(xm, ym)
        return out

    def sample_nodata(
        self, xm: ArrayLike, ym: ArrayLike
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """What ``sample`` gives where no source has data (the finest one's fill), unread."""
        return self.sources[0].sample_nodata(xm, ym)  # type: ignore[attr-defined, no-any-return]

    def has_data(self, left: ArrayLike, bottom: ArrayLike, right: ArrayLike, top: ArrayLike) -> B:
        """Which boxes any source may hold a valid pixel in (``_GridSource.has_data``)."""
        out: B | None = None
        for s in self.sources:
            got = s.has_data(left, bottom, right, top)  # type: ignore[attr-defined]
            out = got if out is None else out | got
        assert out is not None
        return out

    def sea_at(self, xm: ArrayLike, ym: ArrayLike, level: float) -> B:
        """Points in the sea any source stores as exactly ``level``."""
        xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        out = np.zeros(xb.shape, bool)
        for s in self.sources:
            if isinstance(s, _GridSource | MosaicSource):
                out |= s.sea_at(xb, yb, level)
        return out

    def void_fill(self, xm: ArrayLike, ym: ArrayLike) -> tuple[NDArray[np.float32], B]:
        """The finest source's filled void at each point where one lies inside its data."""
        xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        h = np.zeros(xb.shape, np.float32)
        inside = np.zeros(xb.shape, bool)
        for s in self.sources:
            if isinstance(s, _GridSource | MosaicSource):
                hk, ik = s.void_fill(xb, yb)
                take = ik & ~inside
                h[take], inside = hk[take], inside | ik
        return h, inside

    def close(self) -> None:
        for s in self.sources:
            s.close()


@dataclass(frozen=True)
class Fill:
    """What stands where the data has none: ``none`` (a hole: nothing drawn), ``nearest`` (the
    nearest valid height, stretched), ``value`` (level ground at ``height``), ``ellipsoid``
    (height 0) or ``interpolate`` (voids inside the data filled smoothly from their rims, the
    world outside the data at height 0, as ``ellipsoid``)."""

    kind: str = "none"
    height: float = 0.0

    def __str__(self) -> str:
        return f"value:{self.height:g}" if self.kind == "value" else self.kind


def parse_fill(text: str) -> Fill:
    """``none``, ``nearest``, ``value:H`` (metres) or ``ellipsoid``; one-line SourceError."""
    kind, _, arg = str(text).strip().partition(":")
    if kind in ("none", "nearest", "ellipsoid", "interpolate") and not arg:
        return Fill(kind)
    if kind == "value":
        try:
            h = float(arg)
        except ValueError:
            h = math.nan
        if math.isfinite(h):
            return Fill("value", h)
    raise SourceError(
        f"--fill must be none, nearest, value:H (metres), ellipsoid or interpolate, got {text!r}"
    )


class FilledSource:
    """A height source whose points without data get the ``fill``'s height (``nearest`` and
    ``none`` keep the source's own nearest-valid fill, which ``none`` never draws). Validity is
    the source's: the fill is a stated default, never data."""

    def __init__(self, source: HeightSource, fill: Fill) -> None:
        self.source = source
        self.fill = fill
        self.name = source.name
        self.crs_wkt = source.crs_wkt
        self.bounds_merc = source.bounds_merc
        self.resolution_merc = source.resolution_merc

    def _filled(
        self,
        got: tuple[NDArray[np.float32], NDArray[np.bool_]],
        points: Callable[[], tuple[F64, F64]],
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        h, valid = got
        if valid.all() or self.fill.kind in ("none", "nearest"):
            return h, valid
        level = self.fill.height if self.fill.kind == "value" else 0.0
        out = np.where(valid, h, np.float32(level)).astype(np.float32)
        if self.fill.kind == "interpolate" and isinstance(self.source, _GridSource | MosaicSource):
            xm, ym = points()
            bad = ~valid
            voids, inside = self.source.void_fill(xm[bad], ym[bad])
            out[bad] = np.where(inside, voids, np.float32(0.0))
        return out, valid

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        def points() -> tuple[F64, F64]:
            xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
            return xb, yb

        return self._filled(self.source.sample(xm, ym, spacing), points)

    def sample_grid(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        def points() -> tuple[F64, F64]:
            xx, yy = np.meshgrid(
                np.asarray(xs, np.float64).ravel(), np.asarray(ys, np.float64).ravel()
            )
            return xx, yy

        return self._filled(self.source.sample_grid(xs, ys, spacing), points)

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        def points() -> tuple[F64, F64]:
            rows, cols = shape
            left, bottom, right, top = (float(v) for v in bounds)
            x = left + np.arange(cols) * (right - left) / (cols - 1)
            y = top - np.arange(rows) * (top - bottom) / (rows - 1)
            x[-1], y[-1] = right, bottom
            xx, yy = np.meshgrid(x, y)
            return xx, yy

        return self._filled(self.source.read(bounds, shape), points)

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        return self.source.covers(xm, ym)

    def sample_nodata(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        """``sample`` where there is no data (the fill's heights, none valid), no pixel read."""

        def points() -> tuple[F64, F64]:
            xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
            return xb, yb

        return self._filled(self.source.sample_nodata(xm, ym), points)  # type: ignore[attr-defined]

    def pixels_in(self, box: Bbox) -> Iterator[tuple[F64, F64, F64]]:
        return self.source.pixels_in(box)

    def close(self) -> None:
        self.source.close()

    #: What a raster source knows beyond its heights, asked for where it is there (the sea
    #: stored as its level, the data's range, its shares of data and voids): forwarded; no
    #: other name is.
    FORWARDED = frozenset({"sea_at", "data_range", "valid_share", "void_share", "has_data"})

    def __getattr__(self, name: str) -> Any:
        if name in FilledSource.FORWARDED and "source" in self.__dict__:
            return getattr(self.source, name)
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")


def open_rasters(
    paths: Sequence[str | os.PathLike[str]],
    *,
    allow_mixed_crs: bool = False,
    band: int | None = None,
    nodata: float | None = None,
    z_units: str | None = None,
) -> HeightSource:
    """One raster as a RasterSource, several as a MosaicSource; each file checked as it opens
    (``band``, ``nodata`` and ``z_units`` apply to every file)."""
    opened: list[RasterSource] = []
    try:
        for p in paths:
            opened.append(RasterSource(p, band=band, nodata=nodata, z_units=z_units))
        if not opened:
            raise SourceError("no input rasters given")
        crs = {CRS.from_wkt(s.crs_wkt) for s in opened}
        if len(crs) > 1 and not allow_mixed_crs:
            first = opened[0]
            other = next(
                s for s in opened if CRS.from_wkt(s.crs_wkt) != CRS.from_wkt(first.crs_wkt)
            )
            raise SourceError(
                f"{other.name}: its CRS ({_crs_name(other.crs_wkt)}) differs from "
                f"{first.name}'s ({_crs_name(first.crs_wkt)}); reproject the inputs to one CRS, "
                "or pass --allow-mixed-crs to reproject each on the fly"
            )
    except BaseException:
        for s in opened:
            s.close()
        raise
    return opened[0] if len(opened) == 1 else MosaicSource(opened)


def identity(source: HeightSource) -> str | None:
    """What a height source's tile statistics depend on, as text: each raster's absolute path,
    size and modification time and those of every file GDAL reads for it (a VRT's sources),
    its band, nodata, height unit and scale, and the fill; None where a raster is not a local
    file (a URL: its statistics are made again each time)."""
    parts: list[str] = [f"fill={getattr(source, 'fill', 'none')}"]
    rasters = rasters_of(source)
    if not rasters:
        return None
    for r in rasters:
        if r.path.startswith("/vsi") or "://" in r.path:
            return None
        try:
            files = [r.path, *(f for f in r._ds.files if f != r.path)]
        except Exception:  # a driver that cannot list its files: the raster's own alone
            files = [r.path]
        for f in files:
            try:
                st = os.stat(f)
            except OSError:
                return None
            parts.append(f"{os.path.abspath(f)}|{st.st_size}|{st.st_mtime_ns}")
        parts.append(f"band={r._band}|nodata={r._nodata}|scale={r._scale!r}|offset={r._offset!r}")
    return "\n".join(parts)


def rasters_of(source: HeightSource) -> list[RasterSource]:
    """The rasters under ``source`` (through its fill and its mosaic), finest first."""
    if isinstance(source, FilledSource):
        return rasters_of(source.source)
    if isinstance(source, MosaicSource):
        return [r for s in source.sources for r in rasters_of(s)]
    return [source] if isinstance(source, RasterSource) else []


def pixel_share(source: HeightSource, share: Callable[[RasterSource], float]) -> float:
    """``share`` (a share of a raster's pixels) over all the rasters under ``source``."""
    parts = [(share(r), r.shape[0] * r.shape[1]) for r in rasters_of(source)]
    total = sum(n for _, n in parts)
    return sum(v * n for v, n in parts) / total if total else 0.0


def sea_note(source: HeightSource, level: float | None) -> str | None:
    """One line on the sea a DEM stores as exactly ``level`` (drawn as water), or None."""
    if level is None:
        return None
    share = pixel_share(source, lambda r: r.sea_share(level))
    if share <= 0.0:
        return None
    return (
        f"{source.name}: {100.0 * share:.1f} % of it lies at exactly {level:g} m and reaches "
        "the data's edge: drawn as sea (--sea-level none draws it as land)"
    )


def raster_notes(source: HeightSource) -> list[str]:
    """What the rasters under ``source`` say of their CRS where they state none and of their
    height units where they are not plain metres (``RasterSource.notes``), once each: for the
    app to say on stderr."""
    return [note for r in rasters_of(source) for note in r.notes]


#: Pixels a raster's ground control points may lie off their affine fit for it to be read on it.
GCP_TOLERANCE = 0.1


def gcp_fit(gcps: Sequence[Any]) -> tuple[Affine, float]:
    """The least-squares affine map of pixel (col, row) edges to coordinates through ground
    control points (rasterio's ``GroundControlPoint``: row, col, x, y), and how far the
    farthest point lies off it, in pixels (inf: fewer than three, or all in a line)."""
    col = np.array([float(g.col) for g in gcps])
    row = np.array([float(g.row) for g in gcps])
    xy = np.array([[float(g.x), float(g.y)] for g in gcps])
    a = np.column_stack([col, row, np.ones_like(col)])
    if len(gcps) < 3 or np.linalg.matrix_rank(a) < 3:
        return Affine.identity(), math.inf
    (ca, cb, cc), *_ = np.linalg.lstsq(a, xy[:, 0], rcond=None)
    (cd, ce, cf), *_ = np.linalg.lstsq(a, xy[:, 1], rcond=None)
    fit = Affine(float(ca), float(cb), float(cc), float(cd), float(ce), float(cf))
    if fit.determinant == 0.0 or not all(math.isfinite(v) for v in fit[:6]):
        return Affine.identity(), math.inf
    inv = ~fit
    back_col = inv.a * xy[:, 0] + inv.b * xy[:, 1] + inv.c
    back_row = inv.d * xy[:, 0] + inv.e * xy[:, 1] + inv.f
    return fit, float(np.hypot(back_col - col, back_row - row).max())


def gcp_placement(name: str, gcps: Sequence[Any], crs: Any) -> tuple[Affine, str]:
    """Where a raster ``name`` placed by ground control points alone (in ``crs``, rasterio's)
    lies: their affine fit (``gcp_fit``), and one line that says so; a SourceError where the
    fit misses a point by more than ``GCP_TOLERANCE`` pixels (warped first, then)."""
    fit, off = gcp_fit(gcps)
    code = crs.to_epsg()
    srs = f"EPSG:{code}" if code else "its CRS"
    if not off <= GCP_TOLERANCE:
        raise SourceError(
            f"{name}: placed by {len(gcps)} ground control points that no affine map fits (off "
            f"by up to {off:.2g} pixels); warp it onto a grid first (e.g. gdalwarp -t_srs {srs} "
            f"{name} warped.tif)"
        )
    note = (
        f"{name}: placed by {len(gcps)} ground control points, read on their affine fit "
        f"({srs}; every point within {max(off, 0.01):.2f} pixels)"
    )
    return fit, note


#: CF's units of longitude and latitude (CF conventions, 4.1 and 4.2).
_CF_EAST = {"degrees_east", "degree_east", "degree_e", "degrees_e", "degreee", "degreese"}
_CF_NORTH = {"degrees_north", "degree_north", "degree_n", "degrees_n", "degreen", "degreesn"}


def _cf_lonlat(tags: dict[str, str]) -> bool:
    """Whether a raster's metadata (GDAL's netCDF tags, ``var#units``) names its axes CF's
    longitude and latitude in degrees."""
    units = {v.strip().lower() for k, v in tags.items() if k.lower().endswith("#units")}
    return bool(units & _CF_EAST) and bool(units & _CF_NORTH)


def _crs_name(wkt: str) -> str:
    crs = CRS.from_wkt(wkt)
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else crs.name
