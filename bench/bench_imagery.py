"""Imagery layers benchmark (issue 18): what the user's own orthophoto costs a frame, and whether
it is drawn at its own resolution.

Data, made here: a 257² fBm DEM (90 m, UTM 16N, 23 km across) and an orthophoto 8× finer
(11.25 m, 2056² RGB, a texture of 2-pixel cells the DEM's own level cannot show).

1. Frames, one-shot renders at 640×360 from three heights above the middle (top down) and one
   oblique view, with the tint alone, one layer (the orthophoto) and three layers (the
   orthophoto under two half-transparent copies): median milliseconds of a frame whose
   resources are all resident (the draw cost), and the drawn layer's pixels per texel.
2. A flight (paper 004's streaming, simulated 30 frames/s) 120 m above the ground at 100 m/s
   across the DEM with the orthophoto: frames falling back more than one terrain level, the
   layer's (tile, layer) fallbacks, frames over their 33.3 ms; against the tint alone.

    python bench/bench_imagery.py [--work DIR] [--repeat 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import lodscape
from lodscape import Camera, SceneOptions
from lodscape.flight import fly
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.stream import SimClock, StreamOptions

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import fbm_heights, write_dem, write_ortho

DEM_RES = 90.0
N = 257
WEST, NORTH = 500_000.0, 4_000_000.0


def data(work: Path) -> tuple[str, str, str]:
    dem = work / "dem.tif"
    ortho = work / "ortho.tif"
    veil = work / "veil.tif"
    if not dem.exists():
        write_dem(
            str(dem),
            fbm_heights(N, seed=11, relief=600.0),
            crs="EPSG:32616",
            west=WEST,
            north=NORTH,
            res=DEM_RES,
        )
    n = (N - 1) * 8
    if not ortho.exists():
        rng = np.random.default_rng(3)
        cells = rng.integers(40, 230, size=(n // 2, n // 2, 3), dtype=np.uint8)
        rgb = np.repeat(np.repeat(cells, 2, axis=0), 2, axis=1)
        write_ortho(str(ortho), rgb, crs="EPSG:32616", west=WEST, north=NORTH, res=DEM_RES / 8)
    if not veil.exists():
        rgb = np.full((n // 4, n // 4, 3), (250, 240, 200), np.uint8)
        alpha = np.full((n // 4, n // 4), 96, np.uint8)
        write_ortho(
            str(veil), rgb, crs="EPSG:32616", west=WEST, north=NORTH, res=DEM_RES / 2, alpha=alpha
        )
    return str(dem), str(ortho), str(veil)


def views(scene: lodscape.Scene) -> dict[str, Camera]:
    b = scene.provider.bounds_merc
    lon, lat = (float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2))
    g = scene.ground_height(lon, lat) or 0.0
    out = {
        f"down {h} m": Camera(lon, lat, g + h, pitch=-90, width=640, height=360)
        for h in (300, 1500, 6000)
    }
    out["oblique"] = Camera(lon, lat - 0.03, g + 800, pitch=-25, width=640, height=360)
    return out


def frames(dem: str, imagery: list[str], repeat: int) -> dict[str, tuple[float, float, float]]:
    """Per view: median ms of a resident frame, and the top layer's px/texel range."""
    out = {}
    with lodscape.open(dem, SceneOptions(anisotropy=1.0), imagery=imagery or None) as scene:
        for name, cam in views(scene).items():
            scene.render(cam)  # loads
            times = []
            for _ in range(repeat):
                t = time.perf_counter()
                scene.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
            sel = scene.view.previous
            assert sel is not None
            if imagery:
                d = sel.layer_px_per_texel(1)
                lo, hi = float(np.nanmin(d)), float(np.nanmax(d))
            else:
                lo, hi = sel.px_per_texel_range
            out[name] = (statistics.median(times), lo, hi)
    return out


def flight(dem: str, imagery: list[str], seconds: float) -> dict[str, float]:
    opts = SceneOptions(anisotropy=1.0, stream=StreamOptions())
    with lodscape.open(dem, opts, clock=SimClock(), imagery=imagery or None) as scene:
        b = scene.provider.bounds_merc
        lat = float(merc_to_lonlat(0.0, (b.top + b.bottom) / 2)[1])
        w = float(merc_to_lonlat(b.left, 0.0)[0])
        e = float(merc_to_lonlat(b.right, 0.0)[0])
        n = int(seconds * 30)
        step = 100.0 / 30 / (111_320 * math.cos(math.radians(lat)))
        start = w + 0.1 * (e - w)
        cams = []
        for i in range(n):
            lon = start + i * step
            g = scene.ground_height(lon, lat) or 0.0
            cams.append(Camera(lon, lat, g + 120.0, heading=90, pitch=-20, width=640, height=360))
        rows = fly(scene, iter(cams), 30.0)
    rows = rows[30:]
    return {
        "frames": len(rows),
        "fallback>1": sum(r["fallback_max"] > 1 for r in rows),
        "layer_fallbacks": sum(r["layer_fallbacks"] for r in rows),
        "over_budget": sum(r["over_budget"] for r in rows),
        "cpu_ms_median": statistics.median(r["frame_cpu_ms"] for r in rows),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=12.0)
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="lodscape-imagery-"))
    work.mkdir(parents=True, exist_ok=True)
    dem, ortho, veil = data(work)
    runs = {"tint": [], "1 layer": [ortho], "3 layers": [ortho, veil, veil]}
    results = {name: frames(dem, layers, args.repeat) for name, layers in runs.items()}
    print("frame ms (median of resident frames) and the top layer's px/texel, 640x360")
    print(f"{'view':>14} | " + " | ".join(f"{n:>22}" for n in runs))
    for view in results["tint"]:
        cells = []
        for name in runs:
            ms, lo, hi = results[name][view]
            cells.append(f"{ms:7.1f} ms {lo:5.2f}..{hi:5.2f}")
        ratio = results["1 layer"][view][0] / results["tint"][view][0]
        ratio3 = results["3 layers"][view][0] / results["tint"][view][0]
        print(
            f"{view:>14} | "
            + " | ".join(f"{c:>22}" for c in cells)
            + f"  (x{ratio:.2f}, x{ratio3:.2f} the tint)"
        )
    print()
    print(f"flight, {args.seconds:g} s at 100 m/s, 120 m above the ground (after the first second)")
    for name, layers in (("tint", []), ("orthophoto", [ortho])):
        print(f"{name:>12}: {flight(dem, layers, args.seconds)}")


if __name__ == "__main__":
    main()
