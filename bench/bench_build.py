"""Build benchmark: tileset build throughput on 1 and 2 Dask workers (and threads, for
reference), and the tileset's size against the DEM's.

The DEM is a spectral fBm surface (Hurst 0.8, 1,200 m of relief, 5 m spacing, UTM 17N) of
``--size``² samples, written as a real tiled GeoTIFF. Each build starts from an empty file; the
Dask builds run on a LocalCluster of single-threaded worker processes started beforehand (its
start-up is not counted). Every build must give the same tiles byte for byte.

    python bench/bench_build.py [--size 2049]
"""

from __future__ import annotations

import argparse
import sqlite3
import tempfile
import time
from contextlib import closing
from pathlib import Path

import numpy as np

from bench_spine import write
from lodscape.build import build
from lodscape.build.executors import BuildExecutor, DaskExecutor, PoolExecutor


def tiles(path: Path) -> dict[tuple[int, int, int], bytes]:
    with closing(sqlite3.connect(path)) as db:
        return {
            (z, x, y): bytes(d) for z, x, y, d in db.execute("SELECT z, x, y, data FROM terrain")
        }


def timed_build(dem: Path, out: Path, executor: BuildExecutor) -> tuple[float, int]:
    t = time.perf_counter()
    report = build([dem], out, executor=executor)
    return time.perf_counter() - t, report.planned


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=2049)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        dem = folder / "fbm.tif"
        write(dem, args.size)
        # warm the numba cache and the source code paths once
        build([dem], folder / "warm.lods", executor=PoolExecutor(1, processes=False))
        runs: dict[str, tuple[float, int, Path]] = {}
        for label, make in [
            ("threads ×1", lambda: PoolExecutor(1, processes=False)),
            ("threads ×2", lambda: PoolExecutor(2, processes=False)),
            ("dask ×1", lambda: DaskExecutor(None, workers=1)),
            ("dask ×2", lambda: DaskExecutor(None, workers=2)),
        ]:
            executor = make()
            out = folder / f"{label.replace(' ', '').replace('×', 'x')}.lods"
            try:
                seconds, n = timed_build(dem, out, executor)
            finally:
                executor.close()
            runs[label] = (seconds, n, out)
            print(f"{label:>11}: {n} tiles in {seconds:6.1f} s = {n / seconds:6.1f} tiles/s")
        reference = tiles(runs["threads ×1"][2])
        same = all(tiles(out) == reference for _, _, out in runs.values())
        d1, d2 = runs["dask ×1"][0], runs["dask ×2"][0]
        t1, t2 = runs["threads ×1"][0], runs["threads ×2"][0]
        print(f"dask speed-up with 2 workers: ×{d1 / d2:.2f} (goal >= 1.8); threads ×{t1 / t2:.2f}")
        print(f"every executor made the same tiles byte for byte: {same}")
        size = runs["dask ×2"][2].stat().st_size
        raw = args.size * args.size * np.dtype(np.float32).itemsize
        print(
            f"tileset {size / 2**20:.1f} MiB (terrain + imagery) against the DEM's "
            f"{raw / 2**20:.1f} MiB of float32 samples (×{size / raw:.2f}) and its "
            f"{dem.stat().st_size / 2**20:.1f} MiB deflated GeoTIFF"
        )
        with closing(sqlite3.connect(runs["dask ×2"][2])) as db:
            (terrain,) = db.execute("SELECT SUM(LENGTH(data)) FROM terrain").fetchone()
            (imagery,) = db.execute("SELECT SUM(LENGTH(tile_data)) FROM tiles").fetchone()
        print(f"of which terrain {terrain / 2**20:.1f} MiB, imagery {imagery / 2**20:.1f} MiB")


if __name__ == "__main__":
    main()
