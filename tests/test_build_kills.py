"""A build killed (SIGKILL) at any phase resumes to the very tileset an unkilled build makes, row
for row, and leaves no process of its own behind: threads, processes and a Dask cluster."""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from contextlib import closing
from pathlib import Path

import pytest

from _synthetic import fbm_heights, write_dem
from lodscape.store.tileset import TilesetError, TilesetProvider

HERE = Path(__file__).parent
TABLES = {
    "plan": "z, x, y",
    "terrain": "z, x, y",
    "tiles": "zoom_level, tile_column, tile_row",
    "blocks": "z, x, y",
    "metadata": "name",
}


def _with(folder: str) -> str:
    """PYTHONPATH with ``folder`` first."""
    return os.pathsep.join([folder, *filter(None, [os.environ.get("PYTHONPATH")])])


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    # small, and fine enough that the build refines a level below the one it planned
    path = tmp_path_factory.mktemp("kills") / "dem.tif"
    return write_dem(
        str(path),
        fbm_heights(129, seed=5),
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=10.0,
    )


def _rows(path: Path) -> dict[str, list[tuple[object, ...]]]:
    with closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
        return {
            t: db.execute(f"SELECT * FROM {t} ORDER BY {k}").fetchall() for t, k in TABLES.items()
        }


def _build(
    phase: str, dem: str, out: Path, pids: Path, flags: list[str], env: dict[str, str] | None = None
) -> int:
    argv = ["build", dem, "-o", str(out), "-q", *flags]
    cmd = [sys.executable, str(HERE / "_kill_build.py"), phase, str(pids), "--", *argv]
    # output to a file, not a pipe: an orphaned worker holding a pipe would hang the run
    with open(out.with_suffix(".log"), "ab") as log:
        return subprocess.run(
            cmd, stdout=log, stderr=log, timeout=300, env={**os.environ, **(env or {})}
        ).returncode


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture(scope="module")
def unkilled(
    dem: str, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, list[tuple[object, ...]]]:
    out = tmp_path_factory.mktemp("unkilled") / "site.lods"
    assert _build("never", dem, out, out.with_suffix(".pids"), []) == 0
    return _rows(out)


def _levels(rows: dict[str, list[tuple[object, ...]]]) -> list[int]:
    return sorted({int(r[0]) for r in rows["terrain"]})  # type: ignore[call-overload]


def _kill_and_resume(
    phase: str,
    flags: list[str],
    dem: str,
    tmp_path: Path,
    want: dict[str, list[tuple[object, ...]]],
) -> None:
    out, pids = tmp_path / "site.lods", tmp_path / "pids"
    assert _build(phase, dem, out, pids, flags) == -9, f"the build was not killed at {phase}"
    if sys.platform.startswith("linux"):
        children = [int(p) for p in pids.read_text().split()]
        if flags:
            assert children, "the build's workers were not seen"
        gone = time.monotonic() + 5.0
        while time.monotonic() < gone and any(_alive(c) for c in children):
            time.sleep(0.1)
        assert not [c for c in children if _alive(c)], (
            f"a worker outlived the build killed at {phase}"
        )
    if phase != "fold":
        with pytest.raises(TilesetError, match="stopped at"):
            TilesetProvider(out)
    assert _build("never", dem, out, pids, flags) == 0
    got = _rows(out)
    for table in TABLES:
        assert got[table] == want[table], f"{table} differs after a kill at {phase}"
    assert not Path(str(out) + "-wal").exists()


def test_the_phases_are_distinct(unkilled: dict[str, list[tuple[object, ...]]]) -> None:
    """Four levels at least: the planned ones and the refinement pass's are each killed in."""
    assert len(_levels(unkilled)) >= 4


@pytest.mark.parametrize("phase", ["plan", "level:0", "level:1", "level:2", "level:-1", "fold"])
def test_a_build_killed_at_any_phase_resumes_to_the_same_rows(
    phase: str, dem: str, tmp_path: Path, unkilled: dict[str, list[tuple[object, ...]]]
) -> None:
    if phase.startswith("level:"):
        # level:-1 is the finest: the refinement pass's
        phase = f"level:{_levels(unkilled)[int(phase.split(':')[1])]}"
    _kill_and_resume(phase, [], dem, tmp_path, unkilled)


@pytest.mark.parametrize("flags", [["--workers", "2"], ["--scheduler", "local", "--workers", "2"]])
def test_a_build_on_processes_killed_in_its_refinement_resumes_and_leaves_no_worker(
    flags: list[str], dem: str, tmp_path: Path, unkilled: dict[str, list[tuple[object, ...]]]
) -> None:
    _kill_and_resume(f"level:{_levels(unkilled)[-1]}", flags, dem, tmp_path, unkilled)


def test_a_build_killed_while_its_workers_start_leaves_none(
    dem: str, tmp_path: Path, unkilled: dict[str, list[tuple[object, ...]]]
) -> None:
    """Killed before its workers have even imported lodscape: they end as soon as they can."""
    _kill_and_resume("spawn", ["--workers", "2"], dem, tmp_path, unkilled)


@pytest.mark.parametrize("flags", [["--workers", "2"], ["--scheduler", "local", "--workers", "2"]])
def test_a_build_whose_worker_is_killed_says_so_and_resumes_to_the_same_rows(
    flags: list[str], dem: str, tmp_path: Path, unkilled: dict[str, list[tuple[object, ...]]]
) -> None:
    """A worker SIGKILLed as it finishes a block of the coarsest band (the build itself lives
    on): one line that says a worker died, and the same build run again ends with the rows
    an unkilled build makes."""
    out, pids = tmp_path / "site.lods", tmp_path / "pids"
    env = {
        "PYTHONPATH": os.pathsep.join(
            [str(HERE / "_worker_kill"), os.environ.get("PYTHONPATH", "")]
        ),
        "LODSCAPE_TEST_KILL_WORKER_AT": str(_levels(unkilled)[0]),
    }
    assert _build("never", dem, out, pids, flags, env) == 2
    log = out.with_suffix(".log").read_text()
    assert "a build worker died" in log, log[-2000:]
    assert _build("never", dem, out, pids, flags) == 0
    got = _rows(out)
    for table in TABLES:
        assert got[table] == unkilled[table], f"{table} differs after a worker was killed"
