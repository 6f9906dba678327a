"""Fractal detail below a DEM and the procedural planet (paper 003): seams to the bit,
determinism across processes and tile orders, error bounds that hold against the generated
surface, the terrain-adaptive diagonal, no cracks on screen, and the command line."""

from __future__ import annotations

import hashlib
import subprocess
import sys

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, run_cli, sky_share, write_dem
from lodscape import Camera, SceneOptions
from lodscape.geo.tiles import tiles_array
from lodscape.store.provider import FractalProvider
from lodscape.terrain.detail import (
    DetailTree,
    Fractal,
    diagonals,
    interpolate,
    parse_procedural,
)
from lodscape.terrain.fractal import MAX_LEVEL, fbm_window
from lodscape.terrain.mesh import GRIDS

# UTM 17N, 513 samples at 30 m: detail starts two levels under the data's finest tiles
EAST, NORTH = 700000.0, 4060000.0


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("dem") / "utm.tif"
    return write_dem(
        str(path), fbm_heights(513, seed=3), crs="EPSG:32617", west=EAST, north=NORTH, res=30.0
    )


@pytest.fixture(scope="module")
def detail(dem: str) -> FractalProvider:
    scene = lodscape.open(dem, detail=Fractal(0.6, 2.0, 11))
    provider = scene.provider
    assert isinstance(provider, FractalProvider)
    return provider


def _centre_tile(provider: FractalProvider, z: int) -> tuple[int, int]:
    b = provider.bounds_merc
    x, y = tiles_array((b.left + b.right) / 2, (b.top + b.bottom) / 2, z)
    return int(x), int(y)


def test_detail_starts_at_zero_below_its_level() -> None:
    """With a start level, the surface is zero on it and the increments below follow 2H."""
    flat = fbm_window(1, 0.5, 3.0, 9, 0, 0, 33, 33, start=9)
    assert not flat.any()
    w = fbm_window(1, 0.5, 1.0, 17, 40_000, 9_000, 1025, 1025, start=9)
    lags = np.array([1, 2, 4, 8, 16, 32])
    msq = [np.mean((w[:, k:] - w[:, :-k]) ** 2) for k in lags]
    slope = np.polyfit(np.log(lags), np.log(msq), 1)[0]
    assert abs(slope - 1.0) < 0.1, slope


def test_seams_are_bit_equal_and_tiles_repeat(detail: FractalProvider) -> None:
    tree = detail.detail_tree
    z = tree.base.zmax + 2
    x, y = _centre_tile(detail, z)
    heights = detail.heights
    for g in GRIDS:
        a = heights.tile(z, x, y, g)
        right = heights.tile(z, x + 1, y, g)
        below = heights.tile(z, x, y + 1, g)
        assert np.array_equal(a[:, -1], right[:, 0])
        assert np.array_equal(a[-1, :], below[0, :])
        # again, after other tiles, in another order: the same bits
        again = heights.tile(z, x, y, g)
        assert a.tobytes() == again.tobytes()
    coarse = heights.tile(z, x, y, 16)
    fine = heights.tile(z, x, y, 64)
    assert not np.allclose(fine[::4, ::4], coarse)


def test_procedural_seams_and_order() -> None:
    provider = lodscape.open("procedural:seed=5").provider
    assert isinstance(provider, FractalProvider)
    h = provider.heights
    for z, x, y in ((3, 2, 3), (12, 2101, 1500), (18, 140_001, 95_000)):
        n = 1 << z
        a = h.tile(z, x, y, 32)
        right = h.tile(z, (x + 1) % n, y, 32)
        assert np.array_equal(a[:, -1], right[:, 0])
        assert np.array_equal(a[-1, :], h.tile(z, x, y + 1, 32)[0, :])
    # the antimeridian: the last column of tiles meets the first
    assert np.array_equal(h.tile(6, 63, 20, 16)[:, -1], h.tile(6, 0, 20, 16)[:, 0])


_CHILD = """
import hashlib, sys
import lodscape
from lodscape.terrain.detail import Fractal
dem = sys.argv[1]
out = hashlib.sha256()
p = lodscape.open("procedural:seed=9,hurst=0.4").provider
for z, x, y in ((14, 8000, 6000), (9, 300, 200)):
    out.update(p.heights.tile(z, x, y, 64).tobytes())
d = lodscape.open(dem, detail=Fractal(0.6, 2.0, 11)).provider
z = d.detail_tree.base.zmax + 2
b = d.bounds_merc
from lodscape.geo.tiles import tiles_array
x, y = tiles_array((b.left + b.right) / 2, (b.top + b.bottom) / 2, z)
out.update(d.heights.tile(z, int(x), int(y), 32).tobytes())
print(out.hexdigest())
"""


