"""Fractal detail below a DEM, and a procedural planet (paper 003).

A real DEM runs out of resolution long before a low camera does. Below the data's own lattice
level ``L0`` (the finest level of its tile tree, where the 64-segment grid samples every texel of
the finest texture), a tile's surface is the DEM's surface (its triangulated lattice at ``L0``,
evaluated exactly, so every tile asks the same thing of the same point) plus fractional Brownian
detail made by midpoint displacement (``lodscape.terrain.fractal``) starting at ``L0``: zero on
the data's own lattice, the first displacement σ metres, each finer level 2^-H smaller. A tile
of level z drawn with g segments samples the lattice of level z + log2(g); the selection splits
a tile until its error on screen is within the bound, so the number of subdivision steps follows
the distance, as paper 003's LOD threshold does, in pixels.

The procedural planet is the same fBm from level 0 over the whole Web Mercator square: no data.

**Honest error.** The selection needs each tile's error before the tile is made. fBm detail is
statistically self-similar, so the error of a g-segment mesh at lattice level L against the
surface at the deepest level (``MAX_LEVEL``) is σ_L = σ·2^-(L-L0)·H times a factor that depends
only on H and g, measured here once per (H, g) on calibration windows (the largest deviation
over several tiles and seeds, at every point of a lattice several levels finer, with the tail of
the remaining levels bounded by a geometric series of the measured per-level increments) and
taken with a margin of 1.5. Either diagonal may be chosen in each cell (the terrain-adaptive
split follows the total heights), so the calibration takes the worse of the two. A tile's
recorded error is the base's (the tree's own, or, below the data, half the largest twist of the
data's lattice cells under it) plus that detail bound plus the chord's sag: a bound on what the
tile's children will add. It is a statistical bound (the displacements are Gaussian); the tests
check it against the generated surface on tiles, levels and seeds the calibration did not see.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from lodscape.errors import SourceError
from lodscape.geo.tiles import ORIGIN, Bbox, merc_to_lonlat
from lodscape.terrain.fractal import HASH_BOUND, MAX_LEVEL, effective_hurst, fbm_window
from lodscape.terrain.mesh import GRIDS
from lodscape.terrain.pyramid import DeeperTree, TileStats, sag

__all__ = [
    "DetailLevel",
    "DetailTree",
    "Fractal",
    "ProceduralHeights",
    "ProceduralTree",
    "detail_bound",
    "diagonals",
    "error_factor",
    "interpolate",
    "parse_procedural",
    "procedural_relief",
    "vista",
]

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
#: Margin on the calibrated error factors.
MARGIN = 1.5


@dataclass(frozen=True)
class Fractal:
    """fBm detail: Hurst exponent (roughness: 0 rough .. 1 smooth), σ metres (the first
    displacement below the data; None: from the data's own roughness) and seed."""

    hurst: float = 0.7
    sigma: float | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 < self.hurst < 1.0:
            raise ValueError(f"Expected a Hurst exponent in (0, 1), got {self.hurst}")
        if self.sigma is not None and not (math.isfinite(self.sigma) and self.sigma >= 0.0):
            raise ValueError(f"Expected a non-negative sigma in metres, got {self.sigma}")


# --- triangulated lattices ------------------------------------------------------------------


def diagonals(h: NDArray[np.floating]) -> NDArray[np.bool_]:
    """Per cell of an (m, n) height grid (row 0 north): True where the cell is split along the
    north-east to south-west diagonal, the one joining its two lowest corners (paper 003); the
    north-west to south-east one otherwise (and on ties)."""
    a, b = h[:-1, :-1], h[:-1, 1:]
    c, d = h[1:, :-1], h[1:, 1:]
    out: NDArray[np.bool_] = (b.astype(np.float64) + c) < (a.astype(np.float64) + d)
    return out


def interpolate(
    h: NDArray[np.floating], fi: F64, fj: F64, diag: NDArray[np.bool_] | None = None
) -> F64:
    """The triangulated grid ``h`` (row 0 north) at fractional grid positions (fi columns, fj
    rows, same shape), each cell split NW–SE, or NE–SW where ``diag`` says so. A point on a cell
    edge belongs to the cell it starts (floor), so every window that holds that cell computes the
    same bits."""
    m, n = h.shape
    ci = np.clip(np.floor(fi).astype(np.int64), 0, n - 2)
    cj = np.clip(np.floor(fj).astype(np.int64), 0, m - 2)
    u, v = fi - ci, fj - cj
    hh = np.asarray(h, dtype=np.float64)
    a, b = hh[cj, ci], hh[cj, ci + 1]
    c, d = hh[cj + 1, ci], hh[cj + 1, ci + 1]
    # NW–SE: triangles (a, b, d) where u >= v, (a, c, d) where v > u
    nwse = np.where(u >= v, a + u * (b - a) + v * (d - b), a + v * (c - a) + u * (d - c))
    if diag is None:
        return nwse
    # NE–SW: triangles (a, b, c) where u + v <= 1, (b, c, d) beyond
    nesw = np.where(
        u + v <= 1.0, a + u * (b - a) + v * (c - a), d + (1.0 - u) * (c - d) + (1.0 - v) * (b - d)
    )
    out: F64 = np.where(diag[cj, ci], nesw, nwse)
    return out


def _refine(h: F64, k: int, diag: NDArray[np.bool_] | None) -> F64:
    """The triangulated grid on the lattice 2^k times finer over the same extent."""
    f = 1 << k
    m, n = h.shape
    fj, fi = np.meshgrid(
        np.arange((m - 1) * f + 1) / f, np.arange((n - 1) * f + 1) / f, indexing="ij"
    )
    return interpolate(h, fi, fj, diag)


# --- calibration ----------------------------------------------------------------------------

#: Levels below the tile's lattice measured directly; deeper levels are a geometric tail.
_DEEP = {16: 4, 32: 4, 64: 3}
_SEEDS = (101, 202, 303, 404, 505, 606, 707, 808, 909)
_OFFSETS = (1, 4)


#: Bump when the lattice's values change (the hash, the scheme): calibrations kept on disk by
#: an older version are then measured again.
_CALIBRATION_VERSION = 3


@cache
def _calibrate(hurst: float, segments: int) -> tuple[float, ...]:
    """Factors f[n]: the largest deviation of a ``segments``-cell tile triangulated on its own
    lattice (either diagonal) from the surface n levels finer, over σ_L; n = 0..MAX_LEVEL.
    Measured once (a second or so) and kept in lodscape's cache folder for the next run."""
    import json
    import os

    from lodscape._cache import user_cache

    name = _calibration_name(hurst, segments)
    shipped = _shipped_calibrations().get(name)
    if shipped is not None:
        return shipped
    path = user_cache() / "calibration" / f"{name}.json"
    try:
        kept = json.loads(path.read_text())
        if isinstance(kept, list) and len(kept) == MAX_LEVEL + 1:
            return tuple(float(v) for v in kept)
    except (OSError, ValueError):
        pass
    out = _measure(hurst, segments)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}")
        tmp.write_text(json.dumps(list(out)))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache: measured again next time
    return out


