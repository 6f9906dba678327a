"""Tileset builds with each mesher (``--mesher rtin|greedy``): size, build time, frame time.

DEMs: the embedded sample (Jacksboro, 403×344, 90 m) and a spectral fBm (Hurst 0.8, 5 m, UTM
17N) of ``--size``² samples. Each is built ``--builds`` times per mesher (alternating, from an
empty file, the default thread pool) and the median build time kept; then, per tileset, the
terrain's stored bytes (gzipped quantized-mesh) and triangles, and the median of 9 frames
(1280×720, colour and distance read back, after the tiles are resident) from three views of the
data, with the triangles drawn and the largest screen-space error.

    python bench/bench_greedy.py [--size 1025] [--builds 3]
"""

from __future__ import annotations

import argparse
import sqlite3
import statistics
import tempfile
import time
from contextlib import closing
from pathlib import Path

import lodscape
from bench_spine import write
from lodscape.build import BuildOptions, build
from lodscape.data import sample_dem_path
from lodscape.store.quantized_mesh import decode


def stored(path: Path) -> tuple[int, int]:
    """Terrain bytes (gzipped quantized-mesh) and triangles."""
    with closing(sqlite3.connect(path)) as db:
        rows = db.execute("SELECT data FROM terrain").fetchall()
    nbytes = sum(len(d) for (d,) in rows)
    tris = sum(len(decode(bytes(d)).triangles) for (d,) in rows)
    return nbytes, tris


def frames(path: Path) -> list[tuple[str, float, int, float]]:
    out = []
    with lodscape.open(path, lodscape.SceneOptions(anisotropy=1.0)) as scene:
        ov = scene.overview_camera(1280, 720)
        views = {
            "overview": ov,
            "oblique": ov.moved(alt=ov.alt * 0.4, pitch=-25.0),
            "low": ov.moved(alt=ov.alt * 0.15, pitch=-12.0),
        }
        for name, cam in views.items():
            for _ in range(3):
                scene.render(cam)
            ts = []
            for _ in range(9):
                t = time.perf_counter()
                scene.render(cam)
                ts.append(time.perf_counter() - t)
            st = scene.frame_stats()
            out.append((name, statistics.median(ts) * 1e3, int(st["triangles"]), st["max_sse_px"]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=1025)
    ap.add_argument("--builds", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        fbm = tmp / "fbm.tif"
        write(fbm, args.size)
        for label, dem in (("sample", Path(sample_dem_path())), (f"fbm{args.size}", fbm)):
            times: dict[str, list[float]] = {"rtin": [], "greedy": []}
            for i in range(args.builds):
                for mesher in times:
                    out = tmp / f"{label}-{mesher}-{i}.lods"
                    s = time.perf_counter()
                    build([dem], out, BuildOptions(mesher=mesher))
                    times[mesher].append(time.perf_counter() - s)
            print(f"\n## {label}")
            got = {}
            for mesher in times:
                path = tmp / f"{label}-{mesher}-0.lods"
                nbytes, tris = stored(path)
                got[mesher] = (statistics.median(times[mesher]), nbytes, tris)
                print(
                    f"{mesher:>7}: build {got[mesher][0]:.2f} s (median of {args.builds}), "
                    f"terrain {nbytes / 1e6:.2f} MB, {tris:,d} triangles stored"
                )
                for name, ms, drawn, sse in frames(path):
                    print(f"{name:>18}: {ms:6.1f} ms, {drawn:8,d} triangles, max SSE {sse:.2f} px")
            (tr, br, nr), (tg, bg, ng) = got["rtin"], got["greedy"]
            print(
                f"greedy / rtin: triangles ×{ng / nr:.2f}, bytes ×{bg / br:.2f}, "
                f"build time ×{tg / tr:.2f}"
            )


if __name__ == "__main__":
    main()