def test_deterministic_across_processes(dem: str) -> None:
    out = hashlib.sha256()
    p = lodscape.open("procedural:seed=9,hurst=0.4").provider
    assert isinstance(p, FractalProvider)
    # the other order here than in the child
    tiles = [p.heights.tile(z, x, y, 64) for z, x, y in ((9, 300, 200), (14, 8000, 6000))]
    for t in reversed(tiles):
        out.update(t.tobytes())
    d = lodscape.open(dem, detail=Fractal(0.6, 2.0, 11)).provider
    assert isinstance(d, FractalProvider)
    z = d.detail_tree.base.zmax + 2
    x, y = _centre_tile(d, z)
    out.update(d.heights.tile(z, x, y, 32).tobytes())
    child = subprocess.run(
        [sys.executable, "-c", _CHILD, dem], capture_output=True, text=True, check=True
    )
    assert child.stdout.strip() == out.hexdigest()


def _measured(heights: object, z: int, x: int, y: int, g: int) -> float:
    """Largest distance between a tile's mesh (its own diagonals) and the surface of a lattice
    up to 4 levels finer, at every point of that lattice."""
    lv = z + int(np.log2(g))
    k = min(4, MAX_LEVEL - lv)
    coarse = heights.tile(z, x, y, g).astype(np.float64)  # type: ignore[attr-defined]
    if k == 0:
        return 0.0
    fine = heights.tile(z, x, y, g << k).astype(np.float64)  # type: ignore[attr-defined]
    f = 1 << k
    fj, fi = np.meshgrid(np.arange(fine.shape[0]) / f, np.arange(fine.shape[1]) / f, indexing="ij")
    mesh = interpolate(coarse, fi, fj, diagonals(coarse))
    return float(np.abs(mesh - fine).max())


def test_error_bounds_hold_below_the_data(detail: FractalProvider) -> None:
    tree = detail.detail_tree
    assert isinstance(tree, DetailTree)
    checked = 0
    assert tree.zmax > tree.base.zmax + 1
    for z in sorted({tree.base.zmax + 1, tree.base.zmax + 2, tree.zmax}):
        cx, cy = _centre_tile(detail, z)
        xs = np.array([cx, cx + 1, cx - 2, cx + 3], dtype=np.int64)
        ys = np.array([cy, cy - 1, cy + 2, cy], dtype=np.int64)
        st = tree.level(z).stats(xs, ys)
        for i in range(xs.size):
            if not st.exists[i]:
                continue
            for kg, g in enumerate(tree.grids):
                real = _measured(detail.heights, z, int(xs[i]), int(ys[i]), g)
                assert real <= st.error[kg, i], (z, g, real, st.error[kg, i])
                checked += 1
    assert checked >= 30
    # the bound is not vacuous: within a small multiple of what is measured
    z = tree.base.zmax + 1
    cx, cy = _centre_tile(detail, z)
    st = tree.level(z).stats(np.array([cx]), np.array([cy]))
    real = _measured(detail.heights, z, cx, cy, 16)
    assert st.error[0, 0] < 12.0 * real


