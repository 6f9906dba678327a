"""The staged pipeline: budgets, the simulated clock, failures and retries (an in-memory source
through the fetch seam), then flights over a real tileset on real OpenGL."""

from __future__ import annotations

import csv
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_tileset, run_cli
from lodscape import Camera, SceneOptions
from lodscape.errors import SourceError
from lodscape.stream import SimClock, Streamer, StreamOptions

EAST, NORTH = 700000.0, 4060000.0


class MemorySource:
    """The fetch seam's in-memory version: bytes per key, a delay, and keys that fail."""

    def __init__(self, size: int = 1000, delay: float = 0.0) -> None:
        self.size = size
        self.delay = delay
        self.failing: set[int] = set()
        self.calls: list[int] = []
        self.lock = threading.Lock()

    def fetch(self, key: int) -> bytes:
        with self.lock:
            self.calls.append(key)
        time.sleep(self.delay)
        if key in self.failing:
            raise SourceError(f"tile {key}: server answered 500")
        return bytes([key % 256]) * self.size

    def cost(self, key: int) -> float:
        """The simulated seconds a fetch is charged: its delay, whatever the machine's load."""
        return self.delay

    def decode(self, key: int, data: bytes) -> np.ndarray:
        return np.frombuffer(data, np.uint8).reshape(1, -1, 1).repeat(4, axis=2)


def _settle(s: Streamer, clock: SimClock, seconds: float = 1.0) -> None:
    s.drain()
    clock.advance(seconds)
    s.collect()


def test_stages_keep_to_their_budgets() -> None:
    src = MemorySource(size=100_000)
    clock = SimClock()
    s = Streamer(src, StreamOptions(cache_mb=0.5, memory_mb=1.0, in_flight=64), clock)
    try:
        for batch in range(5):
            keys = list(range(batch * 20, batch * 20 + 20))
            s.request(keys, "memory", lambda k: False)
            s.request([k + 1000 for k in keys], "cache", lambda k: False)
            _settle(s, clock)
            assert s.cache_bytes <= 0.5 * 2**20
            assert s.memory_bytes <= 1.0 * 2**20
            assert s.memory_bytes == sum(m.nbytes for m in s.memory.values())
            assert s.cache_bytes == sum(len(b) for b in s.cache.values())
        assert s.stats.fetched == 200
    finally:
        s.close()


def test_the_simulated_clock_charges_workers_their_declared_cost() -> None:
    """Deterministic: each job costs its declared 50 ms on one simulated worker, however long
    its thread really took (it failed 1–5 % of runs under load when wall time was charged)."""
    src = MemorySource(delay=0.05)
    clock = SimClock()
    s = Streamer(src, StreamOptions(workers=1, in_flight=8), clock)
    try:
        s.request([1, 2, 3, 4], "memory", lambda k: False)
        s.drain()  # the jobs are really done; each is charged 50 ms on the one worker
        clock.advance(0.06)
        s.collect()
        assert len(s.memory) == 1
        clock.advance(0.1)
        s.collect()
        assert len(s.memory) == 3
        clock.advance(1.0)
        s.collect()
        assert len(s.memory) == 4
    finally:
        s.close()


class _SlowThreads(MemorySource):
    """Threads that take 0.3 s of real time for a fetch declared to cost 10 ms (a loaded
    machine, a starved thread)."""

    def fetch(self, key: int) -> bytes:
        time.sleep(0.3)
        return bytes([key % 256]) * self.size

    def cost(self, key: int) -> float:
        return 0.01


