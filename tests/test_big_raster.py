"""A raw DEM far larger than the memory a view needs: 16385² (a VRT mosaic of a seamless tile,
read through GDAL as any user's file) opens and renders within a stated peak RSS, its coarse
levels read from overviews built once in the cache, nothing written beside the file."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _synthetic import write_dem

pytestmark = pytest.mark.gl

#: Peak resident memory allowed to open and render the 16385² DEM (the process, GL included).
RSS_LIMIT_MB = 600
TILE = 1024
COPIES = 16


def _periodic_fbm(n: int, seed: int, relief: float) -> np.ndarray:
    """Spectral fBm of period n (Hurst 0.8): its copies side by side join without a seam."""
    rng = np.random.default_rng(seed)
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    k[0, 0] = 1.0
    spectrum = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * k**-1.8
    spectrum[0, 0] = 0.0
    h = np.fft.ifft2(spectrum).real
    h = (h - h.min()) / (h.max() - h.min()) * relief + 200.0
    return np.pad(h, ((0, 1), (0, 1)), mode="wrap").astype(np.float32)


def _mosaic(folder: Path) -> Path:
    base = folder / "tile.tif"
    write_dem(str(base), _periodic_fbm(TILE, 3, 800.0), crs="EPSG:32617", west=500000.0,
              north=4000000.0, res=2.0)  # fmt: skip
    import rasterio

    with rasterio.open(base) as ds:
        wkt = ds.crs.to_wkt()
    size = TILE * COPIES + 1
    sources = "".join(
        f'<SimpleSource><SourceFilename relativeToVRT="1">tile.tif</SourceFilename>'
        f"<SourceBand>1</SourceBand>"
        f'<SrcRect xOff="0" yOff="0" xSize="{TILE + 1}" ySize="{TILE + 1}"/>'
        f'<DstRect xOff="{i * TILE}" yOff="{j * TILE}" xSize="{TILE + 1}" ySize="{TILE + 1}"/>'
        "</SimpleSource>"
        for j in range(COPIES)
        for i in range(COPIES)
    )
    from html import escape

    vrt = folder / "big.vrt"
    vrt.write_text(
        f'<VRTDataset rasterXSize="{size}" rasterYSize="{size}"><SRS>{escape(wkt)}</SRS>'
        "<GeoTransform>500000.0, 2.0, 0.0, 4000000.0, 0.0, -2.0</GeoTransform>"
        f'<VRTRasterBand dataType="Float32" band="1">{sources}</VRTRasterBand></VRTDataset>'
    )
    return vrt


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
cam = scene.overview_camera(320, 200)
rgb, depth = scene.render(cam)
src = scene.source.source
print(json.dumps({
    "peak_mb": hwm(),
    "open_s": opened,
    "shape": list(src.shape),
    "sidecar": src.sidecar,
    "ground": float((depth < 1e30).mean()),
    "tiles": scene.last.selection["tiles"],
}))
"""


def test_a_16385_dem_renders_within_its_memory_bound(tmp_path: Path) -> None:
    vrt = _mosaic(tmp_path)
    cache = tmp_path / "cache"
    env = {**os.environ, "LODSCAPE_CACHE": str(cache)}
    env.pop("GDAL_CACHEMAX", None)
    got = []
    for _ in range(2):  # the first run builds the overviews, the second finds them
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE, str(vrt)],
            capture_output=True,
            text=True,
            timeout=600,
            env=env,
        )
        assert proc.returncode == 0, proc.stderr
        got.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    first, again = got
    assert first["shape"] == [16385, 16385]
    assert first["ground"] > 0.5
    # the overviews went to the cache, beside a VRT of the band; none beside the user's file
    sidecar = Path(first["sidecar"])
    assert sidecar.parent == cache / "overviews"
    assert Path(str(sidecar) + ".ovr").stat().st_size > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.vrt", "cache", "tile.tif"]
    assert again["sidecar"] == first["sidecar"]
    for run in got:
        assert run["peak_mb"] < RSS_LIMIT_MB, run
