"""The tileset from the command line: build, info, render, export; and what outside readers
(GDAL's MBTiles driver, a Cesium-style layer.json consumer) see in it."""

from __future__ import annotations

import json
import shutil
import sqlite3
from contextlib import closing
from pathlib import Path

import pytest

from _synthetic import fbm_heights, run_cli, sky_share, write_dem
from lodscape.cli import main
from lodscape.store.geographic import available_tiles
from lodscape.store.manifest import connect_readonly
from lodscape.store.quantized_mesh import decode

pytestmark = pytest.mark.gl


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("cli-build")
    dem = write_dem(
        str(folder / "dem.tif"),
        fbm_heights(257, seed=2),
        crs="EPSG:4326",
        west=7.0,
        north=46.5,
        res=0.0002,
    )
    out = folder / "site.lods"
    main(["build", dem, "-o", str(out), "-q"])  # returns on success, exits 2 on failure
    assert out.exists()
    return out


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    return run_cli(argv, capsys)


def test_info_render_and_export(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, err = _run(["info", str(built)], capsys)
    assert code == 0, err
    assert "quantized-mesh-1.0" in out
    assert "dem.tif" in out
    assert "levels" in out
    view = tmp_path / "view.png"
    argv = ["render", str(built), "--size", "200x120", "-o", str(view), "--no-ellipsoid"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    assert 0.0 < sky_share(view) < 0.6  # the tileset's terrain fills most of its overview
    assert "tiles:" in out
    folder = tmp_path / "cesium"
    code, out, err = _run(["export", str(built), "--cesium", str(folder)], capsys)
    assert code == 0, err
    with closing(sqlite3.connect(built)) as db:
        (terrain,) = db.execute("SELECT COUNT(*) FROM terrain").fetchone()
        (imagery,) = db.execute("SELECT COUNT(*) FROM tiles").fetchone()
    mercator = tmp_path / "mercator"
    argv = ["export", str(built), "--cesium", str(mercator), "--tiling", "mercator"]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    for where, projection in ((folder, "EPSG:4326"), (mercator, "EPSG:3857")):
        layer = json.loads((where / "layer.json").read_text())
        assert layer["format"] == "quantized-mesh-1.0"
        assert layer["projection"] == projection
        assert layer["scheme"] == "tms"
        # every level from 0 is there, and every available tile is a file that decodes
        assert len(layer["available"]) == layer["maxzoom"] + 1
        files = 0
        for z, ranges in enumerate(layer["available"]):
            for r in ranges:
                for x in range(r["startX"], r["endX"] + 1):
                    for y in range(r["startY"], r["endY"] + 1):
                        qm = decode((where / str(z) / str(x) / f"{y}.terrain").read_bytes())
                        assert qm.vertex_count >= 4
                        files += 1
        assert files == len(list(where.rglob("*.terrain")))
        # the stored tiles and the fillers above them; geographic ones from each level's
        assert files >= terrain if projection == "EPSG:3857" else files >= terrain // 2
    # every stored tile, and the overviews above them (levels from 0)
    pngs = list((folder / "imagery").rglob("*.png"))
    assert len(pngs) > imagery
    assert {p.parent.parent.name for p in pngs} >= {"0", "1"}
    # the imagery's TileJSON: its levels are the stored ones, its tiles the exported files
    tj = json.loads((folder / "imagery.json").read_text())
    with closing(sqlite3.connect(built)) as db:
        lo, hi = db.execute("SELECT MIN(zoom_level), MAX(zoom_level) FROM tiles").fetchone()
    # from level 0: the levels above the stored ones are overviews made from them
    assert (tj["tilejson"], tj["minzoom"], tj["maxzoom"]) == ("3.0.0", 0, hi)
    assert lo > 0
    w, s, e, n = tj["bounds"]
    assert w < e
    assert s < n
    z, x, y = hi, *_any_tile(folder / "imagery" / str(hi))
    assert (folder / tj["tiles"][0].format(z=z, x=x, y=y)).exists()
    # a tileset without a city has no 3D Tiles to export
    assert not (folder / "3dtiles").exists()
    code, _, err = _run(["export", str(built), "--cesium", str(folder)], capsys)
    assert code == 2
    assert "not an empty folder" in err


def test_gdal_reads_the_imagery_as_mbtiles(built: Path, tmp_path: Path) -> None:
    """GDAL's MBTiles driver (inside rasterio's wheel) wants the .mbtiles ending; given that, it
    reads the tileset's imagery as a raster, covering the data with opaque pixels."""
    import rasterio

    copy = tmp_path / "site.mbtiles"
    shutil.copy(built, copy)
    with rasterio.open(copy) as ds:
        assert ds.driver == "MBTiles"
        assert ds.count == 4
        alpha = ds.read(4)
    assert alpha.max() == 255
    assert 0.3 < (alpha == 255).mean() <= 1.0


def test_a_tileset_that_is_not_one_fails_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "other.lods"
    with closing(sqlite3.connect(other)) as db:
        db.execute("CREATE TABLE t (a)")
        db.commit()
    code, _, err = _run(["render", str(other), "-o", str(tmp_path / "x.png")], capsys)
    assert code == 2
    assert "not a lodscape tileset" in err
    assert err.count("\n") == 1
    assert not (tmp_path / "x.png").exists()


def _any_tile(level: Path) -> tuple[int, int]:
    """(x, y) of some exported imagery file of a level folder."""
    f = next(level.rglob("*.png"))
    return int(f.parent.name), int(f.stem)


def test_heights_in_a_tile_are_its_triangles(built: Path) -> None:
    """The grid of cells finds, for every point, the triangle the brute force finds (points on
    a grid, at vertices, on edges and outside the tile included), and its height there."""
    import numpy as np

    from lodscape.store.tileset import TilesetProvider, _heights_in

    tp = TilesetProvider(built)
    try:
        z = tp.tree.zmax
        ys, xs = np.nonzero(tp.tree.level(z).exists)
        lv = tp.tree.level(z)
        mesh = tp._decoded(z, int(xs[0] + lv.x0), int(ys[0] + lv.y0))
    finally:
        tp.close()
    assert mesh is not None
    plon, plat, h, tri = mesh
    rng = np.random.default_rng(5)
    g = np.linspace(plon.min(), plon.max(), 40)
    gy = np.linspace(plat.min(), plat.max(), 40)
    gx, gy = np.meshgrid(g, gy)
    lon = np.concatenate([gx.ravel(), plon, rng.uniform(plon.min() - 0.01, plon.max(), 500)])
    lat = np.concatenate([gy.ravel(), plat, rng.uniform(plat.min(), plat.max() + 0.01, 500)])
    got = _heights_in(mesh, lon, lat)
    for i in range(len(lon)):  # the reference: every triangle for each point
        a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
        det = (plat[b] - plat[c]) * (plon[a] - plon[c]) + (plon[c] - plon[b]) * (plat[a] - plat[c])
        wa = (
            (plat[b] - plat[c]) * (lon[i] - plon[c]) + (plon[c] - plon[b]) * (lat[i] - plat[c])
        ) / det
        wb = (
            (plat[c] - plat[a]) * (lon[i] - plon[c]) + (plon[a] - plon[c]) * (lat[i] - plat[c])
        ) / det
        wc = 1.0 - wa - wb
        hit = np.nonzero((wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9))[0]
        if hit.size == 0:
            assert np.isnan(got[i])
            continue
        k = hit[0]
        want = wa[k] * h[a[k]] + wb[k] * h[b[k]] + wc[k] * h[c[k]]
        assert got[i] == pytest.approx(want, abs=1e-6)


def test_names_with_uri_characters(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A "?", "#", "%" or space in a folder's or file's name (SQLite's URIs read them as the
    query, the fragment or an escape: the reader opened another file, or none)."""
    from lodscape.imagery.sources import MBTilesSource

    folder = tmp_path / "survey? 50%#2"
    folder.mkdir()
    odd = folder / "site #1.lods"
    shutil.copy(built, odd)
    code, out, err = _run(["info", str(odd)], capsys)
    assert code == 0, err
    assert "quantized-mesh-1.0" in out
    source = MBTilesSource(odd)
    assert source.max_zoom >= source.min_zoom
    z = source.max_zoom
    with closing(sqlite3.connect(odd)) as db:
        x, row = db.execute(
            "SELECT tile_column, tile_row FROM tiles WHERE zoom_level = ? LIMIT 1", (z,)
        ).fetchone()
    assert source.fetch(z, x, (1 << z) - 1 - row)[:8] == b"\x89PNG\r\n\x1a\n"
    source.close()


def test_an_export_on_workers_writes_the_same_folder(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``export --cesium`` on processes writes the same files, byte for byte, as in one
    process; chunks of columns, several per level (made small here to have many)."""
    from lodscape.build.executors import PoolExecutor
    from lodscape.store import export

    serial, parallel = tmp_path / "one", tmp_path / "many"
    code, _, err = _run(["export", str(built), "--cesium", str(serial)], capsys)
    assert code == 0, err
    monkeypatch.setattr(export, "_CHUNK", 3)
    with closing(connect_readonly(built)) as db:
        chunks = list(export._chunks(db, ("terrain", "tiles")))
        geographic = list(export._geographic_chunks(available_tiles(db)))
    assert len(chunks) > 6
    assert len(geographic) > 6
    pool = PoolExecutor(2, processes=False)
    try:
        export.export_cesium(built, parallel, pool)
        export.export_cesium(built, tmp_path / "many-mercator", pool, tiling="mercator")
    finally:
        pool.close()
    export.export_cesium(built, tmp_path / "one-mercator", tiling="mercator")

    def files(root: Path) -> dict[str, bytes]:
        return {str(p.relative_to(root)): p.read_bytes() for p in root.rglob("*") if p.is_file()}

    assert files(serial) == files(parallel)
    assert files(tmp_path / "one-mercator") == files(tmp_path / "many-mercator")
    code, _, err = _run(
        ["export", str(built), "--cesium", str(tmp_path / "w"), "--workers", "2"], capsys
    )
    assert code == 0, err
    assert files(tmp_path / "w") == files(serial)


def test_an_export_for_a_known_url_names_its_imagery_absolutely(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """MapLibre resolves a TileJSON's relative tile URL against the page, not the TileJSON:
    with --base-url the exported imagery.json names its tiles absolutely."""
    folder = tmp_path / "web"
    argv = ["export", str(built), "--cesium", str(folder), "--base-url", "https://cdn.example/t/"]
    code, _, err = _run(argv, capsys)
    assert code == 0, err
    tj = json.loads((folder / "imagery.json").read_text())
    assert tj["tiles"] == ["https://cdn.example/t/imagery/{z}/{x}/{y}.png"]
    code, _, err = _run(
        ["export", str(built), "--cesium", str(tmp_path / "w2"), "--base-url", "cdn"], capsys
    )
    assert code == 2
    assert "--base-url" in err


def test_the_credit_is_what_the_data_states_or_what_the_user_gives(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A GeoTIFF's copyright tag is the tileset's attribution in its MBTiles metadata, its
    imagery's TileJSON and its layer.json; --attribution overrides it; a raster that states
    none is credited by name (never a placeholder sentence)."""
    import rasterio

    dem = write_dem(
        str(tmp_path / "dem.tif"), fbm_heights(65, seed=3), crs="EPSG:32617", west=700000.0,
        north=4060000.0, res=30.0,
    )  # fmt: skip
    with rasterio.open(dem, "r+") as ds:
        ds.update_tags(TIFFTAG_COPYRIGHT="© Test Survey 2024")
    for flags, want in (([], "© Test Survey 2024"), (["--attribution", "© Mine"], "© Mine")):
        out = tmp_path / f"site{len(flags)}.lods"
        code, _, err = _run(["build", dem, "-o", str(out), "-q", *flags], capsys)
        assert code == 0, err
        folder = tmp_path / f"web{len(flags)}"
        code, _, err = _run(["export", str(out), "--cesium", str(folder)], capsys)
        assert code == 0, err
        assert json.loads((folder / "imagery.json").read_text())["attribution"] == want
        assert json.loads((folder / "layer.json").read_text())["attribution"] == want
        with closing(sqlite3.connect(out)) as db:
            row = db.execute("SELECT value FROM metadata WHERE name = 'attribution'").fetchone()
        assert row[0] == want
    plain = write_dem(
        str(tmp_path / "plain.tif"), fbm_heights(65, seed=3), crs="EPSG:32617", west=700000.0,
        north=4060000.0, res=30.0,
    )  # fmt: skip
    code, _, err = _run(["build", plain, "-o", str(tmp_path / "p.lods"), "-q"], capsys)
    assert code == 0, err
    with closing(sqlite3.connect(tmp_path / "p.lods")) as db:
        row = db.execute("SELECT value FROM metadata WHERE name = 'attribution'").fetchone()
    assert row[0].startswith("plain.tif")
