"""``lodscape export --pmtiles/--terrarium``: PMTiles v3 archives read back by the PyPI
``pmtiles`` reader, tile for tile; Terrarium heights decoded against the tileset's own, holes
transparent."""

from __future__ import annotations

import io
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from pmtiles.reader import MmapSource, Reader, all_tiles
from pmtiles.tile import TileType

from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.build import BuildOptions, build
from lodscape.geo.tiles import Tile, merc_to_lonlat, tiles_array, xy_bounds
from lodscape.store.tileset import TilesetProvider

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0


@pytest.fixture(scope="module")
def tileset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    h = fbm_heights(129, seed=12)
    h[50:80, 45:85] = -9999.0  # a hole: no data, not a height
    folder = tmp_path_factory.mktemp("pmtiles")
    dem = write_dem(
        str(folder / "hole.tif"),
        h,
        crs="EPSG:32617",
        west=EAST,
        north=NORTH,
        res=RES,
        nodata=-9999,
    )
    out = folder / "site.lods"
    build([dem], out, BuildOptions(fill="none"))
    return out


def test_export_writes_imagery_and_terrarium_archives_a_reader_reads(
    tileset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    img, dem = tmp_path / "imagery.pmtiles", tmp_path / "terrain.pmtiles"
    argv = ["export", str(tileset), "--pmtiles", str(img), "--terrarium", str(dem)]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "imagery tiles" in out
    assert "terrain tiles" in out
    db = sqlite3.connect(tileset)
    stored = {
        (z, x, (1 << z) - 1 - row): bytes(d)
        for z, x, row, d in db.execute(
            "SELECT zoom_level, tile_column, tile_row, tile_data FROM tiles"
        )
    }
    terrain = {(z, x, y) for z, x, y in db.execute("SELECT z, x, y FROM terrain")}
    db.close()
    # every imagery tile, byte for byte, and nothing else
    with img.open("rb") as f:
        get = MmapSource(f)
        reader = Reader(get)
        header = reader.header()
        assert header["tile_type"] == TileType.PNG
        assert header["min_zoom"] == 0
        assert header["max_zoom"] == max(z for z, _, _ in stored)
        got = {zxy: bytes(data) for zxy, data in all_tiles(get)}
        assert header["addressed_tiles_count"] == len(got)
        assert {k: got[k] for k in stored} == stored
        assert reader.get(*next(iter(stored))) == stored[next(iter(stored))]
        assert "name" in reader.metadata()
    # and every other tile over the data's bounds from level 0: none of the advertised range
    # is missing (a client logs each 404 as a failure); overviews above the stored levels,
    # transparent tiles where a stored level has none
    lo, hi = min(z for z, _, _ in stored), max(z for z, _, _ in stored)
    assert set(got) == _over_bounds(tileset, 0, hi)
    shown = 0
    for k in set(got) - set(stored):
        alpha = np.asarray(Image.open(io.BytesIO(got[k])).convert("RGBA"))[..., 3]
        if k[0] >= lo:
            assert alpha.max() == 0, k
        else:
            shown += int(alpha.max() > 0)
    assert shown >= lo - 4  # the data, a few pixels or more, down to a few levels above
    # the terrain: every tile over the data from level 0 to the data's own (the texture
    # level), heights as the stored tile of its level has them; none at -32768 m
    provider = TilesetProvider(tileset)
    try:
        levels = provider.manifest["levels"]
        with dem.open("rb") as f:
            get = MmapSource(f)
            meta = Reader(get).metadata()
            assert meta["encoding"] == "terrarium"
            assert meta["fill"] == "none"
            assert meta["nodata_height"] == 0.0
            tiles = dict(all_tiles(get))
        assert set(tiles) == _over_bounds(tileset, 0, levels["texture_zmax"])
        assert levels["texture_zmax"] < levels["zmax"]  # not the finer terrain levels
        for data in tiles.values():
            rgba = np.asarray(Image.open(io.BytesIO(data)), np.float64)
            h = rgba[..., 0] * 256 + rgba[..., 1] + rgba[..., 2] / 256 - 32768
            assert h.min() > -1000.0
            # no data: transparent, at the fill's height (0 m here), never -32768
            assert (h[rgba[..., 3] == 0] == 0.0).all()
        holes = checked = 0
        for z, x, y in sorted(terrain & set(tiles), reverse=True):
            if checked == 8:
                break
            rgba = np.asarray(Image.open(io.BytesIO(tiles[(z, x, y)])), np.float64)
            h = rgba[..., 0] * 256 + rgba[..., 1] + rgba[..., 2] / 256 - 32768
            b = xy_bounds(Tile(x, y, z))
            f = (np.arange(256) + 0.5) / 256
            xm, ym = np.meshgrid(b.left + f * (b.right - b.left), b.top - f * (b.top - b.bottom))
            lon, lat = merc_to_lonlat(xm, ym)
            want = provider.tile_heights(z, x, y, lon, lat)
            ok = np.isfinite(want)
            assert np.array_equal(rgba[..., 3] == 255, ok)
            holes += int((~ok).sum())
            if ok.any():
                assert np.abs(h[ok] - want[ok]).max() <= 1 / 256
                checked += 1
        assert checked >= 4
        assert holes > 0  # the hole (and the outside) is transparent, not a made-up height
        # the overviews above the roots: the roots' surface, not empty
        top = [tiles[k] for k in tiles if k[0] == levels["zmin"] - 1]
        assert any(np.asarray(Image.open(io.BytesIO(t)))[..., 3].max() == 255 for t in top)
    finally:
        provider.close()


def _over_bounds(tileset: Path, lo: int, hi: int) -> set[tuple[int, int, int]]:
    """Every tile (z, x, OSM row) of levels lo..hi that the data's bounds touch."""
    p = TilesetProvider(tileset)
    b = p.bounds_merc
    p.close()
    out = set()
    for z in range(lo, hi + 1):
        (x0, x1), (y0, y1) = (
            (int(v0), int(v1))
            for v0, v1 in (
                tiles_array([b.left, b.right], [b.top, b.bottom], z)[0].tolist(),
                tiles_array([b.left, b.right], [b.top, b.bottom], z)[1].tolist(),
            )
        )
        out |= {(z, x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)}
    return out


def test_export_refuses_in_one_line_and_leaves_nothing(
    tileset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _, err = run_cli(["export", str(tileset)], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    missing = tmp_path / "no" / "x.pmtiles"
    code, _, err = run_cli(["export", str(tileset), "--pmtiles", str(missing)], capsys)
    assert code == 2
    assert "x.pmtiles" in err
    assert len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.lods"
    bad.write_bytes(b"not a tileset")
    out = tmp_path / "x.pmtiles"
    code, _, err = run_cli(["export", str(bad), "--pmtiles", str(out)], capsys)
    assert code == 2
    assert "bad.lods" in err
    assert not out.exists()
    assert not list(tmp_path.glob(".*tmp"))


def test_two_archives_are_written_together_or_not_at_all(
    tileset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The imagery archive is complete before the terrain's fails: neither is left."""
    import shutil

    broken = tmp_path / "cut.lods"
    shutil.copy(tileset, broken)
    with sqlite3.connect(broken) as db:  # a root terrain tile cut short
        z, x, y = db.execute("SELECT z, x, y FROM terrain ORDER BY z LIMIT 1").fetchone()
        db.execute("UPDATE terrain SET data = X'00010203' WHERE z=? AND x=? AND y=?", (z, x, y))
    img, dem = tmp_path / "img.pmtiles", tmp_path / "dem.pmtiles"
    code, _, err = run_cli(
        ["export", str(broken), "--pmtiles", str(img), "--terrarium", str(dem)], capsys
    )
    assert code == 2, err
    assert "cut short" in err
    assert len(err.strip().splitlines()) == 1
    assert not img.exists()
    assert not dem.exists()
    assert not list(tmp_path.glob(".*tmp"))
