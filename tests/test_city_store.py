"""Cities stored in a tileset: ``lodscape city add/list/remove``, read back whole, draped by
render, refused cleanly when the input is wrong, and never half-written."""

from __future__ import annotations

import shutil
import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
import shapely

from _synthetic import helsinki_tileset, run_cli
from lodscape.city.osm import read_osm
from lodscape.data import sample_city_path
from lodscape.store.city import add_city, read_city
from lodscape.store.tileset import TilesetError, TilesetProvider, lonlat_bounds


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return helsinki_tileset(tmp_path_factory.mktemp("city-store"))


@pytest.fixture
def fresh(site: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "site.lods"
    shutil.copy(site, copy)
    return copy


def _count(path: Path, table: str) -> int:
    with closing(sqlite3.connect(path)) as db:
        try:
            return int(db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
        except sqlite3.OperationalError:
            return 0


def test_add_list_read_back_and_remove(fresh: Path, capsys: pytest.CaptureFixture[str]) -> None:
    osm = sample_city_path()
    code, out, err = run_cli(["city", "add", str(fresh), str(osm), "--name", "centre"], capsys)
    assert code == 0, err
    assert "stored centre" in out
    city = read_osm(osm)
    w, s, e, n = lonlat_bounds(TilesetProvider(fresh).bounds_merc)
    box = shapely.box(w, s, e, n)
    inside = [b for b in city.buildings if b.footprint.intersects(box)]
    feats = [f for f in city.features if w <= f.lon <= e and s <= f.lat <= n]
    # the DEM covers part of the city: some objects are left out, and say so
    assert 0 < len(inside) < len(city.buildings)
    outside = len(city.buildings) - len(inside) + len(city.features) - len(feats)
    assert f"{outside:,} outside" in out
    provider = TilesetProvider(fresh)
    try:
        back = provider.city()
        assert back is not None
        assert len(back.buildings) == len(inside)
        assert len(back.features) == len(feats)
        for a, b in zip(inside, back.buildings, strict=True):
            assert a.osm_id == b.osm_id
            assert a.footprint.equals_exact(b.footprint, 0.0)
            assert (a.height, a.min_height, a.roof_shape, a.roof_height) == (
                b.height,
                b.min_height,
                b.roof_shape,
                b.roof_height,
            )
            assert (a.wall_material, a.roof_material, a.height_from) == (
                b.wall_material,
                b.roof_material,
                b.height_from,
            )
        assert [(f.kind, f.lon, f.lat, f.height) for f in feats] == [
            (f.kind, f.lon, f.lat, f.height) for f in back.features
        ]
        assert back.repaired == city.repaired
        assert back.holes == city.holes
        # the R*Tree index reads a box's objects only
        with closing(sqlite3.connect(fresh)) as db:
            part = read_city(db, "t", box=(w, s, (w + e) / 2, n))
        assert part is not None
        half = shapely.box(w, s, (w + e) / 2, n)
        assert len(part.buildings) == sum(b.footprint.intersects(half) for b in inside)
        assert 0 < len(part.buildings) < len(back.buildings)
    finally:
        provider.close()

    code, out, err = run_cli(["city", "list", str(fresh)], capsys)
    assert code == 0
    assert f"centre: {len(inside):,} buildings" in out
    # a second add under the same name is refused and changes nothing
    before = _count(fresh, "city_buildings")
    code, out, err = run_cli(["city", "add", str(fresh), str(osm), "--name", "centre"], capsys)
    assert code == 2
    assert "already holds a city named 'centre'" in err
    assert err.count("\n") == 1
    assert _count(fresh, "city_buildings") == before
    code, out, err = run_cli(
        ["city", "add", str(fresh), str(osm), "--name", "centre", "--replace"], capsys
    )
    assert code == 0, err
    assert _count(fresh, "city_buildings") == before
    assert _count(fresh, "city_building_index") == before
    code, out, err = run_cli(["city", "remove", str(fresh), "centre"], capsys)
    assert code == 0, err
    assert _count(fresh, "city_buildings") == 0
    assert _count(fresh, "city_building_index") == 0
    assert TilesetProvider(fresh).city() is None
    code, out, err = run_cli(["city", "remove", str(fresh), "centre"], capsys)
    assert code == 2
    assert "no city named 'centre'" in err


@pytest.mark.gl
def test_render_drapes_the_stored_city(
    fresh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from PIL import Image

    view = ["--lon", "24.9395", "--lat", "60.1655", "--alt", "160", "--heading", "20"]
    view += ["--pitch", "-25", "--size", "240x160", "--anisotropy", "1"]
    code, out, err = run_cli(
        ["render", str(fresh), "-o", str(tmp_path / "bare.png"), *view], capsys
    )
    assert code == 0, err
    assert "city" not in out
    code, out, err = run_cli(["city", "add", str(fresh), str(sample_city_path())], capsys)
    assert code == 0, err
    code, out, err = run_cli(
        ["render", str(fresh), "-o", str(tmp_path / "city.png"), *view], capsys
    )
    assert code == 0, err
    stats = dict(line.strip().split(": ", 1) for line in out.splitlines() if ": " in line)
    assert int(stats["city_draw_calls"]) > 0
    assert int(stats["city_triangles"]) > 1000
    a = np.asarray(Image.open(tmp_path / "bare.png"), np.int16)
    b = np.asarray(Image.open(tmp_path / "city.png"), np.int16)
    changed = float((np.abs(a - b).max(axis=2) > 24).mean())
    assert changed > 0.05, changed


@pytest.mark.gl
def test_fly_from_orbit_down_to_the_stored_city(
    fresh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One scene from 300 km straight down to 150 m over the city's streets: the globe, the
    tileset's tiles and its stored city, no cut."""
    import csv

    code, _, err = run_cli(["city", "add", str(fresh), str(sample_city_path())], capsys)
    assert code == 0, err
    route = tmp_path / "descent.csv"
    route.write_text(
        "lon,lat,alt,time,pitch\n24.9395,59.9,300000,0,-90\n24.9395,60.150,2000,4,-40\n"
        "24.9395,60.158,150,6,-20\n"
    )
    stats = tmp_path / "d.csv"
    argv = ["fly", str(fresh), "--globe", "--path", str(route), "--fps", "2", "--size"]
    argv += ["160x100", "-o", str(tmp_path / "d.mp4"), "--stats", str(stats), "-q"]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 13
    assert int(rows[0]["terrain_pixels"]) < 0.01 * 160 * 100  # from orbit: a speck
    assert int(rows[0]["facets"]) > 0
    last = rows[-1]
    assert int(last["terrain_pixels"]) > 0.5 * 160 * 100  # at street level: the tileset's
    assert int(last["city_objects_drawn"]) > 50  # and its city


def test_bad_inputs_are_one_line_errors(
    fresh: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    osm = str(sample_city_path())
    not_lods = tmp_path / "dem.tif"
    not_lods.write_bytes(b"II*\x00garbage")
    garbage = tmp_path / "broken.osm.pbf"
    garbage.write_bytes(b"\x00\x01 not a pbf")
    far = tmp_path / "far.osm"
    far.write_text(
        "<?xml version='1.0'?><osm version='0.6'>"
        "<node id='1' lat='48.85' lon='2.35'><tag k='natural' v='tree'/></node></osm>"
    )
    cases = [
        (["city", "add", str(not_lods), osm], "not a lodscape tileset"),
        (["city", "add", str(tmp_path / "missing.lods"), osm], "no such file"),
        (["city", "add", str(fresh), str(garbage)], "broken.osm.pbf"),
        (["city", "add", str(fresh), str(far)], "no object lies inside"),
    ]
    for argv, message in cases:
        code, _out, err = run_cli(argv, capsys)
        assert code == 2, (argv, err)
        assert message in err, err
        assert err.count("\n") == 1, err
        assert "Traceback" not in err
    assert _count(fresh, "city_sets") == 0


def test_a_failed_add_leaves_nothing(fresh: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    city = read_osm(sample_city_path())
    add_city(fresh, city, name="kept")
    kept = _count(fresh, "city_buildings")
    calls = {"n": 0}
    real = shapely.to_wkb

    def failing(geom: object, *a: object, **k: object) -> object:
        calls["n"] += 1
        if calls["n"] > 50:
            raise sqlite3.OperationalError("database or disk is full")
        return real(geom, *a, **k)

    monkeypatch.setattr(shapely, "to_wkb", failing)
    with pytest.raises(TilesetError, match="cannot store the city"):
        add_city(fresh, city, name="second")
    assert calls["n"] > 50
    assert _count(fresh, "city_buildings") == kept
    assert _count(fresh, "city_features") == _count(fresh, "city_feature_index")
    with closing(sqlite3.connect(fresh)) as db:
        names = [r[0] for r in db.execute("SELECT name FROM city_sets")]
    assert names == ["kept"]


_KILLED_ADD = """
import os, signal, sys
import shapely
from lodscape.cli import main

real, calls = shapely.to_wkb, [0]

def to_wkb(*args, **kwargs):  # the 20th building's footprint: deep inside the transaction
    calls[0] += 1
    if calls[0] == 20:
        os.kill(os.getpid(), signal.SIGKILL)
    return real(*args, **kwargs)

shapely.to_wkb = to_wkb
main(["city", "add", sys.argv[1], sys.argv[2], "--name", "half-added"])
"""


def _kill_city_add(tileset: Path) -> None:
    import subprocess
    import sys

    run = subprocess.run(
        [sys.executable, "-c", _KILLED_ADD, str(tileset), str(sample_city_path())],
        capture_output=True,
        timeout=120,
        check=False,
    )
    assert run.returncode == -9, run.stderr.decode()[-2000:]


def test_a_killed_city_add_leaves_a_readable_tileset(
    fresh: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """SIGKILL in the middle of ``city add``'s transaction: every reader still opens the file
    (it read "attempt to write a readonly database" for good), the half-added city is not there,
    and the next ``city add`` works."""
    before = fresh.read_bytes()
    _kill_city_add(fresh)
    for argv in (["info", str(fresh)], ["city", "list", str(fresh)]):
        code, out, err = run_cli(argv, capsys)
        assert code == 0, (argv, err)
        assert "half-added" not in out
    with closing(TilesetProvider(fresh)) as provider:
        assert provider.cities() == []
        assert provider.tree.levels
    code, _, err = run_cli(["city", "add", str(fresh), str(sample_city_path())], capsys)
    assert code == 0, err
    assert _count(fresh, "city_sets") == 1
    assert not Path(str(fresh) + "-wal").exists()  # the log folded back: one file again
    assert fresh.read_bytes() != before


def test_a_hot_rollback_journal_is_undone_by_readers(
    fresh: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A writer in rollback-journal mode (an older lodscape, or sqlite3 by hand) killed mid-write
    leaves a hot journal: the first reader undoes it and every reader works."""
    import subprocess
    import sys

    code = (
        "import os, signal, sqlite3, sys\n"
        "db = sqlite3.connect(sys.argv[1], isolation_level=None)\n"
        "db.execute('PRAGMA cache_size=1')\n"  # spill to the file: the journal is hot
        "db.execute('BEGIN IMMEDIATE')\n"
        "db.execute('DELETE FROM terrain')\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    run = subprocess.run([sys.executable, "-c", code, str(fresh)], timeout=60, check=False)
    assert run.returncode == -9
    assert Path(str(fresh) + "-journal").stat().st_size > 0
    code_, _, err = run_cli(["info", str(fresh)], capsys)
    assert code_ == 0, err
    assert _count(fresh, "terrain") > 0  # the delete was undone
    assert not Path(str(fresh) + "-journal").exists()
