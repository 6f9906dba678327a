"""Tile meshes cut by error (``terrain.tin_tiles``): each keeps to its bound against the tile's
curved lattice, the selection's ladder charges what the meshes keep to, and a picture drawn
with them keeps the screen-space bound on far fewer triangles than the grids."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, periodic_fbm, write_dem
from lodscape import Camera
from lodscape.geo.frames import geodetic_to_ecef, up_vector
from lodscape.geo.keys import mesh_key
from lodscape.geo.tiles import Tile, merc_to_lonlat, tile_id, tile_size
from lodscape.stream import StreamOptions
from lodscape.terrain import rtin_numpy
from lodscape.terrain.mesh import grid_coordinates
from lodscape.terrain.pyramid import TileStats
from lodscape.terrain.tin_tiles import (
    LADDER,
    SPLIT_RUNG,
    TRUTH_SPLIT_RUNG,
    ErrorLadder,
    SplitBeforeFinest,
    cache_order,
    ladder_errors,
    tin_tile_mesh,
)


def _inside(
    corners: np.ndarray, cols: np.ndarray, rows: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The points (column, row) of a grid ``cols``, ``rows`` inside a triangle of (3, 2)
    ``corners``, its edges included, and their barycentric weights."""
    a, b, c = corners
    lo, hi = np.floor(corners.min(axis=0)), np.ceil(corners.max(axis=0))
    box = (cols >= lo[0]) & (cols <= hi[0]) & (rows >= lo[1]) & (rows <= hi[1])
    q = np.column_stack([cols[box], rows[box]]).astype(np.float64)
    m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
    uv = np.linalg.solve(m, (q - a).T).T
    w = np.column_stack([1.0 - uv.sum(axis=1), uv])
    inside = (w >= -1e-9).all(axis=1)
    return q[inside], w[inside]


def _lattice_error(z: int, x: int, y: int, h: np.ndarray, mesh: Any) -> float:
    """The largest distance, along the local vertical, between a lattice point (on the curved
    Earth) and the mesh's flat triangle over it."""
    s = h.shape[0] - 1
    xs, ys = grid_coordinates(z, x, y, s)
    lon, lat = merc_to_lonlat(xs[None, :], ys[:, None])
    lon, lat = np.broadcast_to(lon, h.shape), np.broadcast_to(lat, h.shape)
    p = geodetic_to_ecef(lon, lat, h.astype(np.float64))
    v = mesh.vertices.astype(np.float64)
    surface = v[:, 5] == 0.0
    n = int(surface.sum())
    tris = mesh.indices.astype(np.int64)
    tris = tris[(tris < n).all(axis=1)]  # skirts out
    cr = v[:n, 3:5] * s  # (column, row) of each vertex
    pos = v[:n, :3] + mesh.center
    worst = 0.0
    rows, cols = np.mgrid[0 : s + 1, 0 : s + 1]
    for t in tris:
        q, w = _inside(cr[t], cols, rows)
        if not len(q):
            continue
        flat = w @ pos[t]
        ij = q.astype(np.int64)
        real = p[ij[:, 1], ij[:, 0]]
        ups = up_vector(lon[ij[:, 1], ij[:, 0]], lat[ij[:, 1], ij[:, 0]])
        worst = max(worst, float(np.abs(np.einsum("ij,ij->i", real - flat, ups)).max()))
    return worst


@pytest.mark.parametrize("z", [7, 12])
@pytest.mark.parametrize("bound", [0.0, 2.0, 25.0])
def test_a_tin_tile_keeps_its_bound_against_the_curved_lattice(z: int, bound: float) -> None:
    # a big tile (z 7: 313 km) sags kilometres under a flat triangle: the mesh must split for it
    rng = np.random.default_rng(z)
    h = fbm_heights(65, seed=z, relief=300.0).astype(np.float64) + rng.normal(0, 1, (65, 65))
    x, y = (1 << z) // 3, (1 << z) // 3
    key = mesh_key(tile_id(Tile(x, y, z)), 3)
    mesh = tin_tile_mesh(key, z, x, y, h, bound)
    assert mesh is not None
    got = _lattice_error(z, x, y, h, mesh)
    # float32 vertices relative to a centre up to 220 km away: centimetres
    assert got <= bound * 1.001 + 0.05, got
    surface = int((mesh.vertices[:, 5] == 0).sum())
    if bound > 0:
        assert mesh.triangles < 2 * 64 * 64 + 8 * 64, mesh.triangles
    # skirts hang from the four sides: every edge vertex has its copy
    uv = mesh.vertices[:surface, 3:5]
    edge = ((uv == 0.0) | (uv == 1.0)).any(axis=1).sum()
    assert mesh.vertices.shape[0] - surface >= edge


