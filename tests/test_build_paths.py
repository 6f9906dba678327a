"""Builds from any path GDAL reads (issue 38): a DEM inside a zip (``/vsizip/``) and one served by
a real loopback server with range requests (``/vsicurl/``) build the same tileset as the plain
file; the manifest records each input's provenance (the archive's size and time for a member,
none for a remote input, said once on stderr)."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import zipfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from _synthetic import fbm_heights, write_dem
from _tileserver import RangeServer
from lodscape.build import BuildOptions, build
from lodscape.terrain.paths import absolute, is_remote, local_file, provenance


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("paths")
    path = folder / "dem.tif"
    heights = fbm_heights(257, seed=5)
    write_dem(str(path), heights, crs="EPSG:32633", west=500000.0, north=5000000.0, res=30.0)
    return path


@pytest.fixture(scope="module")
def served(dem: Path) -> Iterator[RangeServer]:
    server = RangeServer(dem)
    yield server
    server.close()


def _rows(path: Path) -> list[tuple[object, ...]]:
    with sqlite3.connect(path) as db:
        query = "SELECT z, x, y, error, min_h, max_h, data FROM terrain ORDER BY 1, 2, 3"
        return db.execute(query).fetchall()


def _manifest(path: Path) -> dict[str, object]:
    from lodscape.store.manifest import connect_readonly, read_manifest

    db = connect_readonly(path)
    try:
        return read_manifest(db, str(path))
    finally:
        db.close()


def test_paths_as_every_process_reads_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.zip").write_bytes(b"PK")
    assert absolute("dem.tif") == str(tmp_path / "dem.tif")
    # a relative archive made absolute in GDAL's form; a remote one left as it is
    assert absolute("/vsizip/a.zip/dem.tif") == f"/vsizip/{tmp_path}/a.zip/dem.tif"
    assert absolute("/vsicurl/http://h/x.tif") == "/vsicurl/http://h/x.tif"
    assert is_remote("/vsizip//vsicurl/http://h/a.zip/x.tif")
    assert not is_remote("/vsizip/a.zip/x.tif")
    assert local_file(absolute("/vsizip/a.zip/dir/x.tif")) == str(tmp_path / "a.zip")
    assert provenance("/vsis3/bucket/x.tif") == {
        "path": "/vsis3/bucket/x.tif",
        "bytes": None,
        "mtime_ns": None,
        "remote": True,
    }
    got = provenance("/vsizip/a.zip/x.tif")
    assert got["bytes"] == 2
    assert got["file"] == str(tmp_path / "a.zip")


def test_a_zipped_and_a_served_dem_build_the_plain_files_tileset(
    dem: Path,
    served: RangeServer,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    zipped = tmp_path / "dem.zip"
    with zipfile.ZipFile(zipped, "w") as z:
        z.write(dem, "inside/dem.tif")
    plain = build([dem], tmp_path / "plain.lods", BuildOptions())
    capsys.readouterr()
    monkeypatch.chdir(tmp_path)  # a relative archive path, as a user types it
    from_zip = build(["/vsizip/dem.zip/inside/dem.tif"], tmp_path / "zip.lods", BuildOptions())
    assert "remote" not in capsys.readouterr().err
    served.sent = 0
    # GDAL holds the interpreter while it reads a URL: the loopback server's thread must be in
    # another process than the build's
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape", "build", f"/vsicurl/{served.url}", "-o",
         str(tmp_path / "url.lods"), "-q"],
        capture_output=True, text=True, timeout=300,
        env={**os.environ, "LODSCAPE_CACHE": str(tmp_path / "cache")},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("a remote input") == 1, proc.stderr
    assert served.sent > 0
    assert plain.planned == from_zip.planned > 0
    rows = _rows(tmp_path / "plain.lods")
    assert _rows(tmp_path / "zip.lods") == rows
    assert _rows(tmp_path / "url.lods") == rows
    zp = _manifest(tmp_path / "zip.lods")["provenance"]
    assert zp == [
        {
            "path": f"/vsizip/{tmp_path}/dem.zip/inside/dem.tif",
            "bytes": zipped.stat().st_size,
            "mtime_ns": zipped.stat().st_mtime_ns,
            "file": str(zipped),
        }
    ]
    up = _manifest(tmp_path / "url.lods")["provenance"]
    assert up == [
        {"path": f"/vsicurl/{served.url}", "bytes": None, "mtime_ns": None, "remote": True}
    ]


def test_a_missing_member_is_one_line_naming_it(tmp_path: Path) -> None:
    from lodscape.errors import LodscapeError

    with zipfile.ZipFile(tmp_path / "empty.zip", "w") as z:
        z.writestr("readme.txt", "nothing here")
    path = f"/vsizip/{tmp_path}/empty.zip/dem.tif"
    with pytest.raises(LodscapeError, match=r"empty\.zip/dem\.tif"):
        build([path], tmp_path / "out.lods", BuildOptions())
    assert not (tmp_path / "out.lods").exists()