def test_a_simulated_clock_waits_for_local_work_but_not_the_network() -> None:
    """When a result is usable is the simulated clock's decision: a frame 20 ms later has the
    tiles declared to cost 10 ms, however slow the threads really were (a flight's statistics
    do not depend on the machine); a network job (an imagery layer) is not waited for."""
    clock = SimClock()
    s = Streamer(_SlowThreads(), StreamOptions(workers=4, in_flight=8), clock)
    try:
        s.request([1, 2, 3, 4], "memory", lambda k: False)
        clock.advance(0.02)
        t = time.perf_counter()
        s.collect()
        assert sorted(s.memory) == [1, 2, 3, 4]
        assert s.stats.sim_wait_ms > 0.0
        assert time.perf_counter() - t < 5.0
    finally:
        s.close()
    s = Streamer(_SlowThreads(), StreamOptions(), SimClock(), remote=lambda k: True)
    try:
        s.request([5, 6], "memory", lambda k: False)
        s.clock.advance(0.02)  # type: ignore[attr-defined]
        t = time.perf_counter()
        s.collect()
        assert time.perf_counter() - t < 0.2
        assert len(s.memory) == 0
        s.drain()
    finally:
        s.close()


def test_the_in_flight_limit_and_priorities() -> None:
    src = MemorySource(delay=0.02)
    s = Streamer(src, StreamOptions(in_flight=3), SimClock())
    try:
        s.request([10, 11], "memory", lambda k: False)
        s.request([20, 21, 22], "cache", lambda k: False)
        assert s.in_flight() == 3
        s.drain()
        assert sorted(src.calls) == [10, 11, 20]  # the urgent class first, then what fits
    finally:
        s.close()


def test_failures_are_counted_and_retried_with_backoff() -> None:
    src = MemorySource()
    src.failing = {7}
    clock = SimClock()
    s = Streamer(src, StreamOptions(backoff=0.5, max_backoff=2.0), clock)
    try:
        for _ in range(3):
            s.request([7, 8], "memory", lambda k: False)
            _settle(s, clock, 0.01)
        assert s.stats.failed == 1  # asked again at once: held back by the backoff
        assert 8 in s.memory
        clock.advance(0.6)
        s.request([7], "memory", lambda k: False)
        _settle(s, clock, 0.01)
        assert s.stats.failed == 2
        assert s.stats.retried == 1
        assert "500" in s.failures()[7]
        src.failing = set()
        clock.advance(1.1)
        s.request([7], "memory", lambda k: False)
        _settle(s, clock, 0.01)
        assert 7 in s.memory
        assert 7 not in s.failures()
    finally:
        s.close()


@pytest.fixture(scope="module")
def tileset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fbm_tileset(tmp_path_factory.mktemp("stream"), seed=6, west=EAST, north=NORTH)


def _line(scene: lodscape.Scene, n: int, speed: float, fps: float, w: int, h: int):
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.provider.bounds_merc
    lon0, lat = (
        float(v) for v in merc_to_lonlat(b.left + 0.05 * (b.right - b.left), (b.top + b.bottom) / 2)
    )
    lon1, _ = (float(v) for v in merc_to_lonlat(b.right - 0.05 * (b.right - b.left), 0.0))
    hi = scene.tree.height_range[1]
    span = (lon1 - lon0) * 111_320 * np.cos(np.radians(lat))
    for i in range(n):
        # back and forth along the DEM at ``speed``
        d = (speed * i / fps) % (2 * span)
        f = (d if d < span else 2 * span - d) / span
        heading = 90.0 if d < span else 270.0
        yield Camera(
            lon0 + f * (lon1 - lon0), lat, hi + 300, heading=heading, pitch=-20, width=w, height=h
        )


@pytest.mark.gl
def test_a_fast_low_flight_streams_within_its_budgets(tileset: Path) -> None:
    from lodscape.flight import fly

    budget_mb = 6.0
    opts = SceneOptions(
        gpu_budget_mb=budget_mb, stream=StreamOptions(cache_mb=budget_mb, memory_mb=budget_mb)
    )
    with lodscape.open(tileset, opts, clock=SimClock()) as scene:
        rows = fly(scene, _line(scene, 240, 300.0, 30.0, 160, 90), 30.0)
    limit = budget_mb * 2**20
    for r in rows:
        assert r["gpu_bytes"] <= limit
        assert r["memory_bytes"] <= limit
        assert r["cache_bytes"] <= limit
    after = rows[30:]
    # nothing waited for but the roots at the start, and no frame fell back far
    assert sum(r["stall_ms"] > 0 for r in after) == 0
    assert max(r["fallback_max"] for r in after) <= 1
    assert sum(r["uploaded"] for r in rows) > 20