def test_flat_ground_on_a_big_tile_is_split_for_the_earths_curvature() -> None:
    h = np.zeros((65, 65))
    z, x, y = 6, 20, 20
    key = mesh_key(tile_id(Tile(x, y, z)), 0)
    coarse = tin_tile_mesh(key, z, x, y, h, 1e6)
    tight = tin_tile_mesh(key, z, x, y, h, 10.0)
    assert coarse is not None
    assert tight is not None
    # within 1 %: measured above the centre's tangent plane, a 626 km tile's sides lean
    assert _lattice_error(z, x, y, h, tight) <= 10.0 * 1.01
    # flat heights, yet the Earth bends under a 626 km tile: hundreds of surface triangles
    # where a flat Earth would need two (as a bound beyond the sag gives)
    assert _surface_triangles(coarse) == 2
    assert _surface_triangles(tight) > 100


def _surface_triangles(mesh: Any) -> int:
    """Triangles of a mesh's surface, its skirts left out."""
    n = int((mesh.vertices[:, 5] == 0.0).sum())
    return int((mesh.indices < n).all(axis=1).sum())


def test_nodata_heights_give_no_tin() -> None:
    h = np.zeros((65, 65))
    h[3, 4] = np.nan
    assert tin_tile_mesh(mesh_key(tile_id(Tile(1, 1, 5)), 0), 5, 1, 1, h, 1.0) is None


def test_the_ladder_charges_each_slot_its_bound_over_the_finest_grid() -> None:
    error = np.array([[40.0, 8.0], [20.0, 4.0], [5.0, 0.0]])  # grids × tiles
    got = ladder_errors(error)
    assert got.shape == (len(LADDER), 2)
    assert np.allclose(got[:, 0], np.array(LADDER) * 40.0 + 5.0)
    assert np.allclose(got[:, 1], np.array(LADDER) * 8.0)
    # coarsest first, the whole finest grid last
    assert np.all(np.diff(got, axis=0) <= 0)
    assert LADDER[-1] == 0.0


def test_the_ladder_keeps_the_whole_grid_for_tiles_that_cannot_split(tmp_path: Path) -> None:
    with _tin_scene(tmp_path, seed=2) as scene:
        tree = scene.tree
        assert isinstance(tree, ErrorLadder)
        assert tree.grids == (64,) * len(LADDER)
        for z in (tree.zmin, tree.zmax):
            x, y = tree.roots() if z == tree.zmin else _some_tiles(tree, z)
            st = tree.level(z).stats(x, y)
            assert isinstance(st, TileStats)
            assert st.error.shape == (len(LADDER), x.size)
            base = tree.base.level(z).stats(x, y).error
            mine = ladder_errors(base)
            if z < tree.zmax:
                # a tile that can split is drawn no finer than SPLIT_RUNG (the whole grid
                # among the rest): where it needs less it splits
                assert np.array_equal(st.error[: SPLIT_RUNG + 1], mine[: SPLIT_RUNG + 1])
                assert np.all(st.error[SPLIT_RUNG + 1 :] == st.error[SPLIT_RUNG])
                assert np.all(mine[SPLIT_RUNG + 1] < mine[SPLIT_RUNG])
            else:  # the finest level's tiles have every rung, and the whole grid
                assert np.array_equal(st.error, mine)
                assert np.allclose(st.error[-1], base[-1])


