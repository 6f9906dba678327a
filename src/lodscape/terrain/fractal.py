"""Fractional Brownian surfaces by midpoint displacement (paper 003), seamless and deterministic.

The surface lives on a global lattice over the unit square (the Web Mercator square, x wrapping
at the antimeridian): level L has 2^L cells a side. Level 0 is one random value (the square's
corners are one point, periodically). Each level halves the spacing by the diamond-square
scheme: the square step sets every cell centre to the mean of its four corners plus a Gaussian
displacement, the diamond step every edge midpoint to the mean of its four neighbours plus a
displacement; displacements shrink by 2^-H per halving of the distance (two half-steps of
2^-H/2), the Hurst exponent H in (0, 1) fixing the roughness, σ the amplitude. As in Saupe's
"successive random additions", every existing point is displaced again at each half-step. The
scheme's increments scale a little off 2H (smoother at high H, rougher at low H); the exponent
the displacements shrink by is calibrated so that the surface's own increments follow H.

Every displacement is a hash of (seed, level, lattice position) turned Gaussian, and a level's
values over any window are made from the previous level's over a window one cell larger each
way. So a point's height depends only on its position, its level and the seed: never on which
window (tile) asked, or in which order: neighbouring tiles agree to the bit on their shared edge,
and a tile computed twice is the same.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

__all__ = ["HASH_BOUND", "MAX_LEVEL", "effective_hurst", "fbm_window", "gaussian_hash"]

#: Deepest lattice level (2^24 cells across the Web Mercator square: about 2.4 m).
MAX_LEVEL = 24

F64 = NDArray[np.float64]
_U = np.uint64
_SQRT3 = math.sqrt(3.0)
#: The largest |value| ``gaussian_hash`` gives (four uniforms, centred and scaled).
HASH_BOUND = 2.0 * _SQRT3


def _mix(z: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """splitmix64's finaliser: a bijection on 64 bits that scrambles every input bit."""
    z = (z ^ (z >> _U(30))) * _U(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> _U(27))) * _U(0x94D049BB133111EB)
    return z ^ (z >> _U(31))


@functools.lru_cache(maxsize=4096)
def _stream(seed: int, level: int) -> np.uint64:
    """The hash's base for (seed, level)."""
    with np.errstate(over="ignore"):
        stream = (seed & 0xFFFFFFFFFFFFFFFF) ^ (0x9E3779B97F4A7C15 * (level + 1) & (2**64 - 1))
        base: np.uint64 = _mix(np.array([stream], dtype=_U))[0]
    return base


def gaussian_hash(seed: int, level: int, i: NDArray[np.integer], j: NDArray[np.integer]) -> F64:
    """Values of mean 0 and variance 1, one per (i, j) (broadcast), from (seed, level, i, j)
    alone: the sum of the four 16-bit uniforms of one hash, centred and scaled (Irwin–Hall:
    close to a normal, bounded by ±3.46; a third of Box–Muller's cost on two hashes)."""
    base = _stream(seed, level)
    with np.errstate(over="ignore"):
        key = (np.asarray(i, dtype=np.int64).astype(_U) << _U(32)) ^ np.asarray(
            j, dtype=np.int64
        ).astype(_U)
        h = _mix(key ^ base)
    m = _U(0xFFFF)
    total = (h & m) + ((h >> _U(16)) & m) + ((h >> _U(32)) & m) + (h >> _U(48))
    # four uniforms on (k + 0.5) / 65536: mean 2, variance 4/12
    out: F64 = (total.astype(np.float64) + 2.0) * (_SQRT3 / 65536.0) - 2.0 * _SQRT3
    return out


def fbm_window(
    seed: int,
    hurst: float,
    sigma: float,
    level: int,
    i0: int,
    j0: int,
    ni: int,
    nj: int,
    *,
    start: int = 0,
) -> F64:
    """Heights of the lattice points (i0 + a, j0 + b), a < ni, b < nj, of level ``level``: an
    (nj, ni) array, rows along j. Indices wrap modulo 2^level.

    With ``start`` > 0 the surface is detail only: zero on every level up to ``start``, the
    displacements beginning at level start + 1 with ``sigma`` in the place of level 1's (what a
    DEM of level ``start``'s spacing lacks)."""
    if not 0.0 < hurst < 1.0:
        raise ValueError(f"Expected a Hurst exponent in (0, 1), got {hurst}")
    if not 0 <= level <= MAX_LEVEL:
        raise ValueError(f"Expected a level in 0..{MAX_LEVEL}, got {level}")
    if ni < 1 or nj < 1:
        raise ValueError(f"Expected a window of at least 1×1 points, got {ni}×{nj}")
    if not 0 <= start <= MAX_LEVEL:
        raise ValueError(f"Expected a start level in 0..{MAX_LEVEL}, got {start}")
    return _window(seed, effective_hurst(hurst), sigma, level, i0, j0, ni, nj, start)