def _calibration_name(hurst: float, segments: int) -> str:
    """A calibration's key: in the shipped table, and its file name in the cache."""
    return f"fbm-v{_CALIBRATION_VERSION}-h{hurst:.6f}-s{segments}-m{MARGIN:g}"


@cache
def _shipped_calibrations() -> dict[str, tuple[float, ...]]:
    """The calibrations of the defaults' Hurst exponents, measured by
    ``python -m lodscape.terrain.detail`` into the package's data (``calibration.json``) so a
    first run does not wait for them; ``tests/test_detail.py`` measures one again."""
    import json
    from importlib.resources import files

    try:
        raw = json.loads(files("lodscape.data").joinpath("calibration.json").read_text())
    except (OSError, ValueError):
        return {}
    return {k: tuple(float(v) for v in vals) for k, vals in raw.items()}


def _measure(hurst: float, segments: int) -> tuple[float, ...]:
    """``_calibrate``'s measurement."""
    deep = _DEEP.get(segments, 3)
    start = 2
    dev = np.zeros(deep + 1)
    inc = 0.0
    for seed in _SEEDS:
        for off in _OFFSETS:
            lv = start + off + int(math.log2(segments))
            i0, j0 = seed * 7 % (1 << lv), seed * 13 % (1 << lv)
            coarse = fbm_window(
                seed, hurst, 1.0, lv, i0, j0, segments + 1, segments + 1, start=start
            )
            scale = 2.0 ** (-(lv - start) * hurst)
            for k in range(1, deep + 1):
                f = 1 << k
                fine = fbm_window(
                    seed,
                    hurst,
                    1.0,
                    lv + k,
                    i0 * f,
                    j0 * f,
                    segments * f + 1,
                    segments * f + 1,
                    start=start,
                )
                worst = max(
                    float(np.abs(_refine(coarse, k, None) - fine).max()),
                    float(
                        np.abs(_refine(coarse, k, np.ones((segments, segments), bool)) - fine).max()
                    ),
                )
                dev[k] = max(dev[k], worst / scale)
                if k == deep:
                    # the last level's own increment, for the tail: against its parent lattice
                    parent = fine[::2, ::2]
                    one = max(
                        float(np.abs(_refine(parent, 1, None) - fine).max()),
                        float(
                            np.abs(
                                _refine(parent, 1, np.ones(np.subtract(parent.shape, 1), bool))
                                - fine
                            ).max()
                        ),
                    )
                    inc = max(inc, one / (scale * 2.0 ** (-(k - 1) * hurst)))
    q = 2.0 ** (-hurst)
    out = []
    for n in range(MAX_LEVEL + 1):
        if n <= deep:
            out.append(MARGIN * dev[n])
        else:
            # levels deep+1..n each add at most inc·σ of their parent level: a geometric series
            tail = inc * sum(q**k for k in range(deep, n))
            out.append(MARGIN * (dev[deep] + tail))
    return tuple(out)


