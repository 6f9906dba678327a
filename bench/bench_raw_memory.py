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
from html import escape
from pathlib import Path

import numpy as np

_PROBE = """
import json, sys, time
import lodscape

def hwm():
    # this process's own peak (VmHWM): getrusage's maxrss keeps the parent's across exec
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

t = time.perf_counter()
scene = lodscape.open(sys.argv[1])
opened = time.perf_counter() - t
t = time.perf_counter()
scene.render(scene.overview_camera(320, 200))
print(json.dumps({"peak_mb": hwm(),
                  "open_s": opened, "render_s": time.perf_counter() - t}))
"""


def periodic_fbm(n: int, seed: int = 3, relief: float = 800.0) -> np.ndarray:
    """Spectral fBm of period n (Hurst 0.8), n + 1 samples a side (the first row repeated)."""
    rng = np.random.default_rng(seed)
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    k[0, 0] = 1.0
    spectrum = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * k**-1.8
    spectrum[0, 0] = 0.0
    h = np.fft.ifft2(spectrum).real
    h = (h - h.min()) / (h.max() - h.min()) * relief + 200.0
    return np.pad(h, ((0, 1), (0, 1)), mode="wrap").astype(np.float32)


def write_tif(path: Path, h: np.ndarray) -> None:
    import rasterio
    from rasterio.transform import from_origin

    with rasterio.open(
        path, "w", driver="GTiff", width=h.shape[1], height=h.shape[0], count=1,
        dtype="float32", crs="EPSG:32617", transform=from_origin(500000.0, 4000000.0, 2.0, 2.0),
        tiled=True, blockxsize=256, blockysize=256, compress="deflate",
    ) as ds:  # fmt: skip
        ds.write(h, 1)


def mosaic(folder: Path, copies: int, tile: int = 1024) -> Path:
    base = folder / "tile.tif"
    write_tif(base, periodic_fbm(tile))
    import rasterio

    with rasterio.open(base) as ds:
        wkt = ds.crs.to_wkt()
    size = tile * copies + 1
    sources = "".join(
        f'<SimpleSource><SourceFilename relativeToVRT="1">tile.tif</SourceFilename>'
        f'<SourceBand>1</SourceBand><SrcRect xOff="0" yOff="0" xSize="{tile + 1}" '
        f'ySize="{tile + 1}"/><DstRect xOff="{i * tile}" yOff="{j * tile}" '
        f'xSize="{tile + 1}" ySize="{tile + 1}"/></SimpleSource>'
        for j in range(copies)
        for i in range(copies)
    )
    vrt = folder / f"mosaic{size}.vrt"
    vrt.write_text(
        f'<VRTDataset rasterXSize="{size}" rasterYSize="{size}"><SRS>{escape(wkt)}</SRS>'
        "<GeoTransform>500000.0, 2.0, 0.0, 4000000.0, 0.0, -2.0</GeoTransform>"
        f'<VRTRasterBand dataType="Float32" band="1">{sources}</VRTRasterBand></VRTDataset>'
    )
    return vrt


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
                path = mosaic(folder, (n - 1) // 1024)
            else:
                path = folder / f"dem{n}.tif"
                write_tif(path, periodic_fbm(n - 1))
            runs = []
            for _ in range(2):
                proc = subprocess.run(
                    [sys.executable, "-c", _PROBE, str(path)],
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
