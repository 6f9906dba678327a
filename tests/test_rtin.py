"""The RTIN mesher keeps its error bound exactly, covers its tile and has no T-junction."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from _synthetic import fbm_heights
from lodscape.terrain.rtin import Rtin, mesh_error, rtin


def _grids() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(11)
    return {
        "fbm-65": fbm_heights(65, seed=1).astype(np.float64),
        "fbm-257": fbm_heights(257, seed=2, relief=400).astype(np.float64),
        "noise-33": rng.normal(0.0, 10.0, (33, 33)),
        "cliff-17": np.where(np.arange(17)[None, :] > 8, 100.0, 0.0) * np.ones((17, 1)),
        "plane-9": np.add.outer(np.arange(9) * 3.0, np.arange(9) * -2.0),
    }


@pytest.mark.parametrize("name", list(_grids()))
@pytest.mark.parametrize("max_error", [0.0, 0.5, 2.0, 10.0])
def test_mesh_keeps_the_bound_at_every_grid_point(name: str, max_error: float) -> None:
    h = _grids()[name]
    v, t = Rtin(h).mesh(max_error)
    assert mesh_error(h, v, t) <= max_error + 1e-9
    n = h.shape[0] - 1
    # the triangles tile the square: their areas add up to it
    p = v[t].astype(np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
    assert area.sum() == pytest.approx(n * n)
    _assert_conforming(v, t, n)


def _assert_conforming(v: np.ndarray, t: np.ndarray, n: int) -> None:
    """Conforming: an edge inside the n×n square is shared by exactly two triangles (a
    T-junction would leave a longer edge with one triangle and two shorter ones with one
    each)."""
    pts = [tuple(p) for p in v.tolist()]
    edges = Counter(
        tuple(sorted((pts[tri[a]], pts[tri[b]])))
        for tri in t.tolist()
        for a, b in ((0, 1), (1, 2), (2, 0))
    )
    for (p0, p1), count in edges.items():
        on_border = any(p0[k] == p1[k] and p0[k] in (0, n) for k in (0, 1))
        assert count == (1 if on_border else 2), (p0, p1, count)


def test_zero_error_is_the_full_grid_and_a_plane_is_two_triangles() -> None:
    h = _grids()["fbm-65"]
    _, t = rtin(h, 0.0)
    assert len(t) == 2 * 64 * 64
    plane = _grids()["plane-9"]
    v, t = rtin(plane, 0.0)
    assert len(t) == 2
    assert sorted(map(tuple, v.tolist())) == [(0, 0), (0, 8), (8, 0), (8, 8)]


def test_a_larger_bound_never_needs_more_triangles() -> None:
    r = Rtin(_grids()["fbm-257"])
    counts = [len(r.mesh(e)[1]) for e in (0.0, 0.25, 1.0, 4.0, 16.0, 1e9)]
    assert counts == sorted(counts, reverse=True)
    assert counts[-1] == 2


def test_the_mesher_is_tighter_than_martinis_midpoint_error() -> None:
    """Martini's error (at hypotenuse midpoints only) can let a mesh exceed its bound; ours is
    measured over every grid point, so at the same request it keeps to it."""
    pymartini = pytest.importorskip("pymartini")
    h = _grids()["fbm-257"]
    tile = pymartini.Martini(257).create_tile(h.astype(np.float32))
    mv, mt = tile.get_mesh(5.0)
    assert mesh_error(h, mv, mt) > 5.0  # the peer overshoots here
    assert mesh_error(h, *rtin(h, 5.0)) <= 5.0


@pytest.mark.parametrize(
    ("heights", "message"),
    [
        (np.zeros((300, 300)), "2\\^k\\+1"),
        (np.zeros((17, 9)), "2\\^k\\+1"),
        (np.full((5, 5), np.nan), "finite"),
    ],
)
def test_bad_grids_are_refused(heights: np.ndarray, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Rtin(heights)


@pytest.mark.parametrize("size", [2, 3, 5, 9, 17, 33, 65])
def test_the_numpy_rtin_is_the_numba_rtin(size: int) -> None:
    """``rtin_numpy`` (the tiles' mesher, no numba to load) gives the errors and the meshes of
    ``Rtin`` with every level exact, on rough and smooth grids, at any bound."""
    from lodscape.terrain import rtin_numpy

    rng = np.random.default_rng(size)
    for k in range(4):
        h = rng.normal(size=(size, size)).cumsum(0).cumsum(1) * rng.uniform(0.1, 10.0)
        if k == 3:
            h = np.round(h)  # ties: equal errors where the bound is
        want = Rtin(h, exact_span=max(size, 2))
        got = rtin_numpy.errors(h)
        np.testing.assert_allclose(got, want.errors, rtol=1e-9, atol=1e-9)
        for bound in (0.0, 0.5, 1.0, 4.0, 1e9):
            va, ta = want.mesh(bound)
            vb, tb = rtin_numpy.mesh(got, bound)
            assert len(ta) == len(tb)
            # the same triangles, each with its vertices in the same (winding) order
            a = {
                tuple(
                    map(tuple, np.roll(va[t], -int(np.argmin(va[t][:, 0] * 99 + va[t][:, 1])), 0))
                )
                for t in ta
            }
            b = {
                tuple(
                    map(tuple, np.roll(vb[t], -int(np.argmin(vb[t][:, 0] * 99 + vb[t][:, 1])), 0))
                )
                for t in tb
            }
            assert a == b


def _turned(v: np.ndarray, t: np.ndarray) -> set[tuple[tuple[int, int], ...]]:
    """Each triangle's vertices from its smallest one, in its winding order."""
    out = set()
    for tri in t:
        p = v[tri]
        first = int(np.lexsort((p[:, 1], p[:, 0]))[0])
        out.add(tuple((int(x), int(y)) for x, y in np.roll(p, -first, axis=0)))
    return out


@pytest.mark.parametrize("m", [2, 8])
def test_a_cut_with_blocks_keeps_each_triangles_error_and_its_blocks_within_the_bound(
    m: int,
) -> None:
    """``rtin_numpy.with_blocks``: cut at E, each triangle's own error over the grid plus the
    largest block it reaches stays within E (E no less than the largest block), the mesh is
    conforming, a uniform map is the plain cut at E less it, and an uneven one needs no more
    triangles than the plain cut at E less its largest block."""
    from lodscape.terrain import rtin_numpy

    h = _grids()["fbm-65"]
    err = rtin_numpy.errors(h)
    np.testing.assert_array_equal(rtin_numpy.merged(err), err)  # errors are merged already
    side = 64 // m
    rng = np.random.default_rng(m)
    blocks = rng.uniform(0.0, 4.0, (m, m))
    field = rtin_numpy.with_blocks(err, blocks)
    uniform = rtin_numpy.with_blocks(err, np.full((m, m), 3.0))
    for bound in (4.0, 12.0, 40.0):
        v, t = rtin_numpy.mesh(field, bound)
        assert len(t) <= len(rtin_numpy.mesh(err, bound - blocks.max())[1])
        vu, tu = rtin_numpy.mesh(uniform, bound)
        vp, tp = rtin_numpy.mesh(err, bound - 3.0)
        assert np.array_equal(vu, vp)
        assert np.array_equal(tu, tp)
        for i, tri in enumerate(t):
            # its own error over the grid, and the blocks whose inside it reaches
            own = mesh_error(h, v, t[i : i + 1])
            (c0, r0), (c1, r1) = v[tri].min(axis=0) // side, -(-v[tri].max(axis=0) // side)
            reach = blocks[r0 : max(r1, r0 + 1), c0 : max(c1, c0 + 1)]
            assert own + reach.max() <= bound + 1e-9
        _assert_conforming(v, t, 64)