def error_factor(hurst: float, segments: int, remaining: NDArray[np.integer] | int) -> F64:
    """The calibrated error of a ``segments``-cell tile with ``remaining`` lattice levels of
    detail below its own, in units of σ at its lattice level."""
    f = np.asarray(_calibrate(round(hurst, 6), segments))
    out: F64 = f[np.clip(np.asarray(remaining), 0, MAX_LEVEL)]
    return out


@cache
def _amplitude(hurst: float) -> float:
    """Largest |detail| over calibration windows, at the deepest level, in units of σ (with the
    margin): what the whole detail can add to a tile that has none of it."""
    start = 2
    worst = 0.0
    for seed in _SEEDS:
        # 2^8 cells deep; the levels below add a geometric tail of their σ
        lv = start + 8
        w = fbm_window(seed, hurst, 1.0, lv, seed, 3 * seed, 257, 257, start=start)
        worst = max(worst, float(np.abs(w).max()))
    tail = float(error_factor(hurst, 16, MAX_LEVEL - 12)[()]) * 2.0 ** (-8 * hurst)
    return float(MARGIN * worst + tail)


@cache
def _ceiling(hurst: float) -> float:
    """The largest |detail| there can be, in units of σ: every level adds to a point at most one
    square-step and one diamond-step displacement (``fractal._window``), each at most
    ``HASH_BOUND`` of its σ, so the sum of their series bounds it. A proof, where ``_amplitude``
    is a measurement: the extremes of the many points a large tile holds can pass the latter."""
    h = effective_hurst(hurst)
    q = 2.0 ** (-h)
    # Σ_{rel≥1} 2^(-(2·rel-1)·h/2) + 2^(-rel·h)
    return float(HASH_BOUND * (2.0 ** (h / 2.0) + 1.0) * q / (1.0 - q))


def detail_bound(fractal: Fractal, sigma: float, start: int, lattice: I64, segments: int) -> F64:
    """Metres of error of detail a ``segments``-cell tile at lattice level ``lattice`` may miss."""
    if sigma == 0.0:
        # no amplitude: no detail to miss (and no calibration to run for it)
        return np.zeros(np.shape(lattice))
    rel = lattice - start
    below = (
        sigma
        * 2.0 ** (-np.maximum(rel, 0) * fractal.hurst)
        * error_factor(fractal.hurst, segments, MAX_LEVEL - lattice)
    )
    # a tile coarser than the detail's first level holds none of it: all of it is its error
    out: F64 = np.where(rel >= 0, below, sigma * _ceiling(round(fractal.hurst, 6)))
    return out


def _log2(n: int) -> int:
    return round(math.log2(n))