def test_the_level_above_the_finest_is_cut_from_the_truth(tmp_path: Path) -> None:
    """Tiles one level above the finest are meshed from the grid twice as fine as their finest,
    the truth the tree measures against (their children's finest grids): a slot costs its bound
    alone, not plus the finest grid's own error, and the mesh keeps it against the truth."""
    with _tin_scene(tmp_path, seed=4) as scene:
        tree = scene.tree
        assert isinstance(tree, ErrorLadder)
        z = tree.from_truth
        assert z == tree.zmax - 1
        assert (tree.segments(z), tree.segments(z + 1)) == (128, 64)
        x, y = _some_tiles(tree, z)
        got = tree.level(z).stats(x, y).error
        base = tree.base.level(z).stats(x, y).error
        bounds = (np.asarray(LADDER)[:, None] * base[0]).astype(np.float32)
        rungs = slice(0, TRUTH_SPLIT_RUNG + 1)
        assert np.array_equal(got[rungs], bounds[rungs])
        # finer than its split rung it splits (the rest cost what that rung does)
        assert np.all(got[TRUTH_SPLIT_RUNG + 1 :] == got[TRUTH_SPLIT_RUNG])
        # the sum the other levels pay: the finest grid misses the truth
        assert np.all(ladder_errors(base)[rungs] > got[rungs])
        provider = scene.provider
        for i in range(min(4, x.size)):
            tx, ty = int(x[i]), int(y[i])
            key = mesh_key(tile_id(Tile(tx, ty, z)), 6)
            data = provider.fetch(key)
            h = np.frombuffer(data, np.float32).reshape(129, 129)
            mesh = provider.decode(key, data)
            bound = tree.threshold(z, tx, ty, 6)
            assert _lattice_error(z, tx, ty, h, mesh) <= bound * 1.001 + 0.05
            # the grid is the truth: the children's finest grids, sampled on their own
            for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                child = mesh_key(tile_id(Tile(2 * tx + dx, 2 * ty + dy, z + 1)), 0)
                ch = np.frombuffer(provider.fetch(child), np.float32).reshape(65, 65)
                part = h[64 * dy : 64 * dy + 65, 64 * dx : 64 * dx + 65]
                assert np.allclose(part, ch, atol=0.01), float(np.abs(part - ch).max())


def test_a_rung_change_cuts_the_kept_rtin_again(tmp_path: Path) -> None:
    """A tile met at another rung (the camera moved) is cut from its kept RTIN: no heights
    read again, the same mesh as one made from nothing."""
    with _tin_scene(tmp_path, seed=5, relief=400.0) as scene:
        provider = scene.provider
        tree = scene.tree
        assert isinstance(tree, ErrorLadder)
        reads: list[int] = []
        sample_grid = provider.source.sample_grid

        def counted(*args: Any) -> Any:
            reads.append(1)
            return sample_grid(*args)

        provider.source.sample_grid = counted  # type: ignore[method-assign]
        x, y = _some_tiles(tree, tree.zmax)
        z, tx, ty = tree.zmax, int(x[0]), int(y[0])
        tid = tile_id(Tile(tx, ty, z))
        first = provider.fetch(mesh_key(tid, 3))
        provider.decode(mesh_key(tid, 3), first)  # meshed once: its RTIN kept
        assert len(reads) == 1
        heights = np.frombuffer(first, np.float32).reshape(65, 65)
        for slot in (3, 9, 17, len(LADDER) - 1):
            key = mesh_key(tid, slot)
            data = provider.fetch(key)
            assert data == first
            got = provider.decode(key, data)
            fresh = tin_tile_mesh(key, z, tx, ty, heights, tree.threshold(z, tx, ty, slot))
            assert fresh is not None
            assert got is not None
            assert np.array_equal(got.indices, fresh.indices)
            assert np.array_equal(got.vertices, fresh.vertices)
            assert np.array_equal(got.center, fresh.center)
        assert len(reads) == 1  # the heights were read once
        # the mesh at the whole grid has every vertex; the coarser rungs fewer
        coarse = provider.decode(mesh_key(tid, 3), first)
        assert coarse.vertices.shape[0] < got.vertices.shape[0]


