"""Tileset builds: honest errors, crack-free rendering, resumable writes, the same tiles from
every executor, and clear failures on bad input (real GeoTIFFs, real SQLite, real processes)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem
from lodscape import Camera, SceneOptions
from lodscape.build import BuildOptions, build
from lodscape.build.executors import DaskExecutor, PoolExecutor
from lodscape.errors import LodscapeError
from lodscape.geo.tiles import Tile, bounds
from lodscape.store.quantized_mesh import decode
from lodscape.store.tileset import TilesetError, TilesetProvider

MAGENTA = (1.0, 0.0, 1.0)
EAST, NORTH = 700000.0, 4060000.0


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("build") / "utm.tif"
    return write_dem(
        str(path), fbm_heights(257, seed=5), crs="EPSG:32617", west=EAST, north=NORTH, res=10.0
    )


@pytest.fixture(scope="module", params=["rtin", "greedy"])
def tileset(dem: str, tmp_path_factory: pytest.TempPathFactory, request: Any) -> Path:
    """The DEM built by each mesher: what holds of one tileset holds of both."""
    out = tmp_path_factory.mktemp("lods") / f"site-{request.param}.lods"
    build([dem], out, BuildOptions(mesher=request.param), executor=PoolExecutor(2, processes=False))
    return out


def _tiles(path: Path) -> dict[tuple[int, int, int], tuple[bytes, float]]:
    with closing(sqlite3.connect(path)) as db:
        terrain = {
            (z, x, y): (bytes(d), e)
            for z, x, y, e, d in db.execute("SELECT z, x, y, error, data FROM terrain")
        }
        imagery = {
            (z, x, r): bytes(d)
            for z, x, r, d in db.execute(
                "SELECT zoom_level, tile_column, tile_row, tile_data FROM tiles"
            )
        }
    return {**terrain, **{("img", *k): (v, 0.0) for k, v in imagery.items()}}  # type: ignore[dict-item]


def _mesh_at(qm: object, rect: tuple[float, ...], lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """The decoded mesh's height at points (NaN outside it), triangle by triangle in numpy."""
    plon, plat, h = qm.positions(*rect)  # type: ignore[attr-defined]
    out = np.full(lon.shape, np.nan)
    for a, b, c in qm.triangles.astype(np.int64):  # type: ignore[attr-defined]
        det = (plat[b] - plat[c]) * (plon[a] - plon[c]) + (plon[c] - plon[b]) * (plat[a] - plat[c])
        wa = ((plat[b] - plat[c]) * (lon - plon[c]) + (plon[c] - plon[b]) * (lat - plat[c])) / det
        wb = ((plat[c] - plat[a]) * (lon - plon[c]) + (plon[a] - plon[c]) * (lat - plat[c])) / det
        wc = 1 - wa - wb
        inside = (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9)
        out[inside] = (wa * h[a] + wb * h[b] + wc * h[c])[inside]
    return out