def _level_for(spacing: float) -> int:
    """The lattice level whose cells are ``spacing`` Web Mercator metres wide (clamped)."""
    return int(np.clip(round(math.log2(2.0 * ORIGIN / max(spacing, 1e-9))), 0, MAX_LEVEL))


# --- fractal detail on a DEM's tile tree ----------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Wrapped:
    """A level of the DEM's own tree with the whole detail's amplitude added to its bounds."""

    base: Any
    dmax: float

    @property
    def z(self) -> int:
        return int(self.base.z)

    def stats(self, x: I64, y: I64) -> TileStats:
        st: TileStats = self.base.stats(x, y)
        return TileStats(
            st.exists, st.min_h - self.dmax, st.max_h + self.dmax, st.error + self.dmax
        )


@dataclass(frozen=True, eq=False)
class DetailLevel:
    """A level below the DEM's finest: its tiles' bounds and errors from their ancestor at the
    finest level plus the detail's calibrated bounds (arithmetic, no data read)."""

    z: int
    tree: DetailTree

    def stats(self, x: I64, y: I64) -> TileStats:
        t = self.tree
        k = self.z - t.base.zmax
        fin = t.base.level(t.base.zmax)
        st = fin.stats(x >> k, y >> k)
        grids = t.base.grids
        errs = []
        for g in grids:
            lat_lv = self.z + _log2(g)
            gp = 1 << (lat_lv - t.base.zmax)
            if gp in grids:
                # the ancestor's mesh of the same lattice, restricted to this tile
                base = st.error[grids.index(gp)]
            else:
                # below the data's lattice its triangulated surface folds only along the data
                # cells' diagonals; a cell 2^-j as wide re-split across a fold is off by half
                # its twist, the data cell's twist · 2^-j
                _, flat = fin.index(x >> k, y >> k)
                base = t.base.twist.ravel()[flat] * 2.0 ** -(lat_lv - t.start + 1)
            det = detail_bound(t.fractal, t.sigma, t.start, np.full(x.shape, lat_lv), g)
            errs.append(base + det + sag(self.z, g, y))
        return TileStats(st.exists, st.min_h - t.dmax, st.max_h + t.dmax, np.stack(errs))


@dataclass(frozen=True, eq=False)
class DetailTree(DeeperTree):
    """A DEM's tile tree with fractal detail below it, down to ``zmax`` (lattice ``MAX_LEVEL``
    at the finest grid)."""

    base: Any
    fractal: Fractal
    #: The DEM's lattice level (detail starts below it) and the first displacement, metres.
    start: int
    sigma: float
    _levels: dict[int, Any] = field(default_factory=dict, repr=False)

    @classmethod
    def over(cls, base: Any, fractal: Fractal) -> DetailTree:
        if base.twist is None or base.roughness is None:
            raise SourceError(
                "fractal detail needs a tile tree built from a raster (not a tileset)"
            )
        start = base.zmax + _log2(base.grids[-1])
        sigma = fractal.sigma
        if sigma is None:
            # the data's one-sample roughness carried one level down by the fBm law
            sigma = float(base.roughness) * 2.0 ** (-fractal.hurst) / 2.0
        return cls(base, fractal, start, sigma)

    @property
    def dmax(self) -> float:
        if self.sigma == 0.0:
            return 0.0
        return self.sigma * _amplitude(round(self.fractal.hurst, 6))

    @property
    def zmax(self) -> int:  # type: ignore[override]
        return max(int(self.base.zmax), MAX_LEVEL - _log2(self.base.grids[-1]))

    @property
    def texture_zmax(self) -> int:
        # textures follow the detail: their hillshade shows it
        return self.zmax

    def _make_level(self, z: int) -> Any:
        if z <= self.base.zmax:
            return _Wrapped(self.base.level(z), self.dmax)
        return DetailLevel(z, self)

    def adaptive(self, z: int, segments: int) -> bool:
        """Whether a tile's mesh is below the data (terrain-adaptive diagonals, detail added)."""
        return z + _log2(segments) > self.start