def test_grids_are_split_before_a_tile_takes_its_finest(tmp_path: Path) -> None:
    """Frames that geomorph draw regular grids: a tile that can split is not drawn with its
    finest grid (it costs its next grid's error, so a tile that needs it splits); the finest
    level's tiles keep it. The same view then draws fewer triangles, within the bound."""
    from lodscape.lod.select import SelectOptions, select
    from test_screen_error import _cameras

    path = _fbm_dem(tmp_path, seed=2, relief=500.0)
    streamed = lodscape.open(path, lodscape.SceneOptions(stream=StreamOptions()))
    still = lodscape.open(path, lodscape.SceneOptions(meshes="grid"))
    try:
        tree = streamed.tree
        assert isinstance(tree, SplitBeforeFinest)
        assert isinstance(still.tree, SplitBeforeFinest)
        base = tree.base
        for z in (tree.zmin, tree.zmax):
            x, y = tree.roots() if z == tree.zmin else _some_tiles(tree, z)
            got = tree.level(z).stats(x, y).error
            own = np.asarray(base.level(z).stats(x, y).error)
            assert np.array_equal(got[:-1], own[:-1])
            if z < tree.zmax:
                assert np.array_equal(got[-1], own[-2])
                assert np.all(own[-1] < own[-2])
            else:
                assert np.array_equal(got[-1], own[-1])
        opts = SelectOptions()
        last = len(tree.grids) - 1
        split_tris = whole_tris = whole_last = 0
        for cam in _cameras(streamed, 6, seed=5):
            fitted = streamed.prepare(cam)
            split = select(opts, fitted, tree)
            whole = select(opts, fitted, base)
            assert np.all(split.grid[split.z < tree.zmax] < last)
            assert float(split.sse.max(initial=0.0)) <= opts.max_sse
            whole_last += int(np.sum(whole.grid[whole.z < tree.zmax] == last))
            split_tris += split.triangles
            whole_tris += whole.triangles
        assert whole_last > 0  # the cameras ask for finest grids above the finest level
        assert split_tris < whole_tris
    finally:
        streamed.close()
        still.close()


def _fbm_dem(tmp_path: Path, seed: int, relief: float) -> Path:
    """A 256² fBm (10 m, UTM 17N) written as a GeoTIFF."""
    path = tmp_path / "dem.tif"
    write_dem(str(path), periodic_fbm(256, seed=seed, relief=relief), crs="EPSG:32617",
              west=700000.0, north=4070000.0, res=10.0)  # fmt: skip
    return path


@contextmanager
def _tin_scene(tmp_path: Path, seed: int, relief: float = 500.0) -> Iterator[Any]:
    """A scene meshed by error over ``_fbm_dem``."""
    scene = lodscape.open(_fbm_dem(tmp_path, seed, relief), lodscape.SceneOptions(meshes="tin"))
    try:
        yield scene
    finally:
        scene.close()


def _some_tiles(tree: Any, z: int) -> tuple[np.ndarray, np.ndarray]:
    x, y = tree.roots()
    for _ in range(tree.zmin, z):
        x = (2 * x[:, None] + np.array([0, 1, 0, 1])).ravel()
        y = (2 * y[:, None] + np.array([0, 0, 1, 1])).ravel()
    ok = tree.level(z).stats(x, y).exists
    return x[ok], y[ok]


