"""Memory over a long flight: the process's RSS every 500 frames, and where a frame's bytes go.

    python bench/bench_memory.py [--loops 3] [--radius 1000] [--budget-mb 16]

A 1025² fBm DEM (10 m, UTM 17N) flown round an orbit ``--loops`` times at 100 m/s, 30 fps,
160×100, every stage at ``--budget-mb`` (``lodscape.flight.fly`` on a simulated clock, no video).
The first loop sees new ground every frame (tiles made, GDAL's blocks read, allocator pools
grown); the loops after it revisit the same ground, so the process must be flat there. Printed:
RSS per 500 frames, the growth per 1,000 frames over the first loop and over the rest, and, in
the same process, the bytes a frame's statistics row costs as a dict (as flights kept them
before) and in ``FlightRows``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import lodscape
from _synthetic import fbm_heights, write_dem
from lodscape import SceneOptions, flight
from lodscape.stream import SimClock, StreamOptions


def _rss_mb() -> float:
    with open(f"/proc/{os.getpid()}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _dict_row_bytes() -> float:
    """Bytes one statistics row takes as a dict of its columns (the dict and its floats)."""
    import tracemalloc

    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    rows = [{c: float(i) + 0.5 for c in flight.STAT_COLUMNS} for i in range(1000)]
    used = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    del rows
    return used / 1000


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--loops", type=int, default=3)
    ap.add_argument("--radius", type=float, default=1000.0)
    ap.add_argument("--budget-mb", type=float, default=16.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        dem = write_dem(
            str(Path(tmp) / "dem.tif"),
            fbm_heights(1025, seed=6),
            crs="EPSG:32617",
            west=700000.0,
            north=4060000.0,
            res=10.0,
        )
        b = args.budget_mb
        opts = SceneOptions(gpu_budget_mb=b, stream=StreamOptions(cache_mb=b, memory_mb=b))
        with lodscape.open(dem, opts, clock=SimClock()) as scene:
            lon, lat = scene.overview_camera(160, 100).lon, scene.overview_camera(160, 100).lat
            top = scene.tree.height_range[1]
            route = flight.orbit_route(lon, lat, args.radius, top + 300.0, 100.0)
            loop = list(flight.cameras(route, 30.0, 160, 100))
            rss: list[tuple[int, float]] = []

            def on_frame(i: int) -> None:
                if i % 500 == 499:
                    rss.append((i + 1, _rss_mb()))
                    print(f"frame {i + 1:>6,}: RSS {rss[-1][1]:.1f} MB", flush=True)

            rows = flight.fly(scene, iter(loop * args.loops), 30.0, on_frame=on_frame)
    n = len(loop)
    first = [r for f, r in rss if f <= n]
    rest = [(f, r) for f, r in rss if f > n]
    print(f"{len(rows):,} frames, {args.loops} loops of {n:,} frames")
    if len(first) > 1:
        grew = (first[-1] - first[0]) / (len(first) - 1) * 2
        print(f"first loop (new ground): {grew:+.2f} MB per 1,000 frames")
    if len(rest) > 1:
        slope = (rest[-1][1] - rest[0][1]) / (rest[-1][0] - rest[0][0]) * 1000
        print(f"later loops (the same ground): {slope:+.2f} MB per 1,000 frames")
    row = rows._data.nbytes / len(rows._data)
    print(f"a statistics row: {_dict_row_bytes():,.0f} bytes as a dict, {row:.0f} in FlightRows")


if __name__ == "__main__":
    main()