class DetailHeights:
    """Heights of a raster plus fractal detail below its resolution: what meshes and textures
    sample. Meshes get exact lattice values (``tile``); textures and single points bilinear."""

    def __init__(self, source: Any, tree: DetailTree) -> None:
        self.source = source
        self.tree = tree
        self.name = source.name
        self.crs_wkt = getattr(source, "crs_wkt", "")
        self.bounds_merc = source.bounds_merc
        self.resolution_merc = source.resolution_merc

    def tile(self, z: int, x: int, y: int, segments: int) -> NDArray[np.float32]:
        """The (S+1)² heights of a tile's grid: the DEM on its lattice (or, below it, the DEM's
        triangulated lattice) plus the detail of the grid's lattice level."""
        t = self.tree
        lv = z + _log2(segments)
        cell = 2.0 * ORIGIN / float(1 << lv)
        i0, j0 = x * segments, y * segments
        if lv <= t.start:
            xs = -ORIGIN + (i0 + np.arange(segments + 1)) * cell
            ys = ORIGIN - (j0 + np.arange(segments + 1)) * cell
            xx, yy = np.meshgrid(xs, ys)
            h, _ = self.source.sample(xx, yy, float(cell))
            return np.asarray(h, dtype=np.float32)
        k = lv - t.start
        f = 1 << k
        # the data's lattice cells holding the grid (one more so each point has its cell)
        a0, b0 = i0 >> k, j0 >> k
        a1, b1 = ((i0 + segments) >> k) + 1, ((j0 + segments) >> k) + 1
        dcell = 2.0 * ORIGIN / float(1 << t.start)
        xs = -ORIGIN + np.arange(a0, a1 + 1) * dcell
        ys = ORIGIN - np.arange(b0, b1 + 1) * dcell
        xx, yy = np.meshgrid(xs, ys)
        base, _ = self.source.sample(xx, yy, float(dcell))
        gi = (i0 + np.arange(segments + 1)) - a0 * f
        gj = (j0 + np.arange(segments + 1)) - b0 * f
        fj, fi = np.meshgrid(gj / f, gi / f, indexing="ij")
        h = interpolate(base, fi, fj)
        f_ = t.fractal
        if t.sigma == 0.0:
            # no amplitude (imagery or land cover finer than the DEM): the lattice refined alone
            return h.astype(np.float32)
        h += fbm_window(
            f_.seed, f_.hurst, t.sigma, lv, i0, j0, segments + 1, segments + 1, start=t.start
        )
        return h.astype(np.float32)

    def _detail_at(self, xm: F64, ym: F64, spacing: float) -> F64:
        t = self.tree
        lv = _level_for(spacing)
        if lv <= t.start or t.sigma == 0.0:
            return np.zeros(np.shape(xm))
        return _field_at(t.fractal.seed, t.fractal.hurst, t.sigma, lv, t.start, xm, ym)

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        h, ok = self.source.sample(xm, ym, spacing)
        xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        return (h + self._detail_at(xb, yb, spacing)).astype(np.float32), ok

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        h, ok = self.source.read(bounds, shape)
        rows, cols = shape
        xs = np.linspace(bounds.left, bounds.right, cols)
        ys = np.linspace(bounds.top, bounds.bottom, rows)
        xx, yy = np.meshgrid(xs, ys)
        spacing = (bounds.right - bounds.left) / (cols - 1)
        return (h + self._detail_at(xx, yy, spacing)).astype(np.float32), ok

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        out: NDArray[np.bool_] = self.source.covers(xm, ym)
        return out

    def close(self) -> None:
        self.source.close()


def _field_at(
    seed: int, hurst: float, sigma: float, level: int, start: int, xm: F64, ym: F64
) -> F64:
    """The fBm of ``level`` at any Web Mercator points, bilinear between lattice points."""
    cell = 2.0 * ORIGIN / float(1 << level)
    gi = (np.asarray(xm, np.float64) + ORIGIN) / cell
    gj = (ORIGIN - np.asarray(ym, np.float64)) / cell
    if gi.size == 0:
        return np.zeros(gi.shape)
    i0, j0 = int(np.floor(gi.min())), int(np.floor(gj.min()))
    ni, nj = int(np.floor(gi.max())) - i0 + 2, int(np.floor(gj.max())) - j0 + 2
    if ni * nj > 1 << 24:
        raise ValueError(f"Expected a window of at most 2^24 lattice points, got {ni}×{nj}")
    w = fbm_window(seed, hurst, sigma, level, i0, j0, ni, nj, start=start)
    u, v = gi - i0, gj - j0
    ci = np.clip(np.floor(u).astype(np.int64), 0, ni - 2) if ni > 1 else np.zeros(u.shape, np.int64)
    cj = np.clip(np.floor(v).astype(np.int64), 0, nj - 2) if nj > 1 else np.zeros(v.shape, np.int64)
    fu, fv = u - ci, v - cj
    c1 = np.minimum(ci + 1, ni - 1)
    r1 = np.minimum(cj + 1, nj - 1)
    top = w[cj, ci] * (1 - fu) + w[cj, c1] * fu
    bot = w[r1, ci] * (1 - fu) + w[r1, c1] * fu
    out: F64 = top * (1 - fv) + bot * fv
    return out


