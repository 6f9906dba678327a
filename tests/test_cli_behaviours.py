"""Command-line behaviours a user reaches that no other test drives: the demo itself, camera files
and roll, JPEG and TIFF outputs, flights by orbit and by line within a memory budget, imagery from
an MBTiles file, builds on a Dask scheduler named by address, mixed CRSs, the error budget, and
point clouds' grids."""

from __future__ import annotations

import csv
import json
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from _synthetic import fbm_heights, run_cli, sky_share, write_dem

EAST, NORTH = 700000.0, 4060000.0


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    folder = tmp_path_factory.mktemp("behaviours")
    return write_dem(
        str(folder / "dem.tif"), fbm_heights(129, seed=7), crs="EPSG:32617", west=EAST,
        north=NORTH, res=20.0,
    )  # fmt: skip


def _rgb(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(int)


def _centre(dem: str) -> tuple[float, float, float]:
    import rasterio
    from rasterio.warp import transform

    with rasterio.open(dem) as src:
        b = src.bounds
        top = float(src.read(1).max())
        lon, lat = transform(
            src.crs, "EPSG:4326", [(b.left + b.right) / 2], [(b.top + b.bottom) / 2]
        )
    return float(lon[0]), float(lat[0]), top


@pytest.mark.gl
def test_demo_renders_the_sample(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo.png"
    code, text, err = run_cli(["demo", "-o", str(out), "--size", "128x80"], capsys)
    assert code == 0, err
    assert _rgb(out).shape == (80, 128, 3)
    assert sky_share(out) < 0.6  # the sample's terrain fills its overview
    assert "tiles:" in text
    assert f"wrote: {out}" in text.replace("\n", " ").replace("  ", " ") or str(out) in text


@pytest.mark.gl
def test_a_camera_file_roll_and_picture_formats(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lon, lat, top = _centre(dem)
    pose = {"lon": lon, "lat": lat, "alt": top + 400.0, "heading": 30.0, "pitch": -30.0}
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps(pose))
    size = ["--size", "96x64", "-q", "--no-ellipsoid"]
    flags = ["--lon", str(lon), "--lat", str(lat), "--alt", str(top + 400.0)]
    flags += ["--heading", "30", "--pitch", "-30"]
    pictures = {}
    for name, argv in (
        ("file", ["--camera", str(cam)]),
        ("flags", flags),
        ("rolled", [*flags, "--roll", "25"]),
    ):
        out = tmp_path / f"{name}.png"
        code, _, err = run_cli(["render", dem, "-o", str(out), *argv, *size], capsys)
        assert code == 0, (name, err)
        pictures[name] = _rgb(out)
    # the camera file is the same camera as the flags; a roll turns the picture
    assert np.array_equal(pictures["file"], pictures["flags"])
    assert np.abs(pictures["rolled"] - pictures["flags"]).mean() > 5
    for suffix in (".jpg", ".tif"):
        out = tmp_path / f"view{suffix}"
        code, _, err = run_cli(["render", dem, "-o", str(out), *flags, *size], capsys)
        assert code == 0, err
        with Image.open(out) as im:
            assert im.format == {".jpg": "JPEG", ".tif": "TIFF"}[suffix]
        # JPEG is lossy: close to the PNG; TIFF is exact
        tolerance = 12 if suffix == ".jpg" else 0
        assert np.abs(_rgb(out) - pictures["flags"]).mean() <= tolerance
    cam.write_text(json.dumps({"lon": lon, "lat": lat}))
    code, _, err = run_cli(
        ["render", dem, "-o", str(tmp_path / "x.png"), "--camera", str(cam)], capsys
    )
    assert code == 2
    assert "cam.json" in err
    assert "lon, lat and alt" in err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.gl
@pytest.mark.parametrize("route", ["orbit", "line"])
def test_flights_by_orbit_and_line_within_a_budget(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], route: str
) -> None:
    import imageio_ffmpeg

    lon, lat, top = _centre(dem)
    alt = top + 300.0
    path = (
        ["--orbit", f"{lon},{lat},600,{alt}"]
        if route == "orbit"
        else ["--line", f"{lon - 0.005},{lat},{lon + 0.005},{lat},{alt}"]
    )
    video, stats = tmp_path / "f.mp4", tmp_path / "f.csv"
    argv = ["fly", dem, *path, "--duration", "2", "--fps", "12", "--size", "96x64"]
    argv += ["--budget-mb", "2", "-o", str(video), "--stats", str(stats), "-q"]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == frames == 25
    budget = 2 * 2**20
    for r in rows:
        assert int(float(r["gpu_bytes"])) <= budget
        assert int(float(r["memory_bytes"])) <= budget
        assert int(float(r["cache_bytes"])) <= budget
    assert max(int(r["tiles"]) for r in rows) > 0


@pytest.mark.gl
def test_a_flight_drapes_imagery_from_an_mbtiles_file(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A tileset is an MBTiles file of imagery too: fly over the DEM with it as --imagery."""
    lods = tmp_path / "site.lods"
    code, _, err = run_cli(["build", dem, "-o", str(lods), "-q"], capsys)
    assert code == 0, err
    mbtiles = tmp_path / "imagery.mbtiles"
    mbtiles.write_bytes(lods.read_bytes())
    lon, lat, top = _centre(dem)
    stats = tmp_path / "f.csv"
    argv = ["fly", dem, "--orbit", f"{lon},{lat},600,{top + 300.0}", "--duration", "1"]
    argv += ["--fps", "12", "--size", "96x64", "--imagery", str(mbtiles)]
    argv += ["-o", str(tmp_path / "f.mp4"), "--stats", str(stats), "-q"]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert all(int(float(r["imagery_failed"])) == 0 for r in rows)
    assert int(float(rows[-1]["http_requests"])) == 0


def test_a_build_on_a_dask_scheduler_named_by_address(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from distributed import LocalCluster

    from lodscape.store.tileset import TilesetProvider

    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        out = tmp_path / "dask.lods"
        code, text, err = run_cli(
            ["build", dem, "-o", str(out), "--scheduler", cluster.scheduler_address], capsys
        )
        assert code == 0, err
        assert cluster.scheduler_address in text
    local = tmp_path / "local.lods"
    code, _, err = run_cli(["build", dem, "-o", str(local), "-q"], capsys)
    assert code == 0, err
    with closing(TilesetProvider(out)) as a, closing(TilesetProvider(local)) as b:
        assert a.tree.zmax == b.tree.zmax
        assert [lv.exists.sum() for lv in a.tree.levels] == [
            lv.exists.sum() for lv in b.tree.levels
        ]


def test_mixed_crs_only_when_allowed(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lon, lat, _ = _centre(dem)
    other = write_dem(
        str(tmp_path / "ll.tif"), fbm_heights(65, seed=2), crs="EPSG:4326", west=lon + 0.005,
        north=lat, res=0.0002,
    )  # fmt: skip
    out = tmp_path / "mixed.lods"
    code, _, err = run_cli(["build", dem, other, "-o", str(out), "-q"], capsys)
    assert code == 2
    assert "--allow-mixed-crs" in err or "differs" in err
    assert not out.exists()
    code, _, err = run_cli(["build", dem, other, "-o", str(out), "-q", "--allow-mixed-crs"], capsys)
    assert code == 0, err
    code, text, err = run_cli(["info", str(out)], capsys)
    assert code == 0, err
    assert "dem.tif" in text
    assert "ll.tif" in text


def test_a_mosaic_of_rasters_far_apart_builds_whole(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two rasters an ocean apart, in their own CRSs: the tileset opens, every level from its
    coarsest has tiles over each, and no warning is printed about points the other's CRS
    cannot hold (a 513² sample of their joint box, or its centre, meets neither of them)."""
    import warnings

    from lodscape.geo.tiles import tile
    from lodscape.store.tileset import TilesetProvider

    other = write_dem(
        str(tmp_path / "europe.tif"), fbm_heights(65, seed=3), crs="EPSG:32633", west=500000.0,
        north=5000000.0, res=20.0,
    )  # fmt: skip
    out = tmp_path / "apart.lods"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        code, _, err = run_cli(
            ["build", dem, other, "-o", str(out), "-q", "--allow-mixed-crs"], capsys
        )
    assert code == 0, err
    assert "Warning" not in err
    places = [_centre(dem)[:2], _centre(other)[:2]]
    # the tiles tested for data while planning are each raster's, not the ocean's between them
    import lodscape.build.blocks as blocks
    from lodscape.build import BuildOptions, _prepare
    from lodscape.terrain.pyramid import level_range

    tested = []

    def counted(source, z, x, y):  # type: ignore[no-untyped-def]
        tested.append(x.size)
        return touching(source, z, x, y)

    touching = blocks.touching
    *_, span, _, source = _prepare(
        [dem, other], tmp_path / "plan.lods", BuildOptions(allow_mixed_crs=True)
    )
    with closing(source), pytest.MonkeyPatch.context() as mp:
        mp.setattr(blocks, "touching", counted)
        assert len(blocks.footprints(source)) == 2
        for band in blocks.bands(span.zmax, span.zmin):
            tested.clear()
            planned = sum(len(row) for row in blocks.plan_blocks(source, band))
            own = sum(
                r[2] * r[3] for r in (level_range(b, band.root) for b in blocks.footprints(source))
            )
            assert 2 <= planned <= sum(tested) <= own, (band, planned, sum(tested), own)
    with closing(TilesetProvider(out)) as t:
        tree = t.tree
        assert tree.zmin <= 3  # their joint box spans an ocean
        for z in range(tree.zmin, tree.zmax + 1):
            st = tree.level(z)
            for lon, lat in places:
                t_ = tile(lon, lat, z)
                got = st.stats(np.array([t_.x], np.int64), np.array([t_.y], np.int64))
                assert bool(got.exists[0]), (z, lon, lat)


def test_the_error_budget_trades_triangles_for_error(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3

    sizes = {}
    for texels in ("0.5", "4"):
        out = tmp_path / f"e{texels}.lods"
        code, _, err = run_cli(
            ["build", dem, "-o", str(out), "-q", "--error-texels", texels], capsys
        )
        assert code == 0, err
        code, text, err = run_cli(["info", str(out)], capsys)
        assert f"error {float(texels):.1f} texel" in text, text
        with closing(sqlite3.connect(out)) as db:
            sizes[texels] = db.execute(
                "SELECT SUM(LENGTH(data)), MAX(error) FROM terrain"
            ).fetchone()
    # a looser budget: smaller meshes, larger recorded errors
    assert sizes["4"][0] < sizes["0.5"][0]
    assert sizes["4"][1] > sizes["0.5"][1]


def test_points_get_a_grid_of_their_own_spacing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --resolution the grid takes the points' median spacing, and is kept beside the
    tileset as OUTPUT.points.tif."""
    import rasterio

    rng = np.random.default_rng(3)
    side = np.arange(0.0, 800.0, 8.0)  # a survey every 8 m, jittered
    x, y = (a.ravel() for a in np.meshgrid(EAST + side, NORTH - side))
    x = x + rng.uniform(-0.5, 0.5, x.size)
    y = y + rng.uniform(-0.5, 0.5, y.size)
    z = 300.0 + 0.05 * (x - EAST) + 0.02 * (NORTH - y)
    pts = tmp_path / "survey.csv"
    with pts.open("w") as f:
        f.write("x,y,z\n")
        f.writelines(f"{a:.2f},{b:.2f},{c:.2f}\n" for a, b, c in zip(x, y, z, strict=True))
    out = tmp_path / "survey.lods"
    code, _, err = run_cli(["build", str(pts), "-o", str(out), "--crs", "EPSG:32617", "-q"], capsys)
    assert code == 0, err
    grid = tmp_path / "survey.lods.points.tif"
    with rasterio.open(grid) as src:
        assert src.crs.to_epsg() == 32617
        assert src.res[0] == pytest.approx(8.0, rel=0.15)
        heights = src.read(1, masked=True)
    assert float(heights.min()) == pytest.approx(z.min(), abs=1.0)
    assert float(heights.max()) == pytest.approx(z.max(), abs=1.0)
