"""A flight over a terrain server that fails keeps flying and says so: each kind of failure once on
stderr, counted in ``--stats`` (``failed``, ``terrain_failed``, ``http_requests``), the tile
asked for again later; a root tile that is down at first is retried, the ellipsoid drawn
meanwhile (a real quantized-mesh server on loopback, the real command)."""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import pytest

from _synthetic import run_cli
from _tileserver import TerrainServer

pytestmark = pytest.mark.gl

#: What stderr says for each fault.
SAID = {
    "hang": "no answer in time",
    "trickle": "no answer in time",
    "500": "error answers",
    "garbage": "answers that are not terrain tiles",
    "bomb": "answers that are not terrain tiles",
    "truncated": "answers cut short",
}


@pytest.fixture
def server(request: pytest.FixtureRequest) -> Iterator[TerrainServer]:
    s = TerrainServer(request.param)
    yield s
    s.close()


def _fly(
    url: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], timeout: float = 5.0
) -> tuple[int, str, list[dict[str, str]]]:
    stats = tmp_path / "s.csv"
    code, _, err = run_cli(
        # 5000 m: the server's deepest level (11) is as fine as the view asks there
        ["fly", url, "--line", "7.98,45.98,8.02,46.02,5000", "--speed", "150", "--fps", "10",
         "--size", "160x96", "-o", str(tmp_path / "f.mp4"), "--stats", str(stats),
         "--imagery-cache", str(tmp_path / "cache"), "--imagery-timeout", f"{timeout:g}", "-q"],
        capsys,
    )  # fmt: skip
    rows: list[dict[str, str]] = []
    if stats.exists():
        with stats.open() as f:
            rows = list(csv.DictReader(f))
    return code, err, rows


@pytest.mark.parametrize("server", sorted(SAID), indirect=True)
def test_each_fault_is_said_once_and_counted(
    server: TerrainServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a hung or trickling server costs a tile its timeout: 1 s keeps the flight short; the
    # others answer at once (on a loaded machine a 1 s deadline could add a timeout to them)
    slow = server.fault in ("hang", "trickle")
    code, err, rows = _fly(server.url, tmp_path, capsys, 1.0 if slow else 5.0)
    assert code == 0, err
    said = [line for line in err.splitlines() if "terrain server" in line]
    kinds = [line.split(": ")[2] for line in said]  # "terrain server URL: KIND: …"
    assert len(kinds) == len(set(kinds)), err  # each kind said once
    assert sum(SAID[str(server.fault)] in line for line in said) == 1, err
    assert all("(counted in --stats)" in line for line in said)
    assert sum(int(r["failed"]) for r in rows) >= 1
    assert int(rows[-1]["terrain_failed"]) >= 1
    assert int(rows[-1]["http_requests"]) >= int(rows[-1]["terrain_failed"])
    assert (tmp_path / "f.mp4").stat().st_size > 1000


@pytest.mark.parametrize("server", [None], indirect=True)
def test_a_healthy_servers_requests_are_counted(
    server: TerrainServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, err, rows = _fly(server.url, tmp_path, capsys)
    assert code == 0, err
    assert "terrain server" not in err
    assert int(rows[-1]["http_requests"]) > 10
    assert int(rows[-1]["terrain_failed"]) == 0
    assert float(rows[-1]["max_sse_px"]) <= 2.0  # it reached the detail the view asks for


@pytest.mark.parametrize("server", ["root-down"], indirect=True)
def test_a_root_tile_down_at_first_is_retried(
    server: TerrainServer, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a 1 s deadline: the HTTP client's own retries end before the 2 s outage does
    code, err, rows = _fly(server.url, tmp_path, capsys, 1.0)
    assert code == 0, err
    assert "error answers" in err
    assert int(rows[0]["triangles"]) == 0  # the first frame: the ellipsoid alone
    assert int(rows[0]["terrain_failed"]) >= 1
    assert int(rows[-1]["tiles"]) >= 1
    assert float(rows[-1]["max_sse_px"]) <= 2.0
