"""Convert matplotlib's Jacksboro Fault sample DEM to ``src/lodscape/data/jacksboro.tif``.

One-off and reproducible: ``python bench/make_sample_dem.py``. Needs matplotlib (the package
itself never imports it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from matplotlib import cbook
from rasterio.transform import Affine

OUT = Path(__file__).resolve().parents[1] / "src" / "lodscape" / "data" / "jacksboro.tif"


def main() -> None:
    path = cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False)
    with np.load(path) as d:
        elevation = np.asarray(d["elevation"], dtype=np.int16)
        dx, dy = float(d["dx"]), float(d["dy"])
        west, east = float(d["xmin"]), float(d["xmax"])
        # the file's "ymin" is the north edge and "ymax" the south one: row 0 is north
        north, south = float(d["ymin"]), float(d["ymax"])
    rows, cols = elevation.shape
    assert abs(rows * dy - (north - south)) < 1e-9, "rows × dy must span the latitude range"
    assert abs(cols * dx - (east - west)) < 1e-9, "cols × dx must span the longitude range"
    profile = {
        "driver": "GTiff",
        "width": cols,
        "height": rows,
        "count": 1,
        "dtype": "int16",
        "crs": "EPSG:4326",
        "transform": Affine(dx, 0.0, west, 0.0, -dy, north),
        "compress": "deflate",
        "predictor": 2,
        "zlevel": 9,
        "tiled": True,
        "blockxsize": 256,
        "blockysize": 256,
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(OUT, "w", **profile) as dst:
        dst.write(elevation, 1)
        dst.update_tags(1, units="metre")
        dst.units = ("metre",)
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
