"""A cloud-optimised GeoTIFF over HTTP (issue 36): opened through GDAL's /vsicurl/ with range
requests from a real loopback server, its first picture made from a small part of the file."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from _synthetic import periodic_fbm
from _tileserver import RangeServer


@pytest.fixture(scope="module")
def cog(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RangeServer]:
    import rasterio
    from rasterio.transform import Affine

    folder = tmp_path_factory.mktemp("cog")
    h = periodic_fbm(4096, seed=8, relief=600.0)
    path = folder / "dem.tif"
    profile = {
        "driver": "COG",
        "width": h.shape[1],
        "height": h.shape[0],
        "count": 1,
        "dtype": "float32",
        "crs": "EPSG:32617",
        "transform": Affine(2.0, 0.0, 500000.0, 0.0, -2.0, 4000000.0),
        "compress": "deflate",
        "blocksize": 256,
        "overview_resampling": "average",
    }
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(h, 1)
    server = RangeServer(path)
    yield server
    server.close()


@pytest.mark.parametrize("prefix", ["", "/vsicurl/"])
def test_a_remote_cog_renders_from_a_small_part_of_it(
    cog: RangeServer, tmp_path: Path, prefix: str
) -> None:
    cog.sent = 0
    out = tmp_path / "remote.png"
    env = {**os.environ, "LODSCAPE_CACHE": str(tmp_path / "cache")}
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape", "render", prefix + cog.url, "--size", "480x270",
         "-o", str(out), "-q"],
        capture_output=True, text=True, env=env, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    share = cog.sent / len(cog.data)
    print(f"fetched {100 * share:.1f} % of the file")
    assert share < 0.25, f"fetched {100 * share:.1f} % of the file"
    from PIL import Image

    rgb = np.asarray(Image.open(out).convert("RGB"))
    assert (rgb.std(axis=(0, 1)) > 5).all()  # a picture, not a blank


def test_a_remote_file_that_is_not_there_is_one_line(cog: RangeServer, tmp_path: Path) -> None:
    url = cog.url.rsplit("/", 1)[0] + "/missing.tif"
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape", "render", url, "-o", str(tmp_path / "x.png"), "-q"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert "missing.tif" in lines[0]
