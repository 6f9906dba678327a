"""A raw DEM far larger than the memory a view needs: 16385² (a VRT mosaic of a seamless tile,
read through GDAL as any user's file) opens and renders within a stated peak RSS, its coarse
levels read from overviews built once in the cache, nothing written beside the file."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from _synthetic import PEAK_PROBE, mosaic_dem

pytestmark = pytest.mark.gl

#: Peak resident memory allowed to open and render the 16385² DEM (the process, GL included).
RSS_LIMIT_MB = 600


def test_a_16385_dem_renders_within_its_memory_bound(tmp_path: Path) -> None:
    vrt = mosaic_dem(tmp_path, 16)
    cache = tmp_path / "cache"
    env = {**os.environ, "LODSCAPE_CACHE": str(cache)}
    env.pop("GDAL_CACHEMAX", None)
    got = []
    for _ in range(2):  # the first run builds the overviews, the second finds them
        proc = subprocess.run(
            [sys.executable, "-c", PEAK_PROBE, str(vrt)],
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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", vrt.name, "tile.tif"]
    assert again["sidecar"] == first["sidecar"]
    for run in got:
        assert run["peak_mb"] < RSS_LIMIT_MB, run
