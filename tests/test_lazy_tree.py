"""The tile tree made as the selection reaches it (terrain.lazy, issue 36): the same tree as the
eager walk where its chunks reach the data's resolution, an error that bounds the eager (exact)
one where they do not, and an open that reads overviews only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from _synthetic import fbm_heights, periodic_fbm, write_dem
from lodscape.data import sample_dem_path
from lodscape.lod.camera import Camera
from lodscape.options import SceneOptions
from lodscape.scene import Scene
from lodscape.terrain.lazy import LazyTree
from lodscape.terrain.pyramid import build_tree
from lodscape.terrain.source import RasterSource
from lodscape.terrain.tin_tiles import SplitBeforeFinest


def _every_tile(lv: object) -> tuple[np.ndarray, np.ndarray]:
    ny, nx = lv.shape  # type: ignore[attr-defined]
    ys, xs = np.nonzero(np.ones((ny, nx), bool))
    return (xs + lv.x0).astype(np.int64), (ys + lv.y0).astype(np.int64)  # type: ignore[attr-defined]


def _compare(src: RasterSource) -> tuple[float, float]:
    """(smallest lazy/exact error ratio over existing tiles and grids, largest): the exact
    errors a whole walk measures with every level against the truth itself."""
    eager = build_tree(src, block_tiles=1 << 20, reference_levels=64)
    lazy = LazyTree(src)
    try:
        assert (lazy.zmin, lazy.zmax, lazy.texture_zmax) == (
            eager.zmin,
            eager.zmax,
            eager.texture_zmax,
        )
        lo, hi = np.inf, 0.0
        for lv in eager.levels:
            x, y = _every_tile(lv)
            a, b = lv.stats(x, y), lazy.level(lv.z).stats(x, y)
            np.testing.assert_array_equal(a.exists, b.exists, err_msg=f"z{lv.z}")
            ex = a.exists
            # sampled over a chunk instead of a block: the projection's lattice differs by
            # 1/1000 of a pixel, so heights by a centimetre
            under = b.error[:, ex] < a.error[:, ex] - 0.05
            assert not under.any(), (lv.z, b.error[:, ex][under], a.error[:, ex][under])
            assert (b.min_h[ex] <= a.min_h[ex] + 0.05).all()
            assert (b.max_h[ex] >= a.max_h[ex] - 0.05).all()
            big = a.error[:, ex] > 0.5  # the ratio of errors of a metre or more
            r = b.error[:, ex][big] / a.error[:, ex][big]
            if r.size:
                lo, hi = min(lo, float(r.min())), max(hi, float(r.max()))
        return lo, hi
    finally:
        lazy.close()


def test_the_lazy_tree_is_the_eager_one_where_its_chunks_reach_the_data() -> None:
    # the last chunk's levels (their chunks sample down to the data's resolution) are exact
    with RasterSource(sample_dem_path()) as src:
        eager = build_tree(src)
        lazy = LazyTree(src)
        try:
            last = lazy.zmin + 3 * ((lazy.zmax - lazy.zmin) // 3)
            for lv in eager.levels:
                x, y = _every_tile(lv)
                a, b = lv.stats(x, y), lazy.level(lv.z).stats(x, y)
                if lv.z < last:
                    # a chunk that does not reach the data's resolution: at least the exact
                    assert (b.error[:, a.exists] >= a.error[:, a.exists] - 0.05).all()
                    continue
                np.testing.assert_array_equal(a.exists, b.exists)
                np.testing.assert_allclose(b.error, a.error, atol=0.05)
                np.testing.assert_allclose(b.min_h[a.exists], a.min_h[a.exists], atol=0.05)
                np.testing.assert_allclose(b.max_h[a.exists], a.max_h[a.exists], atol=0.05)
        finally:
            lazy.close()


@pytest.mark.parametrize(
    ("kind", "crs", "res"),
    [
        ("periodic", "EPSG:32617", 1.0),
        ("octaves", "EPSG:4326", 1e-5),
        ("terraced", "EPSG:3035", 2.0),
        ("plain beside mountains", "EPSG:32633", 1.0),
    ],
)
def test_the_lazy_error_bounds_the_exact_one_on_unseen_dems(
    tmp_path: Path, kind: str, crs: str, res: float
) -> None:
    # DEMs deep enough that the coarse chunks do not reach the data: their error below it is
    # the measured tail, which must cover what the eager walk finds reading every pixel
    if kind == "periodic":
        h = periodic_fbm(1024, seed=11)
    elif kind == "plain beside mountains":
        h = _plain_beside_mountains(seed=3)
    elif kind == "octaves":
        h = fbm_heights(1025, seed=5, relief=1500.0)
    else:
        # terraces: flats and steps, a surface unlike fBm
        h = np.floor(fbm_heights(1025, seed=9, relief=600.0) / 40.0) * 40.0
    west, north = {
        "EPSG:32617": (500000.0, 4000000.0),
        "EPSG:4326": (8.0, 46.0),
        "EPSG:3035": (4200000.0, 2600000.0),
        "EPSG:32633": (400000.0, 5200000.0),
    }[crs]
    name = kind.replace(" ", "_")
    path = write_dem(str(tmp_path / f"{name}.tif"), h, crs=crs, west=west, north=north, res=res)
    with RasterSource(path) as src:
        lo, hi = _compare(src)
    assert lo >= 0.99
    # and not uselessly loose: the coarse tiles' bound within a few times the exact one
    assert hi < 6.0, hi


def _plain_beside_mountains(seed: int, n: int = 1025) -> np.ndarray:
    """fBm whose relief falls from whole in the east to 2 % in the west (a sharp shore)."""
    h = fbm_heights(n, seed=seed, relief=1500.0)
    x = np.linspace(0.0, 1.0, n)[None, :]
    w = 0.02 + 0.98 / (1.0 + np.exp(-(x - 0.5) * 40.0))
    out: np.ndarray = (h.min() + (h - h.min()) * w).astype(np.float32)
    return out


def test_a_plain_is_not_charged_the_mountains_detail(tmp_path: Path) -> None:
    # what a chunk misses below its finest level is charged by the tile's own roughness there:
    # the plain's coarse tiles stay near their exact error, far under the mountains' tail
    h = _plain_beside_mountains(seed=7)
    path = write_dem(str(tmp_path / "shore.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=1.0)  # fmt: skip
    with RasterSource(path) as src:
        eager = build_tree(src, block_tiles=1 << 20, reference_levels=64)
        lazy = LazyTree(src, keep=False)
        try:
            tailed = [z for z in range(lazy.zmin, lazy.truth) if lazy.tail(z) > 0]
            assert tailed, "the DEM is meant to be deep enough for a tail"
            worst = max(lazy.tail(z) for z in tailed)
            checked = 0
            for lv in eager.levels:
                x, y = _every_tile(lv)
                a, b = lv.stats(x, y), lazy.level(lv.z).stats(x, y)
                plain = a.exists & (x < lv.x0 + 0.4 * lv.shape[1])
                if not plain.any() or np.allclose(a.error[-1], b.error[-1], atol=0.05):
                    continue  # this level's chunks reach the data: nothing charged below
                exact, got = a.error[-1, plain], b.error[-1, plain]
                assert (got >= exact - 0.05).all()
                assert np.median(got) < 4.0 * np.median(exact) + 0.1, (lv.z, np.median(exact))
                if np.median(exact) < 0.1 * worst:
                    # a tail charged alike everywhere would put every plain tile above the worst
                    checked += 1
                    assert np.median(got) < 0.25 * worst, (lv.z, np.median(got), worst)
            assert checked
        finally:
            lazy.close()


def test_a_scene_selects_as_the_eager_tree_once_known(tmp_path: Path) -> None:
    # a small DEM: every chunk reaches the data's resolution, so nothing is estimated
    h = fbm_heights(161, seed=21, relief=700.0)
    path = write_dem(str(tmp_path / "d.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=8.0)  # fmt: skip
    with RasterSource(path) as src:
        eager = build_tree(src)
        # the trees themselves, not the error ladder TIN meshes wrap them in
        grids = SceneOptions(meshes="grid")
        lazy = Scene(src, grids, tree=LazyTree(src))  # type: ignore[arg-type]
        fixed = Scene(src, grids, tree=eager)
        try:
            assert isinstance(lazy.tree, SplitBeforeFinest)  # both scenes' grids the same way
            assert isinstance(lazy.tree.base, LazyTree)
            assert not lazy.tree.base._tails, "the DEM is meant to be small enough for no tail"
            assert lazy.tree.base.made <= 4  # the roots at most
            cams = [lazy.overview_camera(640, 360)]
            lon, lat = cams[0].lon, cams[0].lat
            for dlat, alt, pitch in [(0.01, 1500.0, -20.0), (0.02, 900.0, -8.0)]:
                cams.append(Camera(lon, lat + dlat, alt, pitch=pitch, width=640, height=360))
            for cam in cams:
                a, b = fixed.select(cam), lazy.select(cam)
                np.testing.assert_array_equal(np.sort(a.keys), np.sort(b.keys))
        finally:
            lazy.close()
            fixed.close()


def test_opening_reads_overviews_only(tmp_path: Path) -> None:
    """A raster with overviews of its own: opening it reads no pixel at full resolution, and
    a far view reads a small share of them (the tail's sample windows)."""
    import rasterio
    from rasterio.enums import Resampling

    h = periodic_fbm(4096, seed=4, relief=100.0)
    path = write_dem(str(tmp_path / "ov.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=1.0)  # fmt: skip
    with rasterio.open(path, "r+") as ds:
        ds.build_overviews([2, 4, 8, 16, 32, 64], Resampling.average)

    full: list[tuple[int, int, int, int]] = []

    class Counting(RasterSource):
        def _read_raw(self, overview, r0, r1, c0, c1):  # type: ignore[no-untyped-def]
            if overview is None:
                full.append((r0, r1, c0, c1))
            return super()._read_raw(overview, r0, r1, c0, c1)

    with Counting(path) as src:
        assert not full, "the coarse grid came from the full resolution"
        lo, hi = src.data_range
        assert 195.0 < lo < 230.0
        assert 270.0 < hi < 305.0
        scene = Scene(src)
        try:
            scene.select(scene.overview_camera(320, 180))
            pixels = sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in full)
            assert pixels < 0.1 * h.size, f"a far view read {pixels} full-resolution pixels"
        finally:
            scene.close()


def test_a_streamed_frame_never_waits_for_statistics(tmp_path: Path) -> None:
    """Without ``wait`` a selection splits only where the children's statistics are known,
    asks for the rest, and reaches the waiting selection once they have come."""
    import time

    from lodscape.lod.select import SelectOptions, select

    h = periodic_fbm(1024, seed=2, relief=500.0)
    path = write_dem(str(tmp_path / "s.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=1.0)  # fmt: skip
    with RasterSource(path) as src:
        grids = SceneOptions(meshes="grid")  # the tree itself, as ``whole``
        scene = Scene(src, grids, tree=LazyTree(src, keep=False))  # type: ignore[arg-type]
        whole = LazyTree(src, keep=False)
        try:
            cam = scene.view.fit(scene.overview_camera(640, 360), None)
            want = select(SelectOptions(), cam, SplitBeforeFinest(whole))  # as the scene's
            tree = scene.tree
            tree.wait = False
            first = select(SelectOptions(), cam, tree)
            assert first.z.max() < want.z.max()  # drawn from what was known
            for _ in range(20):
                sel = select(SelectOptions(), cam, tree)
                if np.array_equal(np.sort(sel.keys), np.sort(want.keys)):
                    break
                time.sleep(0.2)
            np.testing.assert_array_equal(np.sort(sel.keys), np.sort(want.keys))
        finally:
            whole.close()
            scene.close()


def test_the_sidecar_is_reused_and_dropped_when_the_file_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    cache = tmp_path / "cache"
    monkeypatch.setenv("LODSCAPE_CACHE", str(cache))
    folder = tmp_path / "data"
    folder.mkdir()
    h = periodic_fbm(1024, seed=6, relief=400.0)
    path = write_dem(str(folder / "dem.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=1.0)  # fmt: skip

    def view(expect_found: bool) -> tuple[int, int, np.ndarray]:
        with RasterSource(path) as src:
            tree = LazyTree(src)
            scene = Scene(src, tree=tree)  # type: ignore[arg-type]
            try:
                sel = scene.select(scene.overview_camera(640, 360))
                if expect_found:
                    assert tree._tails
                    assert tree.made == 0
                return tree.made, tree.found, np.sort(sel.keys)
            finally:
                scene.close()
                tree.close()

    made, found, first = view(False)
    assert made > 0
    assert found == 0
    assert sorted(os.listdir(folder)) == ["dem.tif"]  # nothing beside the user's file
    assert list((cache / "trees").glob("*.sqlite"))
    # a second open makes nothing: every chunk and the tails come from the sidecar
    made2, found2, second = view(True)
    assert (made2, found2) == (0, made)
    np.testing.assert_array_equal(first, second)
    # the file changes: what was kept is dropped, the statistics made again from the new data
    write_dem(path, h[::-1].copy() * 1.5, crs="EPSG:32617", west=500000.0, north=4000000.0,
              res=1.0)  # fmt: skip
    st = os.stat(path)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    made3, found3, _ = view(False)
    assert made3 > 0
    assert found3 == 0
    assert len(list((cache / "trees").glob("*.sqlite"))) == 1  # the same sidecar, renewed


def test_a_chunk_keeps_its_tiles_grid_error_block_by_block(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each tile's finest grid's own error block by block (``LazyTree.grid_blocks``: what a
    ladder's cut spends its charge against) is what its chunk measured: the largest is the
    tile's recorded error, a chunk root's blocks are its descendants' errors two levels down,
    a chunk not in memory gives none (nothing is made for them), and the sidecar keeps them."""
    monkeypatch.setenv("LODSCAPE_CACHE", str(tmp_path / "cache"))
    h = periodic_fbm(1024, seed=8, relief=500.0)
    path = write_dem(str(tmp_path / "dem.tif"), h, crs="EPSG:32617", west=500000.0,
                     north=4000000.0, res=1.0)  # fmt: skip
    with RasterSource(path) as src:
        tree = LazyTree(src)
        kept: dict[tuple[int, int, int], np.ndarray] = {}
        try:
            b = 1 << (len(tree.grids) - 1)
            x, y = tree.roots()
            deep = tree.zmin + 3
            assert deep < tree.zmax
            made = tree.made
            assert tree.grid_blocks(deep, int(x[0]) << 3, int(y[0]) << 3) is None
            assert tree.made == made  # nothing made for it
            for z in range(tree.zmin, deep + 2):
                n = 1 << (z - tree.zmin)
                dy, dx = np.divmod(np.arange(n * n), n)
                xs = ((x[:, None] * n) + dx).ravel()
                ys = ((y[:, None] * n) + dy).ravel()
                st = tree.level(z).stats(xs, ys)
                for i in np.flatnonzero(st.exists):
                    got = tree.grid_blocks(z, int(xs[i]), int(ys[i]))
                    assert got is not None
                    assert got.shape == (b, b)
                    assert float(got.max()) == pytest.approx(float(st.error[-1, i]), abs=1e-4)
                    kept[(z, int(xs[i]), int(ys[i]))] = got.copy()
            # a chunk root's blocks: its descendants' own 16-segment errors
            z, tx, ty = tree.zmin, int(x[0]), int(y[0])
            dy, dx = np.divmod(np.arange(b * b), b)
            under = tree.level(z + 2).stats((tx << 2) + dx, (ty << 2) + dy)
            got = kept[(z, tx, ty)].ravel()
            np.testing.assert_allclose(got[under.exists], under.error[0][under.exists], atol=1e-5)
        finally:
            tree.close()
        again = LazyTree(src)
        try:
            for (z, tx, ty), want in kept.items():
                again.level(z).stats(np.array([tx]), np.array([ty]))
                np.testing.assert_array_equal(again.grid_blocks(z, tx, ty), want)
            assert again.made == 0  # every chunk from the sidecar
        finally:
            again.close()