@pytest.mark.gl
@pytest.mark.slow
def test_ten_thousand_frames_keep_memory_flat(tileset: Path) -> None:
    """Small budgets and a tiny viewport: tiles churn through every stage for 10,000 frames;
    the budgets hold every frame and the process's memory does not grow."""
    # what one frame draws must fit (the GPU stage never evicts it): 3.9 MiB at worst since
    # the build refines its finest level where it missed its budget
    budget_mb = 5.0
    opts = SceneOptions(
        gpu_budget_mb=budget_mb,
        anisotropy=1.0,
        stream=StreamOptions(cache_mb=budget_mb, memory_mb=budget_mb),
    )
    clock = SimClock()
    rss = []
    limit = budget_mb * 2**20
    with lodscape.open(tileset, opts, clock=clock) as scene:
        for i, cam in enumerate(_line(scene, 10_000, 600.0, 30.0, 32, 24)):
            scene.render(cam)
            clock.advance(1 / 30)
            assert scene.last is not None
            st = scene.last.stream
            assert st["gpu_bytes"] <= limit
            assert st["memory_bytes"] <= limit
            assert st["cache_bytes"] <= limit
            if i % 1000 == 999:
                rss.append(_rss_mb())
    # after warming up, flat: within a few MiB from the second thousand frames on
    assert max(rss[2:]) - rss[1] < 8.0, rss


def _rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.gl
def test_fly_writes_a_video_and_statistics(
    tileset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import imageio_ffmpeg

    route = tmp_path / "route.csv"
    with lodscape.open(tileset) as scene:
        cams = list(_line(scene, 2, 1000.0, 1.0, 8, 8))
    with route.open("w") as f:
        f.write("lon,lat,alt\n")
        for c in cams:
            f.write(f"{c.lon},{c.lat},{c.alt}\n")
    video, stats = tmp_path / "flight.mp4", tmp_path / "stats.csv"
    code, out, err = run_cli(
        [
            "fly",
            str(tileset),
            "--path",
            str(route),
            "--speed",
            "300",
            "--fps",
            "24",
            "--size",
            "96x64",
            "-o",
            str(video),
            "--stats",
            str(stats),
        ],
        capsys,
    )
    assert code == 0, err
    # the summary counts every frame and names frame 0 (the one that waits for the first tiles)
    summary = out.strip().splitlines()[-1]
    assert summary.startswith(f"wrote {video}: "), summary
    assert "frame 0 took " in summary
    assert "of all frames " in summary
    # (read_frames leaves its pipes to the garbage collector; counting runs ffmpeg to the end)
    frames, seconds = imageio_ffmpeg.count_frames_and_secs(str(video))
    assert seconds == pytest.approx(frames / 24, abs=0.1)
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == frames > 10
    assert {"fallback_max", "gpu_bytes", "cache_hits", "failed", "http_retries"} <= set(rows[0])
    took = float(rows[0]["frame_cpu_ms"])
    assert f"frame 0 took {took:.0f} ms" in summary
    for args, message in [
        (["--path", str(tmp_path / "nope.csv")], "no such file"),
        (["--orbit", "1,2,3"], "--orbit"),
        (["--line", "0,0,0,0,500"], "no length"),
        (["--path", str(route), "--size", "97x64"], "even"),
        ([], "one of --path"),
    ]:
        out_mp4 = tmp_path / "bad.mp4"
        code, _, err = run_cli(["fly", str(tileset), "-o", str(out_mp4), "-q", *args], capsys)
        assert code == 2, (args, err)
        assert message in err
        assert err.count("\n") == 1
        assert not out_mp4.exists()