@pytest.mark.parametrize("hurst", [0.3, 0.8])
def test_error_bounds_hold_on_the_procedural_planet(hurst: float) -> None:
    provider = lodscape.open(f"procedural:seed=21,hurst={hurst},sigma=1500").provider
    assert isinstance(provider, FractalProvider)
    tree = provider.detail_tree
    rng = np.random.default_rng(4)
    for z in (5, 9, 13, 17):
        n = 1 << z
        xs = rng.integers(0, n, 3)
        ys = rng.integers(n // 4, 3 * n // 4, 3)
        st = tree.level(z).stats(xs, ys)
        for i in range(3):
            mesh = provider.heights.tile(z, int(xs[i]), int(ys[i]), 16)
            # the bounds hold the tile's own vertices
            assert st.min_h[i] <= mesh.min()
            assert mesh.max() <= st.max_h[i]
            for kg, g in enumerate(tree.grids):
                real = _measured(provider.heights, z, int(xs[i]), int(ys[i]), g)
                assert real <= st.error[kg, i], (z, g, real, st.error[kg, i])


def _valley(angle_deg: float, n: int = 257) -> np.ndarray:
    """A V-shaped valley (slope 0.5) across a gently tilted plane, at any angle."""
    j, i = np.mgrid[0:n, 0:n].astype(np.float64)
    a = np.radians(angle_deg)
    across = (i - n / 2) * np.sin(a) - (j - n / 2) * np.cos(a)
    return 0.5 * np.abs(across) + 0.01 * i


def _rms_errors(fine: np.ndarray, k: int) -> tuple[float, float]:
    f = 1 << k
    coarse = fine[::f, ::f]
    fj, fi = np.meshgrid(np.arange(fine.shape[0]) / f, np.arange(fine.shape[1]) / f, indexing="ij")
    plain = interpolate(coarse, fi, fj) - fine
    adaptive = interpolate(coarse, fi, fj, diagonals(coarse)) - fine
    return float(np.sqrt((plain**2).mean())), float(np.sqrt((adaptive**2).mean()))


def test_adaptive_diagonal_follows_valleys() -> None:
    """Split along the two lowest corners, a cell follows a valley at any angle: never worse
    than the fixed diagonal, much better across it."""
    for angle in range(0, 180, 15):
        plain, adaptive = _rms_errors(_valley(angle + 0.3), 2)
        assert adaptive <= plain * 1.001 + 1e-9, angle
    plain, adaptive = _rms_errors(_valley(135.3), 2)  # a valley from north-east to south-west
    assert adaptive < 0.5 * plain


def test_adaptive_diagonal_reduces_error_on_a_real_dem() -> None:
    from lodscape.data import sample_dem_path
    from lodscape.terrain.source import RasterSource

    with RasterSource(sample_dem_path()) as src:
        b = src.bounds_merc
        xs = np.linspace(b.left, b.right, 1025)[100:869]
        ys = np.linspace(b.top, b.bottom, 1025)[100:869]
        h, _ = src.sample(*np.meshgrid(xs, ys), xs[1] - xs[0])
    for k in (1, 2, 3):
        plain, adaptive = _rms_errors(h.astype(np.float64), k)
        assert adaptive < plain, (k, plain, adaptive)


def test_parse_procedural() -> None:
    f = parse_procedural("procedural:seed=3,hurst=0.5,sigma=100")
    assert (f.seed, f.hurst, f.sigma) == (3, 0.5, 100.0)
    assert parse_procedural("procedural").seed == 0
    for bad in ("procedural:seed=-1", "procedural:seed=1.5", "procedural:hurst=1", "procedural:x"):
        with pytest.raises(ValueError, match="procedural"):
            parse_procedural(bad)


MAGENTA = (1.0, 0.0, 1.0)


def _cracks(rgb: np.ndarray) -> int:
    magenta = np.all(rgb == (255, 0, 255), axis=2)
    seen_above = np.maximum.accumulate(~magenta, axis=0)
    return int((magenta & seen_above).sum())


@pytest.mark.gl
def test_no_cracks_with_fractal_detail(dem: str) -> None:
    with lodscape.open(
        dem, SceneOptions(background=MAGENTA, ellipsoid=False), detail=Fractal(0.5, 3.0, 2)
    ) as s:
        tree = s.tree
        assert isinstance(tree, DetailTree)
        b = s.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        g = s.ground_height(lon, lat) or 0.0
        views = [
            Camera(lon, lat, g + 40.0, heading=30, pitch=-20, width=320, height=180),
            Camera(lon, lat, g + 120.0, heading=200, pitch=-60, width=320, height=180),
            Camera(lon, lat - 0.01, g + 400.0, heading=0, pitch=-25, width=320, height=180),
        ]
        for cam in views:
            rgb, _ = s.render(cam)
            assert s.last is not None
            sel = s.last.selection
            assert _cracks(rgb) == 0, cam
            assert (~np.all(rgb == (255, 0, 255), axis=2)).mean() > 0.3
        # the views reach below the data, with several levels at once
        assert sel["max_depth"] > tree.base.zmax
        assert len({int(z) for z in s.select(s.prepare(views[0])).z}) >= 3


@pytest.mark.gl
def test_cli_detail_and_procedural(
    dem: str, tmp_path: object, capsys: pytest.CaptureFixture[str]
) -> None:
    from pathlib import Path

    import rasterio

    lon, lat = (float(v) for v in _lonlat_centre(dem))
    with rasterio.open(dem) as src:
        top = float(src.read(1).max())
    # low over the highest ground: the DEM's 30 m cells are magnified, detail is added
    view = ["--size", "160x90", "--lon", str(lon), "--lat", str(lat), "--alt", str(top + 150)]
    view += ["--pitch", "-40", "--no-ellipsoid", "-q"]
    pictures = {}
    for name, extra in (
        ("fractal", ["--detail", "fractal", "--sigma", "2", "--seed", "4"]),
        ("none", []),
    ):
        out = Path(str(tmp_path)) / f"{name}.png"
        code, _, err = run_cli(["render", dem, "-o", str(out), *view, *extra], capsys)
        assert code == 0, err
        from PIL import Image

        with Image.open(out) as im:
            pictures[name] = np.asarray(im.convert("RGB")).astype(int)
    # looking down at the DEM: all terrain, and the fractal detail changes its surface
    assert sky_share(Path(str(tmp_path)) / "fractal.png") < 0.05
    changed = np.abs(pictures["fractal"] - pictures["none"]).sum(axis=2) > 10
    assert changed.mean() > 0.01, changed.mean()
    proc = Path(str(tmp_path)) / "p.png"
    code, _, err = run_cli(["demo", "--procedural", "--size", "96x64", "-o", str(proc)], capsys)
    assert code == 0, err
    from PIL import Image

    px = np.asarray(Image.open(proc).convert("RGB")).reshape(-1, 3)
    assert np.unique(px, axis=0).shape[0] > 20
    for argv, msg in (
        (["render", dem, "--sigma", "2", "-o", str(out)], "need --detail fractal"),
        (["render", dem, "--detail", "fractal", "--hurst", "1.2", "-o", str(out)], "Hurst"),
        (["render", dem, "--detail", "wavelet", "-o", str(out)], "none or fractal"),
        (["render", "procedural:seed=a", "-o", str(out)], "seed"),
    ):
        code, _text, err = run_cli(argv, capsys)
        assert code == 2, argv
        assert msg in err, err
        assert len(err.strip().splitlines()) == 1, err


def _lonlat_centre(path: str) -> tuple[float, float]:
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.terrain.source import RasterSource

    with RasterSource(path) as src:
        b = src.bounds_merc
    lon, lat = merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
    return float(lon), float(lat)


def test_fractal_detail_needs_a_raster() -> None:
    from lodscape.errors import SourceError

    with pytest.raises(SourceError, match="raster"):
        lodscape.open(lodscape.open("procedural").provider, detail=Fractal())


@pytest.mark.gl
def test_patch_culling_never_removes_a_pixel(tmp_path: object) -> None:
    """Patches facing away are skipped (normal cones): the picture is the same to the bit, the
    triangles fewer. A ridge seen from one side shows its back slope facing away."""
    from pathlib import Path

    n = 513
    i = np.arange(n, dtype=np.float64)
    ridge = 900.0 - 0.9 * np.abs(i - n / 2)[None, :] * 10.0 / 10.0
    heights = np.repeat(ridge, n, axis=0).astype(np.float32) + 0.02 * i[:, None].astype(np.float32)
    path = write_dem(
        str(Path(str(tmp_path)) / "ridge.tif"),
        heights,
        crs="EPSG:32617",
        west=EAST,
        north=NORTH,
        res=10.0,
    )
    lon, lat = _lonlat_centre(path)
    pictures, tris = [], []
    for cull in (True, False):
        with lodscape.open(
            path, SceneOptions(cull_backfacing=cull, background=MAGENTA, ellipsoid=False)
        ) as s:
            views = [
                # west of the ridge, low, looking east across it
                Camera(lon - 0.025, lat, 820.0, heading=90, pitch=-8, width=320, height=180),
                Camera(
                    lon - 0.01, lat + 0.01, 950.0, heading=120, pitch=-20, width=320, height=180
                ),
            ]
            for cam in views:
                rgb, _ = s.render(cam)
                assert s.last is not None
                pictures.append(rgb)
                tris.append((s.last.triangles, s.last.backfacing))
            # the same view again, after the other (the cones kept for the last frame's
            # meshes are not another frame's), and once more (kept: the same draws)
            for _ in range(2):
                again, _ = s.render(views[0])
                assert s.last is not None
                assert np.array_equal(again, pictures[-2])
                assert (s.last.triangles, s.last.backfacing) == tris[-2]
    for a, b in zip(pictures[:2], pictures[2:], strict=True):
        assert np.array_equal(a, b)
    for (culled_tris, patches), (all_tris, none) in zip(tris[:2], tris[2:], strict=True):
        assert none == 0
        assert patches > 0
        assert culled_tris < all_tris


def test_the_shipped_calibrations_are_what_is_measured() -> None:
    """``lodscape/data/calibration.json`` (``python -m lodscape.terrain.detail``) holds every
    default's calibration, equal to a measurement made now: a change to the lattice that did not
    bump its version, or remake the file, fails here."""
    from lodscape.terrain import detail as d
    from lodscape.terrain.mesh import GRIDS

    shipped = d._shipped_calibrations()
    for h in d.SHIPPED_HURSTS:
        for g in GRIDS:
            assert d._calibration_name(h, g) in shipped, (h, g)
    name = d._calibration_name(d.MOUNTAIN_HURST, 16)
    np.testing.assert_allclose(d._measure(d.MOUNTAIN_HURST, 16), shipped[name], rtol=1e-9)
