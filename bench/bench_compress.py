"""Block-compressed textures (issue 22, paper 001) on the embedded sample: the overview drawn
with and without ``compress_textures`` (GPU bytes resident, frame time, the picture's PSNR
against the uncompressed one), and what compressing one 256² RGB tile with its mip chain costs
on one core (numpy, as a worker does it). The city's atlas and frame times are in
``bench/bench_city.py``.

    python bench/bench_compress.py [--size 640x360] [--frames 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import lodscape
from lodscape.data import sample_dem_path
from lodscape.imagery.compress import compress


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--frames", type=int, default=7)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    got = {}
    for on in (False, True):
        with lodscape.open(sample_dem_path(), lodscape.SceneOptions(compress_textures=on)) as s:
            cam = s.overview_camera(w, h)
            rgb, _ = s.render(cam)
            times = []
            for _ in range(args.frames):
                t = time.perf_counter()
                s.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
            assert s.last is not None
            got[on] = (rgb, s.last.resident_mb, statistics.median(times))
    (a, mb_a, ms_a), (b, mb_b, ms_b) = got[False], got[True]
    mse = float(((a.astype(float) - b.astype(float)) ** 2).mean())
    psnr = 10 * np.log10(255.0**2 / max(mse, 1e-9))
    print(
        f"the sample's overview at {w}×{h}: GPU resident {mb_b:.2f} MiB compressed, "
        f"{mb_a:.2f} MiB not (×{mb_b / mb_a:.2f}); frame {ms_b:.1f} ms vs {ms_a:.1f} ms "
        f"(×{ms_a / ms_b:.2f}); the picture {psnr:.1f} dB PSNR from the uncompressed one"
    )
    tile = np.ascontiguousarray(a[:256, :256]) if min(w, h) >= 256 else np.resize(a, (256, 256, 3))
    times = []
    for _ in range(9):
        t = time.perf_counter()
        c = compress(tile)
        times.append((time.perf_counter() - t) * 1e3)
    print(
        f"one 256² RGB tile and its mip chain into BC1: {statistics.median(times):.1f} ms "
        f"(median of 9), {c.nbytes:,} bytes against {tile.nbytes * 4 // 3:,} uncompressed"
    )


if __name__ == "__main__":
    main()
