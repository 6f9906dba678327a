"""Peak memory of opening and rendering a raw DEM, by its size (issue 24).

DEMs of 1025², 2049², 4097² (GeoTIFFs, no overviews) and 16385² (a VRT mosaic of 16×16
copies of a seamless 1025² tile) of spectral fBm at 2 m: each opened and its overview
rendered at 320×200 in a fresh process, twice (the first run of a large raster builds its
sidecar overviews in the cache, the second finds them). Prints the peak RSS and the time to
open (tile tree included) of each run, and the peak's growth per ×4 data.

    python bench/bench_raw_memory.py [--sizes 1025,2049,4097,16385]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import PEAK_PROBE, mosaic_dem, periodic_fbm, write_dem


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="1025,2049,4097,16385")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        env = {**os.environ, "LODSCAPE_CACHE": str(folder / "cache")}
        peaks = []
        for n in sizes:
            if n > 4097:
                path = mosaic_dem(folder, (n - 1) // 1024)
            else:
                path = folder / f"dem{n}.tif"
                write_dem(str(path), periodic_fbm(n - 1), crs="EPSG:32617", west=500000.0,
                          north=4000000.0, res=2.0)  # fmt: skip
            runs = []
            for _ in range(2):
                proc = subprocess.run(
                    [sys.executable, "-c", PEAK_PROBE, str(path)],
                    capture_output=True, text=True, env=env, check=True,
                )  # fmt: skip
                runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
            peaks.append(max(r["peak_mb"] for r in runs))
            print(
                f"{n}²: peak RSS {runs[0]['peak_mb']:.0f} / {runs[1]['peak_mb']:.0f} MB, open "
                f"{runs[0]['open_s']:.1f} / {runs[1]['open_s']:.1f} s, render "
                f"{runs[0]['render_s']:.1f} / {runs[1]['render_s']:.1f} s (first / second run)"
            )
        for a, b, na, nb in zip(peaks, peaks[1:], sizes, sizes[1:], strict=False):
            growth = (b / a) ** (1.0 / max(np.log((nb - 1) ** 2 / (na - 1) ** 2) / np.log(4), 1))
            print(f"{na}² → {nb}²: peak ×{b / a:.2f} (×{growth:.2f} per ×4 data)")


if __name__ == "__main__":
    main()
