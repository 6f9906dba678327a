"""Spine benchmark: a 4097×4097 DEM at 1280×720 with the default 2 px bound.

Prints, per view and as medians:
- triangles drawn as a share of the full-resolution mesh (2·4096² triangles; goal ≤ 3 %), and
  the error measured on the frame's pixels (``bench_peers``' measure: each drawn point and the
  DEM's point at the same place, both projected; 99.9th percentile / largest, pixels);
- selection time, vectorised against the naive recursive per-tile traversal of the same tree
  (``lodscape.lod._reference``), measured in this same process (goal ≥ 10× faster);
- headless frame time (EGL) once every tile is resident (a software rasteriser gets no
  anisotropic filtering, whatever the option), and the first frame with its loading.

The DEM is generated here (spectral fBm, Hurst 0.8, seed 0, 5 m spacing, UTM 17N): a synthetic
stand-in of realistic roughness, written as a real GeoTIFF and read back through rasterio.

    python bench/bench_spine.py [--size 4097] [--repeat 15]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from rasterio.transform import Affine

import lodscape
from lodscape import Camera
from lodscape.lod._reference import select_reference
from lodscape.lod.select import select


def spectral_fbm(n: int, hurst: float = 0.8, seed: int = 0, relief: float = 1200.0) -> np.ndarray:
    """Fractional Brownian surface by spectral synthesis: amplitude ∝ f^-(H+1)."""
    rng = np.random.default_rng(seed)
    fx = np.fft.fftfreq(n)[None, :]
    fy = np.fft.fftfreq(n)[:, None]
    f = np.hypot(fx, fy)
    f[0, 0] = 1.0
    amp = f ** (-(hurst + 1.0))
    amp[0, 0] = 0.0
    phase = rng.uniform(0, 2 * np.pi, (n, n))
    z = np.real(np.fft.ifft2(amp * np.exp(1j * phase)))
    z -= z.min()
    return (200.0 + relief * z / z.max()).astype(np.float32)


def write(path: Path, n: int) -> None:
    heights = spectral_fbm(n)
    profile = {
        "driver": "GTiff",
        "height": n,
        "width": n,
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:32617",
        "transform": Affine(5.0, 0.0, 700000.0, 0.0, -5.0, 4070000.0),
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
        "compress": "deflate",
    }
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(heights, 1)


def views(scene: lodscape.Scene) -> dict[str, Camera]:
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.source.bounds_merc
    lon, lat = (float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2))
    hi = scene.tree.height_range[1]
    kw = {"width": 1280, "height": 720, "fov_y": 60.0}
    return {
        "overview": scene.overview_camera(1280, 720),
        "oblique": Camera(lon, lat - 0.06, hi + 2500.0, heading=5, pitch=-30, **kw),  # type: ignore[arg-type]
        "low": Camera(lon - 0.03, lat - 0.05, hi + 300.0, heading=30, pitch=-12, **kw),  # type: ignore[arg-type]
        "down": Camera(lon, lat, hi + 1500.0, pitch=-90, **kw),  # type: ignore[arg-type]
    }


def timed(fn, repeat: int) -> float:  # type: ignore[no-untyped-def]
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    from bench_peers import _lodscape_error, ground_depth

    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=4097)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument(
        "--meshes", choices=("auto", "tin", "grid"), default="auto",
        help="SceneOptions.meshes (auto: a picture's TINs); grid: the regular grids",
    )  # fmt: skip
    args = ap.parse_args()
    n = args.size
    full = 2 * (n - 1) ** 2
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fbm.tif"
        t = time.perf_counter()
        write(path, n)
        heights = spectral_fbm(n).astype(np.float64)
        print(f"DEM {n}x{n} written in {time.perf_counter() - t:.1f} s")
        t = time.perf_counter()
        scene = lodscape.open(path, lodscape.SceneOptions(meshes=args.meshes))
        print(
            f"tile tree (levels {scene.tree.zmin}..{scene.tree.zmax}) in "
            f"{time.perf_counter() - t:.1f} s"
        )
        tree = scene.tree
        if hasattr(tree, "tail"):  # a lazy tree: the detail its chunks do not read, bounded
            tails = {z: tree.tail(z) for z in range(tree.zmin, tree.truth) if tree.tail(z) > 0}
            print("tail below a chunk's deepest level, m: " + ", ".join(
                f"level {z} {v:.1f}" for z, v in tails.items()))  # fmt: skip
            if hasattr(tree, "tails"):  # a tile's own: base + slope × its last step, at most that
                print("a tile's tail, m: " + ", ".join(
                    f"level {z} {t.base:.2f} + {t.slope:.2f}·d" for z in tails
                    for t in [tree.tails(z)]))  # fmt: skip
        rows = []
        for name, cam in views(scene).items():
            c = scene.prepare(cam)
            sel = select(scene.options.select, c, scene.tree)
            t_vec = timed(lambda c=c: select(scene.options.select, c, scene.tree), args.repeat)
            t_ref = timed(
                lambda c=c: select_reference(scene.options.select, c, scene.tree),
                max(3, args.repeat // 5),
            )
            t = time.perf_counter()
            scene.render(cam)
            first = time.perf_counter() - t
            depth = ground_depth(scene, cam)
            got = _lodscape_error({"dem": str(path)}, heights, scene.prepare(cam), depth)
            t_frame = timed(lambda cam=cam: scene.render(cam), max(3, args.repeat // 3))
            # as drawn (a TIN's count is known once it is meshed), skirts included
            tris = int(scene.frame_stats()["triangles"])
            share = tris / full
            rows.append((name, sel.count, tris, share, t_vec, t_ref, first, t_frame))
            print(
                f"{name:>9}: tiles {sel.count:4d}  triangles {tris:9,d} "
                f"({100 * share:.2f} % of {full:,d})  max SSE {sel.max_sse:.2f} px  "
                f"measured {got['pixel_sse_p999']:.2f}/{got['pixel_sse_max']:.2f} px  "
                f"select {1e3 * t_vec:.2f} ms vs naive {1e3 * t_ref:.1f} ms "
                f"(×{t_ref / t_vec:.0f})  first frame {first:.2f} s  frame {1e3 * t_frame:.0f} ms"
            )
        scene.close()
    med = statistics.median
    print(
        f"median triangle share {100 * med(r[3] for r in rows):.2f} % "
        f"(max {100 * max(r[3] for r in rows):.2f} %), goal <= 3 %"
    )
    print(
        f"median selection speed-up ×{med(r[5] / r[4] for r in rows):.0f} "
        f"(vectorised {1e3 * med(r[4] for r in rows):.2f} ms), goal >= 10×"
    )
    print(
        f"median headless frame {1e3 * med(r[7] for r in rows):.0f} ms at 1280x720 "
        f"(first frame with loading {med(r[6] for r in rows):.2f} s)"
    )


if __name__ == "__main__":
    main()