# --- the procedural planet ------------------------------------------------------------------

#: Tiles a side of the blocks whose bounds are computed and kept together.
_BLOCK = 8


@dataclass(frozen=True, eq=False)
class ProceduralLevel:
    """A level of the procedural planet: each tile's bounds from its 16-segment lattice (blocks
    of 8×8 tiles computed together and kept) widened by the detail it does not hold."""

    z: int
    tree: ProceduralTree

    def stats(self, x: I64, y: I64) -> TileStats:
        t = self.tree
        n = 1 << self.z
        ok = (x >= 0) & (x < n) & (y >= 0) & (y < n)
        mn = np.zeros(x.shape)
        mx = np.zeros(x.shape)
        bx, by = x // _BLOCK, y // _BLOCK
        blocks = np.unique(np.stack([bx[ok], by[ok]], axis=1), axis=0)
        for bxi, byi in blocks:
            lo, hi = t.block(self.z, int(bxi), int(byi))
            m = ok & (bx == bxi) & (by == byi)
            mn[m] = lo[y[m] - byi * _BLOCK, x[m] - bxi * _BLOCK]
            mx[m] = hi[y[m] - byi * _BLOCK, x[m] - bxi * _BLOCK]
        errs = [
            t.bound(np.full(x.shape, self.z + _log2(g)), g) + sag(self.z, g, y) for g in t.grids
        ]
        return TileStats(ok, mn, mx, np.stack(errs))


@dataclass(frozen=True)
class Band:
    """One fBm of the procedural planet: zero down to lattice level ``start``, displacements from
    there on with σ ``sigma`` metres shrinking by 2^-hurst a level."""

    hurst: float
    sigma: float
    start: int
    seed: int

    def window(self, level: int, i0: int, j0: int, ni: int, nj: int) -> F64:
        return fbm_window(
            self.seed, self.hurst, self.sigma, level, i0, j0, ni, nj, start=self.start
        )

    def bound(self, lattice: I64, segments: int) -> F64:
        """Metres this band may hold below a ``segments``-cell tile of lattice level ``lattice``."""
        return detail_bound(
            Fractal(self.hurst, self.sigma, self.seed), self.sigma, self.start, lattice, segments
        )


