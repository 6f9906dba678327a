"""What a remote COG's first picture fetches (issue 36): a COG served by a loopback HTTP server
that answers byte ranges (``tests/_tileserver.RangeServer``), rendered by ``lodscape render URL``
with an empty cache; prints the share of the file the server sent, its requests and the time.

COGs of spectral fBm at 2 m (UTM 17N, float32, deflate, predictor 3, 512² blocks, GDAL's
average overviews): 4097² (one seamless tile) and 16385² (the mosaic of 16×16 copies, converted
by GDAL), each at 480×270 and 1280×720.

    python bench/bench_remote_cog.py [--sizes 4097,16385]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from _synthetic import mosaic_dem, periodic_fbm, write_dem  # noqa: E402
from _tileserver import RangeServer  # noqa: E402


def _cog(folder: Path, n: int) -> Path:
    import rasterio.shutil

    if n <= 4097:
        src = folder / f"dem{n}.tif"
        write_dem(str(src), periodic_fbm(n - 1), crs="EPSG:32617", west=500000.0,
                  north=4000000.0, res=2.0)  # fmt: skip
    else:
        src = mosaic_dem(folder, (n - 1) // 1024)
    out = folder / f"cog{n}.tif"
    rasterio.shutil.copy(str(src), str(out), driver="COG", compress="deflate", predictor=3,
                         blocksize=512, overview_resampling="average")  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="4097,16385")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n in (int(s) for s in args.sizes.split(",")):
            path = _cog(folder, n)
            server = RangeServer(path)
            try:
                for size in ("480x270", "1280x720"):
                    server.sent = server.requests = 0
                    env = {**os.environ, "LODSCAPE_CACHE": str(folder / f"cache-{n}-{size}")}
                    t0 = time.perf_counter()
                    proc = subprocess.run(
                        [sys.executable, "-m", "lodscape", "render", server.url, "--size", size,
                         "-o", str(folder / "out.png"), "-q"],
                        capture_output=True, text=True, env=env,
                    )  # fmt: skip
                    s = time.perf_counter() - t0
                    if proc.returncode != 0:
                        raise RuntimeError(proc.stderr.strip().splitlines()[-1])
                    mb = len(server.data) / 2**20
                    print(
                        f"{n}² COG ({mb:.1f} MB) at {size}: {s:.1f} s, fetched "
                        f"{100 * server.sent / len(server.data):.2f} % in {server.requests} "
                        "requests",
                        flush=True,
                    )
            finally:
                server.close()
            path.unlink()


if __name__ == "__main__":
    main()
