"""The last silent failures: each said in one line, nothing left behind, nothing lost (real files,
real processes, the real command)."""

from __future__ import annotations

import csv
import os
import signal
import sqlite3
import subprocess
import sys
import time
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.imagery.sources import ImageryError

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0


def _dem(folder: Path) -> str:
    return write_dem(
        str(folder / "dem.tif"), fbm_heights(65, seed=1), crs="EPSG:32617", west=EAST,
        north=NORTH, res=RES,
    )  # fmt: skip


def test_a_garbage_height_tile_is_named_not_its_buffer() -> None:
    from lodscape.store.remote import _decode_png

    with pytest.raises(ImageryError) as err:
        _decode_png(b"<html>nope</html>", "terrarium", "http://h/1/2/3.png")
    assert "http://h/1/2/3.png" in str(err.value)
    assert "BytesIO" not in str(err.value)


def test_a_vrt_with_a_missing_source_is_one_line(tmp_path: Path) -> None:
    """GDAL's own "ERROR 4" lines (printed by its default handler, outside rasterio's) stay
    out of the terminal: the command's one line says it."""
    _dem(tmp_path)
    (tmp_path / "m.vrt").write_text(
        '<VRTDataset rasterXSize="64" rasterYSize="64"><SRS>EPSG:32617</SRS>'
        f"<GeoTransform>{EAST}, {RES}, 0, {NORTH}, 0, -{RES}</GeoTransform>"
        '<VRTRasterBand dataType="Float32" band="1"><SimpleSource>'
        '<SourceFilename relativeToVRT="1">gone.tif</SourceFilename><SourceBand>1</SourceBand>'
        "</SimpleSource></VRTRasterBand></VRTDataset>"
    )
    run = subprocess.run(
        [sys.executable, "-m", "lodscape.cli", "info", str(tmp_path / "m.vrt")],
        capture_output=True, text=True, timeout=300,
        env={k: v for k, v in os.environ.items() if k != "CPL_LOG"},
    )  # fmt: skip
    assert run.returncode == 2
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, run.stderr
    assert "m.vrt" in lines[0]
    assert "gone.tif" in lines[0]


def _journal(path: Path) -> str:
    with closing(sqlite3.connect(path)) as db:
        return str(db.execute("PRAGMA journal_mode").fetchone()[0])


def test_a_refused_build_leaves_the_file_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dem = _dem(tmp_path)
    out = tmp_path / "site.lods"
    code, _, err = run_cli(["build", dem, "-o", str(out), "-q"], capsys)
    assert code == 0, err
    assert _journal(out) == "delete"
    before = out.read_bytes()
    code, _, err = run_cli(["build", dem, "-o", str(out), "-q", "--error-texels", "3"], capsys)
    assert code == 2
    assert "other inputs or options" in err
    assert _journal(out) == "delete"
    assert out.read_bytes() == before
    assert not Path(str(out) + "-wal").exists()


def _dead_pid() -> int:
    pid = 4_000_000
    while True:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return pid
        except OSError:
            pass
        pid += 1


@pytest.mark.gl
def test_a_killed_runs_temporary_files_are_swept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dem = _dem(tmp_path)
    dead = tmp_path / f".out.png.{_dead_pid()}.tmp"
    live = tmp_path / f".out.png.{os.getppid()}.tmp"  # another run, still going: kept
    dead.write_bytes(b"half a picture")
    live.write_bytes(b"being written")
    code, _, err = run_cli(["render", dem, "--size", "64x48", "-o", str(tmp_path / "out.png")],
                           capsys)  # fmt: skip
    assert code == 0, err
    assert not dead.exists()
    assert live.exists()
    assert (tmp_path / "out.png").exists()


@pytest.mark.gl
def test_a_killed_flight_keeps_its_statistics_rows(tmp_path: Path) -> None:
    dem = _dem(tmp_path)
    stats = tmp_path / "s.csv"
    cmd = [sys.executable, "-m", "lodscape.cli", "fly", dem, "--orbit=-78.78,36.66,500,2000",
           "--duration", "600", "--size", "64x48", "-o", str(tmp_path / "f.mp4"),
           "--stats", str(stats), "-q"]  # fmt: skip
    with open(tmp_path / "log", "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=log)
        rows = 0
        deadline = time.monotonic() + 240
        try:
            while time.monotonic() < deadline and proc.poll() is None and rows < 5:
                time.sleep(0.2)
                if stats.exists():
                    rows = len(stats.read_text().splitlines()) - 1
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
    assert rows >= 5, (tmp_path / "log").read_text()
    with stats.open() as f:
        got = list(csv.DictReader(f))
    assert len(got) >= rows
    assert [int(r["frame"]) for r in got] == list(range(len(got)))


def _six_band(folder: Path) -> str:
    data = np.random.default_rng(4).integers(0, 255, (6, 64, 64), dtype=np.uint8)
    path = folder / "scene.tif"
    with rasterio.open(
        path, "w", driver="GTiff", width=64, height=64, count=6, dtype="uint8",
        crs="EPSG:32617", transform=Affine(RES, 0.0, EAST, 0.0, -RES, NORTH),
    ) as dst:  # fmt: skip
        dst.write(data)
    return str(path)


@pytest.mark.gl
def test_a_multiband_scenes_colour_bands_are_said_or_chosen(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dem, scene = _dem(tmp_path), _six_band(tmp_path)
    out = tmp_path / "o.png"
    code, _, err = run_cli(["render", dem, "--imagery", scene, "--size", "64x48", "-o", str(out)],
                           capsys)  # fmt: skip
    assert code == 0, err
    assert err.count("bands 1,2,3 drawn as red, green, blue") == 1, err
    code, _, err = run_cli(
        ["render", dem, "--imagery", scene, "--imagery-bands", "4,3,2", "--size", "64x48",
         "-o", str(out)],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "drawn as red" not in err


@pytest.mark.gl
def test_imagery_strict_says_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_cli(
        ["render", _dem(tmp_path), "--imagery", "http://127.0.0.1:9/{z}/{x}/{y}.png",
         "--imagery-strict", "--imagery-timeout", "1", "--imagery-cache", str(tmp_path),
         "--size", "64x48", "-o", str(tmp_path / "o.png")],
        capsys,
    )  # fmt: skip
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "--imagery-strict" in lines[0]