class ProceduralTree:
    """The tile tree of the procedural planet: level 0 (one tile, the whole Web Mercator square)
    down to the level whose finest grid is the lattice's deepest; bounds computed on demand.

    The planet is the sum of two fBm bands: the continents (``fractal``: σ at lattice level
    PROCEDURAL_START, cells of 2,500 km) and the mountains (σ ``relief`` from lattice level
    MOUNTAIN_START, cells of 20 km, smoother: H = MOUNTAIN_HURST). A mesh interpolates the sum
    of the bands' lattices, so a tile's error is at most the sum of the bands' bounds."""

    def __init__(self, fractal: Fractal, sigma: float, relief: float = 0.0) -> None:
        self.fractal = fractal
        self.sigma = sigma
        self.bands: tuple[Band, ...] = tuple(
            b
            for b in (
                Band(fractal.hurst, sigma, PROCEDURAL_START, fractal.seed),
                Band(MOUNTAIN_HURST, relief, MOUNTAIN_START, fractal.seed + MOUNTAIN_SEED),
            )
            if b.sigma > 0.0
        )
        self.grids: tuple[int, ...] = GRIDS
        self.tile_size = 256
        self.zmin = 0
        self.zmax = MAX_LEVEL - _log2(GRIDS[-1])
        self.texture_zmax: int | None = self.zmax
        self.coarsened = 0
        self.start = PROCEDURAL_START
        self._lock = threading.Lock()
        self._blocks: dict[tuple[int, int, int], tuple[F64, F64]] = {}
        self._levels = [ProceduralLevel(z, self) for z in range(self.zmax + 1)]
        # the tint's range: the planet's heights on a fine enough lattice (2^10 cells a side)
        w = self.lattice(10, 0, 0, 1025)
        self.height_range = (float(w.min()), float(w.max()))

    def bound(self, lattice: I64, segments: int) -> F64:
        """Metres of the planet a ``segments``-cell tile of lattice level ``lattice`` may miss."""
        out: F64 = sum(
            (b.bound(lattice, segments) for b in self.bands), np.zeros(np.shape(lattice))
        )
        return out

    def field_at(self, level: int, xm: F64, ym: F64) -> F64:
        """The planet's lattice of ``level`` at any Web Mercator points (bilinear)."""
        out: F64 = sum(
            (_field_at(b.seed, b.hurst, b.sigma, level, b.start, xm, ym) for b in self.bands),
            np.zeros(np.shape(xm)),
        )
        return out

    @property
    def levels(self) -> tuple[ProceduralLevel, ...]:
        return tuple(self._levels)

    def level(self, z: int) -> ProceduralLevel:
        return self._levels[z]

    def roots(self) -> tuple[I64, I64]:
        return np.zeros(1, np.int64), np.zeros(1, np.int64)

    def adaptive(self, z: int, segments: int) -> bool:
        return True

    def lattice(self, level: int, i0: int, j0: int, n: int) -> F64:
        """The planet's n×n lattice points of ``level`` from (i0, j0)."""
        out: F64 = sum((b.window(level, i0, j0, n, n) for b in self.bands), np.zeros((n, n)))
        return out

    def block(self, z: int, bx: int, by: int) -> tuple[F64, F64]:
        """(min, max) heights of the block's tiles, (rows, cols), bounds included."""
        key = (z, bx, by)
        with self._lock:
            hit = self._blocks.get(key)
        if hit is not None:
            return hit
        g = GRIDS[0]
        n = min(_BLOCK, 1 << z)
        lv = z + _log2(g)
        w = self.lattice(lv, bx * _BLOCK * g, by * _BLOCK * g, n * g + 1)
        tiles = sliding_window_view(w, (g + 1, g + 1))[::g, ::g]
        e = float(self.bound(np.array(lv), g)[()])
        out = (tiles.min(axis=(2, 3)) - e, tiles.max(axis=(2, 3)) + e)
        with self._lock:
            if len(self._blocks) > 4096:
                self._blocks.clear()
            self._blocks[key] = out
        return out


def vista(tree: ProceduralTree) -> tuple[float, float]:
    """(lon, lat) of the procedural planet's most rugged land away from the poles: the point of
    its 2^9 lattice (cells of 78 km) whose 3×3 neighbourhood, all above sea level, spans the
    most height, within 55° of the equator (where a view of mountains shows the most)."""
    n = 1 << 9
    w = tree.lattice(9, 0, 0, n + 1)
    win = sliding_window_view(w, (3, 3))
    lo, hi = win.min(axis=(2, 3)), win.max(axis=(2, 3))
    rows = np.arange(1, n)
    _, lat = merc_to_lonlat(np.zeros(rows.size), ORIGIN - rows * (2.0 * ORIGIN / n))
    score = np.where((lo > 0.0) & (np.abs(lat)[:, None] < 55.0), hi - lo, -1.0)
    j, i = np.unravel_index(int(np.argmax(score)), score.shape)
    cell = 2.0 * ORIGIN / n
    (lon,), (lat0,) = merc_to_lonlat(
        np.array([-ORIGIN + (i + 1) * cell]), np.array([ORIGIN - (j + 1) * cell])
    )
    return float(lon), float(lat0)


