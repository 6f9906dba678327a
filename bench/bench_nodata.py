"""What telling the truth about the data costs and gives (issue 19), in one process.

1. A 513² fBm DEM with a nodata hole (a fifth of it) built with each ``--fill``: tiles, stored
   triangles, bytes, build seconds; and, rendered from above the hole, the share of the hole's
   pixels that show invented ground.
2. A coarse (0.03°, ~3 km), rough topo-bathymetric DEM: the planned finest level's worst error
   against its budget, and the level the build added below it.
3. What the ellipsoid drawn behind the terrain costs a frame.

    python bench/bench_nodata.py [--work /tmp/bn]
"""

from __future__ import annotations

import argparse
import math
import sqlite3
import sys
import time
from contextlib import closing
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
import lodscape
from _synthetic import fbm_heights, write_dem
from lodscape import Camera, SceneOptions
from lodscape.build import BuildOptions, build
from lodscape.build.tiles import level_budget
from lodscape.store.quantized_mesh import decode

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0
HOLE = (slice(150, 380), slice(140, 370))
SKY = (0.25, 0.5, 0.75)


def _hole_camera() -> Camera:
    from pyproj import Transformer

    rows, cols = HOLE
    x = EAST + (cols.start + cols.stop) / 2 * RES
    y = NORTH - (rows.start + rows.stop) / 2 * RES
    lon, lat = Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True).transform(x, y)
    return Camera(lon, lat, 6000.0, pitch=-90.0, fov_y=40.0, width=256, height=256)


def holes(work: Path) -> None:
    h = fbm_heights(513, seed=21)
    h[HOLE] = -9999.0
    dem = write_dem(
        str(work / "hole.tif"), h, crs="EPSG:32617", west=EAST, north=NORTH, res=RES, nodata=-9999
    )
    cam = _hole_camera()
    print("## a 513² DEM with a nodata hole of 230×230 px (20 % of it)")
    print("| fill | tiles | triangles | MiB | build s | hole px drawn as ground |")
    print("|---|---|---|---|---|---|")
    for fill in ("none", "nearest", "ellipsoid"):
        out = work / f"hole-{fill}.lods"
        out.unlink(missing_ok=True)
        t0 = time.perf_counter()
        build([dem], out, BuildOptions(fill=fill))
        seconds = time.perf_counter() - t0
        with closing(sqlite3.connect(out)) as db:
            rows = db.execute("SELECT data FROM terrain").fetchall()
        tris = sum(decode(bytes(r[0])).triangles.shape[0] for r in rows)
        with lodscape.open(out, SceneOptions(background=SKY, ellipsoid=False)) as scene:
            rgb, _ = scene.render(cam)
        sky = np.all(np.abs(rgb.astype(int) - np.array(SKY) * 255) <= 1, axis=2)
        print(
            f"| {fill} | {len(rows)} | {tris:,} | {out.stat().st_size / 2**20:.2f} | "
            f"{seconds:.1f} | {100 * (1 - sky.mean()):.1f} % |"
        )
    for fill in ("none", "nearest", "ellipsoid"):
        with lodscape.open(dem, SceneOptions(background=SKY, ellipsoid=False), fill=fill) as scene:
            rgb, depth = scene.render(cam)
        sky = np.all(np.abs(rgb.astype(int) - np.array(SKY) * 255) <= 1, axis=2)
        seen = depth[np.isfinite(depth)]
        distance = float(np.median(seen)) if seen.size else math.inf
        print(
            f"render of the raw DEM, --fill {fill}: {100 * (1 - sky.mean()):.1f} % of the hole's "
            f"pixels drawn, median distance {distance:.0f} m"
        )


def finest(work: Path) -> None:
    h = (fbm_heights(129, seed=3, relief=6000.0) - 3300.0).astype(np.float32)
    dem = write_dem(str(work / "coarse.tif"), h, crs="EPSG:4326", west=-30.0, north=45.0, res=0.03)
    out = work / "coarse.lods"
    out.unlink(missing_ok=True)
    report = build([dem], out)
    _, tex, zmax = report.levels
    planned = tex + 2
    print("\n## a coarse (0.03°), rough topo-bathymetric DEM (-3,000..3,000 m)")
    print("| level | tiles | worst error m | its budget m | tiles over budget |")
    print("|---|---|---|---|---|")
    with closing(sqlite3.connect(out)) as db:
        for z in range(planned, zmax + 1):
            rows = db.execute("SELECT x, y, error FROM terrain WHERE z = ?", (z,)).fetchall()
            # the default budget: one of the level's 256 texels a tile
            budgets = [float(level_budget(1.0, 256, z, y)) for _, y, _ in rows]
            ratio = [(e / b, e, b) for (_, _, e), b in zip(rows, budgets, strict=True)]
            worst = max(ratio)
            over = sum(1 for r in ratio if r[0] > 1.0 + 1e-9)
            tag = " (planned finest)" if z == planned else " (added)"
            print(f"| {z}{tag} | {len(rows)} | {worst[1]:.0f} | {worst[2]:.0f} | {over} |")


def ellipsoid_cost(repeat: int) -> None:
    """The ellipsoid behind the terrain: one full-screen pass, no depth written."""
    from lodscape.data import sample_dem_path

    print("\n## the ellipsoid pass: the sample DEM's overview, 1280×720, frames after warm-up")
    print("| ellipsoid | median frame ms | median draw ms |")
    print("|---|---|---|")
    frames: dict[bool, list[float]] = {True: [], False: []}
    draws: dict[bool, list[float]] = {True: [], False: []}
    scenes = {e: lodscape.open(sample_dem_path(), SceneOptions(ellipsoid=e)) for e in (True, False)}
    try:
        cams = {e: s.overview_camera(1280, 720, 60.0) for e, s in scenes.items()}
        for e, s in scenes.items():
            s.render(cams[e])  # loads and uploads
        for _ in range(repeat):
            for e, s in scenes.items():  # interleaved: the machine's noise hits both alike
                t0 = time.perf_counter()
                s.render(cams[e])
                frames[e].append((time.perf_counter() - t0) * 1e3)
                assert s.last is not None
                draws[e].append(float(s.last.as_dict()["draw_ms"]))
    finally:
        for s in scenes.values():
            s.close()
    for e in (False, True):
        label = "on" if e else "off"
        print(f"| {label} | {np.median(frames[e]):.1f} | {np.median(draws[e]):.1f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_nodata"))
    ap.add_argument("--repeat", type=int, default=15)
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    holes(args.work)
    finest(args.work)
    ellipsoid_cost(args.repeat)


if __name__ == "__main__":
    main()
