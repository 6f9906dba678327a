"""Heights over a server against the DEM they were built from (issue 40, item 7): a 513² fBm DEM
(30 m, UTM) built into a tileset, served by ``lodscape serve`` in both tilings on loopback, read
back by lodscape's own client at several spacings; the mean, median and 95th percentile of
(served − DEM) at 3,000 random points inside the data.

    python bench/bench_remote_bias.py
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import fbm_heights, write_dem
from _tileserver import serve_tileset


def _line(what: str, d: np.ndarray) -> str:
    return (
        f"{what}: mean {np.nanmean(d):+.3f} m, median {np.nanmedian(d):+.3f} m, "
        f"p95 |d| {np.nanpercentile(np.abs(d), 95):.3f} m"
    )


def main() -> None:
    from lodscape.build import build
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.store.remote import open_server
    from lodscape.store.tileset import TilesetProvider
    from lodscape.terrain.source import RasterSource

    folder = Path(tempfile.mkdtemp(prefix="remote_bias_"))
    dem = write_dem(
        str(folder / "dem.tif"),
        fbm_heights(513, seed=9) + 300.0,
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=30.0,
    )
    lods = folder / "dem.lods"
    build([dem], lods)
    raster = RasterSource(dem)
    provider = TilesetProvider(lods)
    b = provider.bounds_merc
    rng = np.random.default_rng(0)
    w, h = b.right - b.left, b.top - b.bottom
    xm = rng.uniform(b.left + 0.1 * w, b.right - 0.1 * w, 3000)
    ym = rng.uniform(b.bottom + 0.1 * h, b.top - 0.1 * h, 3000)
    want, _ok = raster.sample(xm, ym, raster.resolution_merc)
    print(_line("the tileset's finest surface", provider.heights(*merc_to_lonlat(xm, ym)) - want))
    provider.close()
    for tiling in ("mercator", "geographic"):
        with serve_tileset(lods, tiling=tiling) as url:
            heights, _tree = open_server(url + "/layer.json")
            for spacing in (heights.resolution_merc, 30.0, 60.0, 120.0):
                got, _ok = heights.sample(xm, ym, spacing)
                level = heights.level_for(spacing)
                print(_line(f"{tiling}, level {level} ({spacing:.1f} m)", got - want))
            heights.close()


if __name__ == "__main__":
    main()