class ProceduralHeights:
    """The procedural planet as a height source: fBm below lattice level PROCEDURAL_START over
    the whole Earth; its lattice is its tree's."""

    def __init__(self, tree: ProceduralTree) -> None:
        self.tree = tree
        self.name = f"procedural:seed={tree.fractal.seed}"
        self.crs_wkt = ""
        self.bounds_merc = Bbox(-ORIGIN, -ORIGIN, ORIGIN, ORIGIN)
        self.resolution_merc = 2.0 * ORIGIN / float(1 << MAX_LEVEL)

    def tile(self, z: int, x: int, y: int, segments: int) -> NDArray[np.float32]:
        w = self.tree.lattice(z + _log2(segments), x * segments, y * segments, segments + 1)
        return w.astype(np.float32)

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        xb, yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        h = self.tree.field_at(_level_for(spacing), xb, yb)
        return h.astype(np.float32), np.ones(xb.shape, bool)

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        rows, cols = shape
        xs = np.linspace(bounds.left, bounds.right, cols)
        ys = np.linspace(bounds.top, bounds.bottom, rows)
        xx, yy = np.meshgrid(xs, ys)
        return self.sample(xx, yy, (bounds.right - bounds.left) / (cols - 1))

    def covers(self, xm: NDArray[np.float64], ym: NDArray[np.float64]) -> NDArray[np.bool_]:
        xb, _yb = np.broadcast_arrays(np.asarray(xm, np.float64), np.asarray(ym, np.float64))
        return np.ones(xb.shape, bool)

    def close(self) -> None:
        pass


#: The procedural planet's continents: fBm below lattice level 4 (cells of 2,500 km; continents
#: are not fBm), its first displacement σ = 2,500 m, H = 0.6.
PROCEDURAL_START = 4
PROCEDURAL_HURST = 0.6
PROCEDURAL_SIGMA = 2500.0
#: Its mountains: a second fBm below lattice level 11 (cells of 20 km), σ = 1,000 m, smoother
#: (H = 0.85); its own seed, offset from the planet's.
MOUNTAIN_START = 11
MOUNTAIN_HURST = 0.85
MOUNTAIN_SIGMA = 1000.0
MOUNTAIN_SEED = 1_000_003


def _procedural_values(spec: str) -> dict[str, float]:
    if not spec.startswith("procedural:") and spec != "procedural":
        raise ValueError(f"{spec}: not a procedural source (procedural:seed=N)")
    body = spec.partition(":")[2]
    values: dict[str, float] = {
        "seed": 0.0,
        "hurst": PROCEDURAL_HURST,
        "sigma": PROCEDURAL_SIGMA,
        "relief": MOUNTAIN_SIGMA,
    }
    for part in filter(None, body.split(",")):
        key, eq, val = part.partition("=")
        key = key.strip()
        if not eq or key not in values:
            raise ValueError(
                f"{spec}: expected seed=N, hurst=H, sigma=S or relief=R separated by commas, "
                f"got {part!r}"
            )
        try:
            values[key] = float(val)
        except ValueError:
            raise ValueError(f"{spec}: {key} is not a number: {val!r}") from None
    if (
        not math.isfinite(values["seed"])
        or values["seed"] != int(values["seed"])
        or values["seed"] < 0
    ):
        raise ValueError(f"{spec}: expected a non-negative integer seed, got {values['seed']:g}")
    if not (math.isfinite(values["relief"]) and values["relief"] >= 0.0):
        raise ValueError(
            f"{spec}: expected a non-negative relief in metres, got {values['relief']:g}"
        )
    return values


def parse_procedural(spec: str) -> Fractal:
    """``procedural:seed=N[,hurst=H][,sigma=S][,relief=R]`` → its continents' Fractal (one-line
    errors); ``procedural_relief`` reads R."""
    values = _procedural_values(spec)
    try:
        return Fractal(values["hurst"], values["sigma"], int(values["seed"]))
    except ValueError as exc:
        raise ValueError(f"{spec}: {exc}") from None


def procedural_relief(spec: str) -> float:
    """The σ in metres of the procedural planet's mountains (``relief=R``; 0: none)."""
    return _procedural_values(spec)["relief"]


#: The Hurst exponents whose calibrations ship with the package: the procedural planet's two
#: bands and the DEM detail's default.
SHIPPED_HURSTS = (PROCEDURAL_HURST, MOUNTAIN_HURST, 0.7)


if __name__ == "__main__":
    import json
    from pathlib import Path

    table = {_calibration_name(h, g): list(_measure(h, g)) for h in SHIPPED_HURSTS for g in GRIDS}
    out = Path(__file__).resolve().parents[1] / "data" / "calibration.json"
    out.write_text(json.dumps(table) + "\n")
    print(f"wrote {out}: {len(table)} calibrations")