def test_tins_draw_the_same_picture_within_the_bound_on_fewer_triangles(tmp_path: Path) -> None:
    """Grids against TINs on one DEM and cameras: the TINs keep the bound as measured on
    screen, spend more of it, and draw well under the grids' triangles."""
    from test_screen_error import BOUND, H, W, _cameras, screen_error

    z = periodic_fbm(512, seed=23, relief=700.0)
    path = tmp_path / "dem.tif"
    write_dem(str(path), z, crs="EPSG:32617", west=700000.0, north=4070000.0, res=10.0)
    opts = dict(ellipsoid=False, anisotropy=1.0)
    tin = lodscape.open(path, lodscape.SceneOptions(meshes="tin", **opts))  # type: ignore[arg-type]
    grid = lodscape.open(path, lodscape.SceneOptions(meshes="grid", **opts))  # type: ignore[arg-type]
    fine = lodscape.open(path, lodscape.SceneOptions(
        meshes="grid", select=lodscape.SelectOptions(max_sse=0.05), **opts))  # type: ignore[arg-type]  # fmt: skip
    try:
        ratios, tails, grid_tails = [], [], []
        for cam in _cameras(tin, 6, seed=4):
            cam = Camera(cam.lon, cam.lat, cam.alt, heading=cam.heading, pitch=cam.pitch,
                         width=W, height=H)  # fmt: skip
            _, d_tin = tin.render(cam)
            _, d_grid = grid.render(cam)
            _, d_fine = fine.render(cam)
            floor = np.percentile(screen_error(path, z, fine.prepare(cam), d_fine), 99.9)
            e_tin = screen_error(path, z, tin.prepare(cam), d_tin)
            e_grid = screen_error(path, z, grid.prepare(cam), d_grid)
            assert e_tin.size > 0.2 * W * H
            tails.append(float(np.percentile(e_tin, 99.9)))
            grid_tails.append(float(np.percentile(e_grid, 99.9)))
            assert tails[-1] <= BOUND + floor, (tails, floor)
            assert tin.frame_stats()["max_sse_px"] <= BOUND + 1e-6
            ratios.append(tin.frame_stats()["triangles"] / grid.frame_stats()["triangles"])
        print("triangles tin/grid", np.round(ratios, 2), "p99.9 tin", np.round(tails, 2),
              "grid", np.round(grid_tails, 2))  # fmt: skip
        assert np.median(ratios) < 0.6, ratios
        assert np.median(tails) > np.median(grid_tails), (tails, grid_tails)
    finally:
        tin.close()
        grid.close()
        fine.close()


def test_meshes_auto_keeps_grids_where_frames_geomorph(tmp_path: Path) -> None:
    path = tmp_path / "dem.tif"
    write_dem(str(path), periodic_fbm(128, seed=1, relief=200.0), crs="EPSG:32617",
              west=700000.0, north=4070000.0, res=10.0)  # fmt: skip
    one_shot = lodscape.open(path)
    streamed = lodscape.open(path, lodscape.SceneOptions(stream=StreamOptions()))
    gpu = lodscape.open(path, lodscape.SceneOptions(terrain_mode="gpu"))
    try:
        assert isinstance(one_shot.tree, ErrorLadder)
        assert not isinstance(streamed.tree, ErrorLadder)
        assert not isinstance(gpu.tree, ErrorLadder)
    finally:
        one_shot.close()
        streamed.close()
        gpu.close()
    with pytest.raises(ValueError, match="meshes"):
        lodscape.SceneOptions(meshes="rtin")


def _shaded_per_triangle(tris: np.ndarray, cache: int = 32) -> float:
    """Vertices shaded per triangle through a FIFO post-transform cache of ``cache`` entries."""
    queue: list[int] = []
    held: set[int] = set()
    missed = 0
    for v in tris.ravel().tolist():
        if v not in held:
            missed += 1
            queue.append(v)
            held.add(v)
            if len(queue) > cache:
                held.discard(queue.pop(0))
    return missed / len(tris)


@pytest.mark.parametrize("bound", [0.05, 1.0, 8.0])
def test_tin_triangles_are_drawn_in_an_order_a_vertex_cache_reuses(bound: float) -> None:
    """A tile's TIN is the RTIN's triangles, wound as it winds them, in Z order of their
    centres: neighbours together, so a GPU shades about two thirds of a vertex per triangle
    (the cut's own order, level by level, shades nearly three)."""
    rng = np.random.default_rng(4)
    heights = np.cumsum(np.cumsum(rng.normal(size=(65, 65)), axis=0), axis=1)
    verts, tris = rtin_numpy.mesh(rtin_numpy.errors(heights), bound)
    ordered = cache_order(verts, tris)
    assert sorted(map(tuple, ordered.tolist())) == sorted(map(tuple, tris.tolist()))
    assert _shaded_per_triangle(tris) > 2.0
    assert _shaded_per_triangle(ordered) < 0.8
    mesh = tin_tile_mesh(1, 14, 3000, 6000, heights, bound)
    assert mesh is not None
    on_ground = mesh.vertices[:, 5] == 0.0  # skirt vertices are flagged 1
    surface = mesh.indices[on_ground[mesh.indices].all(axis=1)]
    assert len(surface) > 10
    assert _shaded_per_triangle(surface) < 0.8