def test_every_tiles_real_error_is_within_its_recorded_error(dem: str, tileset: Path) -> None:
    """The recorded error of every tile bounds the decoded mesh's distance to every sample of
    the DEM it covers (read here straight from the file, projected here with pyproj)."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(dem) as ds:
        values = ds.read(1).astype(np.float64)
        rows, cols = np.mgrid[0 : ds.height, 0 : ds.width]
        a = ds.transform
        c, r = cols.ravel() + 0.5, rows.ravel() + 0.5
        xs, ys = a.a * c + a.b * r + a.c, a.d * c + a.e * r + a.f
        to_ll = Transformer.from_crs(ds.crs, "EPSG:4326", always_xy=True)
        # ground metres from each sample to the raster's edge
        edge = np.minimum(np.minimum(c, ds.width - c), np.minimum(r, ds.height - r)) * a.a
    lon, lat = (np.asarray(v) for v in to_ll.transform(xs, ys))
    h = values.ravel()
    with closing(sqlite3.connect(tileset)) as db:
        rows = db.execute("SELECT z, x, y, error, data FROM terrain").fetchall()
    # up to twelve tiles of every level, chosen at random
    rng = np.random.default_rng(4)
    tiles = []
    for level in sorted({r[0] for r in rows}):
        at = [r for r in rows if r[0] == level]
        tiles += [at[i] for i in rng.permutation(len(at))[:12]]
    for z, x, y, error, data in tiles:
        b = bounds(Tile(x, y, z))
        inside = (lon >= b.left) & (lon <= b.right) & (lat >= b.bottom) & (lat <= b.top)
        # the data ends at the last grid cell whose corners all have data: beyond it the mesh
        # drops to the ellipsoid, and samples there are not the tile's to match (one grid cell
        # of the tile's level, and a pixel, from the raster's edge)
        cell = (b.right - b.left) * 111319.49 * np.cos(np.radians(b.bottom)) / 64
        inside &= edge > cell + 10.0
        if not inside.any():
            continue  # a tile of the ellipsoid beside the data, at one of its corners
        mesh = _mesh_at(
            decode(bytes(data)), (b.left, b.bottom, b.right, b.top), lon[inside], lat[inside]
        )
        real = np.abs(mesh - h[inside])
        assert np.isfinite(real).all()
        assert real.max() <= error + 1e-3, (z, x, y, real.max(), error)
    assert len(tiles) > 10


def test_a_tilesets_heights_are_its_meshes(dem: str, tileset: Path) -> None:
    # many points at once (a city's footprints, a globe's facets): each tile decoded once,
    # the finest mesh's height, within its recorded error of the DEM
    from lodscape.geo.tiles import merc_to_lonlat

    provider = TilesetProvider(tileset)
    try:
        b = provider.bounds_merc
        rng = np.random.default_rng(0)
        xm, ym = rng.uniform(b.left, b.right, 3000), rng.uniform(b.bottom, b.top, 3000)
        lon, lat = merc_to_lonlat(xm, ym)
        got = provider.heights(lon, lat)
        with lodscape.open(dem) as source:
            want = source.heights(lon, lat)
            # the data is what lies between its pixel centres: the meshes end (and the wall
            # down to the ellipsoid begins) at the last grid vertex with data, so points
            # within two pixels of the data's edge are left out of the comparison
            d = 2.0 * 10.0 / np.cos(np.radians(36.6))
            for dx, dy in ((d, 0.0), (-d, 0.0), (0.0, d), (0.0, -d)):
                near = source.heights(*merc_to_lonlat(xm + dx, ym + dy))
                want = np.where(np.isfinite(near), want, np.nan)
        both = np.isfinite(got) & np.isfinite(want)
        assert both.mean() > 0.5
        errors = {k: e for k, (_, e) in _tiles(tileset).items() if k[0] != "img"}
        zmax = max(k[0] for k in errors)
        error = max(e for k, e in errors.items() if k[0] == zmax)
        assert np.abs(got - want)[both].max() <= error
        one = [
            provider.ground_height(float(a), float(c))
            for a, c in zip(lon[:40], lat[:40], strict=True)
        ]
        assert np.allclose([np.nan if v is None else v for v in one], got[:40], equal_nan=True)
        assert np.isnan(provider.heights(np.array([0.0, 120.0]), np.array([0.0, -40.0]))).all()
        assert got.shape == lon.shape
        assert provider.heights(lon.reshape(60, 50), lat.reshape(60, 50)).shape == (60, 50)
        kept = sum(sum(a.nbytes for a in m) for m in provider._meshes.values() if m is not None)
        assert kept == provider._meshes.nbytes <= provider.DECODED_BYTES
    finally:
        provider.close()


@pytest.mark.gl
def test_the_globe_takes_a_tilesets_heights(tileset: Path) -> None:
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.globe import Globe, GlobeOptions

    with lodscape.open(tileset) as scene:
        b = scene.provider.bounds_merc
        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        g = scene.ground_height(lon, lat)
        assert g is not None
    cam = Camera(lon, lat - 0.01, g + 1500.0, pitch=-50, width=240, height=160)
    depths = []
    for terrain in (lodscape.open(tileset), None):
        earth = Globe(terrain, GlobeOptions())
        try:
            depths.append(earth.render(cam)[1])
            # no facet finer than the data's cells (10 m: level 20 at most)
            assert earth.last["max_level"] <= 20
        finally:
            earth.close()
    both = np.isfinite(depths[0]) & np.isfinite(depths[1])
    assert both.mean() > 0.5
    # the ground the DEM lifts: hundreds of metres nearer than the ellipsoid
    assert (np.abs(depths[0] - depths[1])[both] > 100.0).mean() > 0.3


@pytest.mark.gl
def test_a_tileset_renders_without_cracks_within_the_bounds(tmp_path: Path) -> None:
    dem = write_dem(
        str(tmp_path / "5km.tif"),
        fbm_heights(513, seed=3),
        crs="EPSG:32617",
        west=EAST,
        north=NORTH,
        res=10.0,
    )
    out = tmp_path / "5km.lods"
    # cracks inside the data: holes where there is none (the walls down to the ellipsoid of
    # the default fill step with the level at the data's rim, see the tileset fill test)
    build([dem], out, BuildOptions(fill="none"))
    with lodscape.open(out, SceneOptions(background=MAGENTA, ellipsoid=False)) as scene:
        lo, hi = scene.tree.height_range
        b = scene.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        g = scene.ground_height(lon, lat)
        assert g is not None
        assert lo <= g <= hi
        views = [
            Camera(lon, lat - 0.01, hi + 500, heading=5, pitch=-45, width=480, height=270),
            Camera(
                lon - 0.006, lat - 0.006, hi + 150, heading=45, pitch=-30, width=480, height=270
            ),
            Camera(lon, lat, g + 800, pitch=-90, width=320, height=320),
        ]
        levels = set()
        for cam in views:
            rgb, _ = scene.render(cam)
            magenta = np.all(rgb == (255, 0, 255), axis=2)
            below = np.maximum.accumulate(~magenta, axis=0)
            assert int((magenta & below).sum()) == 0
            assert (~magenta).mean() > 0.5
            sel = scene.select(cam)
            # within the bound except at the finest level, where the error is what resampling
            # the DEM's own samples onto the Web Mercator grid leaves, and no finer tile exists
            assert np.all(sel.sse[sel.z < scene.tree.zmax] <= 2.0)
            levels |= set(sel.z.tolist())
            assert scene.last is not None
            assert scene.last.triangles > 0
        assert len(levels) >= 3


def test_processes_and_dask_make_the_same_tiles_as_threads(
    dem: str, tileset: Path, tmp_path: Path
) -> None:
    want = _tiles(tileset)
    options = BuildOptions(mesher=tileset.stem.removeprefix("site-"))  # the fixture's mesher
    procs = tmp_path / "procs.lods"
    executor = PoolExecutor(2, processes=True)
    try:
        build([dem], procs, options, executor=executor)
    finally:
        executor.close()
    assert _tiles(procs) == want
    dask = tmp_path / "dask.lods"
    executor = DaskExecutor(None, workers=2)
    try:
        report = build([dem], dask, options, executor=executor)
    finally:
        executor.close()
    assert "dask" in report.executor
    assert _tiles(dask) == want


def test_a_dask_build_starts_beside_another_dashboard() -> None:
    """Port 8787 taken (a user's Jupyter or Dask dashboard): the local cluster starts anyway,
    with no warning (the suite turns warnings into errors)."""
    import socket

    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", 8787))
            sock.listen()
        except OSError:
            pass  # taken already: the case itself
        executor = DaskExecutor(None, workers=1)
        try:
            assert list(executor.imap(abs, [(-2,), (3,)])) in ([2, 3], [3, 2])
        finally:
            executor.close()


def test_points_are_triangulated_and_built(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    x = rng.uniform(EAST, EAST + 2000, 1500)
    y = rng.uniform(NORTH - 2000, NORTH, 1500)
    z = 400 + 0.05 * (x - EAST) + 30 * np.sin((y - NORTH) / 300)
    csv = tmp_path / "survey.csv"
    csv.write_text(
        "id,x,y,z\n"
        + "".join(f"{i},{a},{b},{c}\n" for i, (a, b, c) in enumerate(zip(x, y, z, strict=True)))
    )
    out = tmp_path / "survey.lods"
    build([csv], out, BuildOptions(crs="EPSG:32617", resolution=10.0))
    with lodscape.open(out) as scene:
        lo, hi = scene.tree.height_range
        assert z.min() - 1 <= lo < hi <= z.max() + 1
    xyz = tmp_path / "survey.xyz"
    xyz.write_text("".join(f"{a} {b} {c}\n" for a, b, c in zip(x, y, z, strict=True)))
    build([xyz], tmp_path / "xyz.lods", BuildOptions(crs="EPSG:32617", resolution=10.0))
    # the same points as XYZ make the same terrain as the CSV
    with lodscape.open(out) as a, lodscape.open(tmp_path / "xyz.lods") as b:
        assert b.tree.height_range == pytest.approx(a.tree.height_range)
        assert b.provider.bounds_merc == pytest.approx(a.provider.bounds_merc)
        assert b.tree.zmax == a.tree.zmax


def _corrupt(tmp_path: Path, dem: str) -> Path:
    data = Path(dem).read_bytes()
    bad = tmp_path / "cut.tif"
    bad.write_bytes(data[: len(data) // 3])
    return bad


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("truncated raster", "cut.tif"),
        ("bad csv row", "row 3"),
        ("two points", "at least three"),
        ("collinear", "one line"),
        ("no crs for points", "--crs"),
        ("mixed crs", "differs"),
        ("output folder missing", "does not exist"),
    ],
)
def test_bad_inputs_fail_clearly_and_leave_nothing(
    case: str, message: str, dem: str, tmp_path: Path
) -> None:
    out = tmp_path / "out.lods"
    opts = BuildOptions(crs="EPSG:32617")
    inputs: list[str | Path]
    if case == "truncated raster":
        inputs = [_corrupt(tmp_path, dem)]
    elif case == "bad csv row":
        (tmp_path / "p.csv").write_text("x,y,z\n1,2,3\n4,five,6\n7,8,9\n")
        inputs = [tmp_path / "p.csv"]
    elif case == "two points":
        (tmp_path / "p.xyz").write_text("1 2 3\n4 5 6\n")
        inputs = [tmp_path / "p.xyz"]
    elif case == "collinear":
        (tmp_path / "p.xyz").write_text("".join(f"{i} {2 * i} {i}\n" for i in range(10)))
        inputs = [tmp_path / "p.xyz"]
    elif case == "no crs for points":
        (tmp_path / "p.xyz").write_text("1 2 3\n4 5 6\n7 9 8\n")
        inputs = [tmp_path / "p.xyz"]
        opts = BuildOptions()
    elif case == "mixed crs":
        other = write_dem(
            str(tmp_path / "ll.tif"),
            fbm_heights(33),
            crs="EPSG:4326",
            west=-78.7,
            north=36.66,
            res=0.0002,
        )
        inputs = [dem, other]
    else:
        inputs = [dem]
        out = tmp_path / "no" / "such" / "out.lods"
    with pytest.raises(LodscapeError, match=message) as info:
        build(inputs, out, opts, executor=PoolExecutor(1, processes=False))
    assert "\n" not in str(info.value)
    assert not out.exists()
    assert not Path(str(out) + "-wal").exists()


def _build_on_a_full_disk(dem: str, out: Path, limit: int) -> subprocess.CompletedProcess[str]:
    """``lodscape build`` in a process that may write files of at most ``limit`` bytes (the
    write limit, RLIMIT_FSIZE, stands in for a full disk)."""
    code = (
        "import resource, signal, sys; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
        f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit})); "
        "from lodscape.cli import main; "
        f"main(['build', {dem!r}, '-o', {str(out)!r}, '-q', '--workers', '1'])"
    )
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)


def test_a_full_disk_fails_in_one_line_and_resumes(dem: str, tmp_path: Path) -> None:
    """A full disk mid-build: the build stops with one line and exit status 2, keeps what it
    committed, and finishes when run again."""
    out = tmp_path / "full.lods"
    proc = _build_on_a_full_disk(dem, out, 400_000)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().count("\n") == 0
    assert "full" in proc.stderr or "cannot write" in proc.stderr
    with pytest.raises(TilesetError):
        TilesetProvider(out)
    report = build([dem], out)
    assert report.resumed
    with lodscape.open(out) as scene:
        assert scene.tree.zmax > scene.tree.zmin
    os.unlink(out)


def test_a_full_disk_at_the_first_write_leaves_no_file(dem: str, tmp_path: Path) -> None:
    """The disk full before the tileset's first page: one line that says so, and no empty SQLite
    file that readers would then call "not a lodscape tileset"."""
    proc = _build_on_a_full_disk(dem, tmp_path / "full.lods", 2_000)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().count("\n") == 0, proc.stderr
    # a real full disk reads "the disk is full"; the size limit standing in for it, an I/O error
    assert "disk is full" in proc.stderr or "is the disk full" in proc.stderr, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_build_being_written_says_so(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """While a build runs, readers say it is being written (not that it stopped), and a second
    build of the same file is refused; once it has ended, killed or not, the lock is gone."""
    out = tmp_path / "site.lods"
    seen: list[tuple[int, str]] = []

    def progress(done: int, total: int) -> None:
        if not seen and done > 0:
            code, _, err = run_cli(["info", str(out)], capsys)
            seen.append((code, err))
            with pytest.raises(TilesetError, match="another lodscape build is writing it"):
                build([dem], out, executor=PoolExecutor(1, processes=False))

    build([dem], out, executor=PoolExecutor(1, processes=False), progress=progress)
    code, err = seen[0]
    assert code == 2
    assert "a build is writing it now" in err, err
    assert "stopped" not in err
    code, _, err = run_cli(["info", str(out)], capsys)
    assert code == 0, err


def test_a_laz_cloud_brings_its_own_crs_and_its_ground_class(tmp_path: Path) -> None:
    laspy = pytest.importorskip("laspy")
    from pyproj import CRS

    rng = np.random.default_rng(9)
    n = 4000
    x = rng.uniform(EAST, EAST + 1500, n)
    y = rng.uniform(NORTH - 1500, NORTH, n)
    z = 300 + 0.02 * (x - EAST)
    ground = rng.random(n) < 0.7
    z_all = np.where(ground, z, z + 25.0)  # trees and roofs above the ground
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([EAST, NORTH, 0.0])
    header.add_crs(CRS.from_epsg(32617))
    las = laspy.LasData(header)
    las.x, las.y, las.z = x, y, z_all
    las.classification = np.where(ground, 2, 5).astype(np.uint8)
    path = tmp_path / "cloud.laz"
    las.write(path)
    out = tmp_path / "cloud.lods"
    build([path], out, BuildOptions(resolution=10.0))  # no --crs: the file names it
    with lodscape.open(out) as scene:
        lo, hi = scene.tree.height_range
    # only the ground: nothing of the 25 m above it
    assert z.min() - 1 <= lo < hi <= z.max() + 1
    with pytest.raises(LodscapeError, match="differs"):
        build([path], tmp_path / "other.lods", BuildOptions(crs="EPSG:4326"))