#: Measured scaling of the scheme's increments (slope/2 of the mean squared increment over lags
#: of 1..64 cells, four seeds) against the exponent its displacements shrink by: the scheme
#: smooths at high H and roughens at low H, so the exponent used is read back from this table.
_MEASURED = np.array(
    [0.162, 0.21, 0.269, 0.339, 0.42, 0.508, 0.604, 0.702, 0.797, 0.878, 0.936, 0.97, 0.992]
)
_USED = np.array([0.05, 0.15, 0.25, 0.35, 0.45, 0.55, 0.65, 0.75, 0.85, 0.95, 1.05, 1.15, 1.3])


def effective_hurst(hurst: float) -> float:
    """The displacement exponent that gives increments scaling as ``hurst`` (calibrated; the
    scheme cannot go rougher than about 0.16 nor smoother than about 0.99)."""
    return float(np.interp(hurst, _MEASURED, _USED))


def _window(
    seed: int, h: float, sigma: float, level: int, i0: int, j0: int, ni: int, nj: int, start: int
) -> F64:
    if start > 0 and level <= start:
        return np.zeros((nj, ni))
    if level == 0:
        # one value: the four corners of the square are one point on the torus
        v = gaussian_hash(seed, 0, np.zeros(1, np.int64), np.zeros(1, np.int64))[0]
        return np.full((nj, ni), sigma * v)
    # the parent window covers this one's points and their neighbours, one parent cell more
    pi0, pj0 = (i0 >> 1) - 1, (j0 >> 1) - 1
    pi1, pj1 = ((i0 + ni) >> 1) + 2, ((j0 + nj) >> 1) + 2
    parent = _window(seed, h, sigma, level - 1, pi0, pj0, pi1 - pi0, pj1 - pj0, start)
    n = 1 << level
    # the child window over the parent's extent: even points are the parent's
    ci0, cj0 = 2 * pi0, 2 * pj0
    cni, cnj = 2 * (pi1 - pi0) - 1, 2 * (pj1 - pj0) - 1
    child = np.zeros((cnj, cni))
    child[::2, ::2] = parent
    ii = ci0 + np.arange(cni)
    jj = cj0 + np.arange(cnj)
    # Saupe's random midpoint displacement with successive random additions: each half-step
    # shrinks the displacement by 2^(-H/2) and adds it to the new points *and* the old ones,
    # which keeps the increments' scaling close to fBm's for every H (plain midpoint
    # displacement drifts towards rougher surfaces as H grows)
    rel = level - start
    d_square = sigma * 2.0 ** (-(2 * rel - 1) * h / 2.0)
    d_diamond = sigma * 2.0 ** (-rel * h)
    odd_i, odd_j = ii[1::2] % n, jj[1::2] % n
    even_i, even_j = ii[0::2] % n, jj[0::2] % n
    # square step: cell centres (odd, odd) from their four corners; then the corners move too
    c = (parent[:-1, :-1] + parent[:-1, 1:] + parent[1:, :-1] + parent[1:, 1:]) / 4.0
    # (i, j) broadcast over the window: columns along i, rows along j
    ci_o, rj_o, ci_e, rj_e = odd_i[None, :], odd_j[:, None], even_i[None, :], even_j[:, None]
    child[1::2, 1::2] = c + d_square * gaussian_hash(seed, 4 * level - 3, ci_o, rj_o)
    child[0::2, 0::2] += d_square * gaussian_hash(seed, 4 * level - 2, ci_e, rj_e)
    # diamond step: edge midpoints from two corners and two centres; then all the others move
    centres = child[1::2, 1::2]
    corners = child[0::2, 0::2]
    # made-up rows and columns at the window's border (its edge repeated)
    up = np.concatenate([centres[:1], centres, centres[-1:]], axis=0)
    left = np.concatenate([centres[:, :1], centres, centres[:, -1:]], axis=1)
    e1 = (corners[:, :-1] + corners[:, 1:] + up[:-1] + up[1:]) / 4.0
    e2 = (corners[:-1, :] + corners[1:, :] + left[:, :-1] + left[:, 1:]) / 4.0
    child[0::2, 1::2] = e1 + d_diamond * gaussian_hash(seed, 4 * level - 1, ci_o, rj_e)
    child[1::2, 0::2] = e2 + d_diamond * gaussian_hash(seed, 4 * level - 1, ci_e, rj_o)
    child[0::2, 0::2] += d_diamond * gaussian_hash(seed, 4 * level, ci_e, rj_e)
    child[1::2, 1::2] += d_diamond * gaussian_hash(seed, 4 * level, ci_o, rj_o)
    # the window's border points had a padded (made-up) neighbour: the margin crops them away
    oi, oj = i0 - ci0, j0 - cj0
    return child[oj : oj + nj, oi : oi + ni].copy()