def _surface_error(mesh: Any, h: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    """The largest vertical difference between a tile's mesh (its heights ``h`` on an
    (S+1)² grid) and ``truth`` on a grid ``f`` times as fine over the same square, where
    ``valid`` (the data's own points, not its fill)."""
    s = h.shape[0] - 1
    f = (truth.shape[0] - 1) // s
    v = mesh.vertices.astype(np.float64)
    n = int((v[:, 5] == 0.0).sum())
    tris = mesh.indices.astype(np.int64)
    tris = tris[(tris < n).all(axis=1)]  # skirts out
    cr = np.rint(v[:n, 3:5] * s).astype(np.int64)  # (column, row) on the tile's grid
    hv = h[cr[:, 1], cr[:, 0]].astype(np.float64)
    rows, cols = np.mgrid[0 : s * f + 1, 0 : s * f + 1] / f
    worst = 0.0
    for t in tris:
        q, w = _inside(cr[t].astype(np.float64), cols, rows)
        flat = w @ hv[t]
        ij = np.rint(q * f).astype(np.int64)
        off = np.abs(flat - truth[ij[:, 1], ij[:, 0]])[valid[ij[:, 1], ij[:, 0]]]
        worst = max(worst, float(off.max(initial=0.0)))
    return worst


def test_a_tile_is_cut_against_its_grids_own_error_block_by_block(tmp_path: Path) -> None:
    """A tile above the level meshed from the truth is cut at its slot's whole charge (its
    bound plus its finest grid's own error), each triangle's error over the grid counted with
    the grid's own error in the blocks it reaches (its descendants' recorded errors): within
    the charge against the truth, on fewer triangles than the bound over the grid alone where
    the ground is rough in part of the tile and smooth in the rest."""
    z = periodic_fbm(512, seed=9, relief=600.0)
    z[:, 256:] = z[:, 256:] * 0.05 + 0.95 * float(z.mean())  # the east half nearly flat
    path = tmp_path / "dem.tif"
    write_dem(str(path), z, crs="EPSG:32617", west=700000.0, north=4070000.0, res=10.0)
    scene = lodscape.open(path, lodscape.SceneOptions(meshes="tin"))
    try:
        tree, provider = scene.tree, scene.provider
        assert isinstance(tree, ErrorLadder)
        zt = tree.zmax - 2
        assert zt > tree.zmin
        assert zt != tree.from_truth
        x, y = _some_tiles(tree, zt)
        fewer = ignored = 0
        for i in range(x.size):
            tx, ty = int(x[i]), int(y[i])
            # the truth under the tile: the data at the finest level's finest grids
            xs, ys = grid_coordinates(zt, tx, ty, 256)
            got, valid = provider.source.sample_grid(xs, ys, float(tile_size(zt)) / 256)
            truth, valid = np.asarray(got, np.float64), np.asarray(valid, bool)
            if valid.mean() < 0.1:
                continue  # the data's edge: little to measure
            for slot in (4, SPLIT_RUNG):
                key = mesh_key(tile_id(Tile(tx, ty, zt)), slot)
                bound, blocks = tree.cut(zt, tx, ty, slot)
                assert blocks is not None
                assert blocks.shape == (4, 4)
                charge = float(tree.level(zt).stats(np.array([tx]), np.array([ty])).error[slot, 0])
                assert bound == pytest.approx(charge, rel=1e-5)
                data = provider.fetch(key)
                h = np.frombuffer(data, np.float32).reshape(65, 65)
                mesh = provider.decode(key, data)
                assert _surface_error(mesh, h, truth, valid) <= bound + 0.15
                plain = tin_tile_mesh(key, zt, tx, ty, h, tree.threshold(zt, tx, ty, slot))
                assert plain is not None
                assert mesh.indices.size <= plain.indices.size
                fewer += mesh.indices.size < plain.indices.size
                # the whole charge against the grid alone, the blocks left out: over it
                blind = tin_tile_mesh(key, zt, tx, ty, h, bound)
                assert blind is not None
                ignored += _surface_error(blind, h, truth, valid) > bound + 0.15
        assert fewer >= 4  # the rough tiles' smooth blocks take the allowance
        assert ignored > 0
    finally:
        scene.close()
