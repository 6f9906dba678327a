"""Scattered elevation points to a regular grid: a Delaunay TIN resampled, as paper 001 does.

Inputs are CSV files with an ``x,y,z`` header (any column order, other columns ignored) or
whitespace-separated XYZ text with no header; coordinates are in the CRS the caller names.
The grid spans the points' bounding box at a resolution given or taken from the points' own
spacing (the median distance to the nearest neighbour); cells outside the points' convex hull are
nodata.
"""

from __future__ import annotations

import csv
import math
import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pyproj import CRS
from rasterio.transform import Affine
from scipy.interpolate import LinearNDInterpolator
from scipy.spatial import Delaunay, QhullError, cKDTree

from lodscape._tmp import temp_beside
from lodscape.errors import SourceError

__all__ = ["MAX_CELLS", "POINT_SUFFIXES", "grid_points", "read_points", "write_grid"]

#: File name endings read as point files.
POINT_SUFFIXES = (".csv", ".xyz", ".txt", ".pts", ".las", ".laz")
#: Largest grid the points may be resampled to (cells).
MAX_CELLS = 1 << 26

F64 = NDArray[np.float64]


def read_points(path: str | os.PathLike[str]) -> tuple[F64, F64, F64, CRS | None]:
    """x, y, z of every point in a CSV (x,y,z header), whitespace XYZ or LAS/LAZ file, and the
    CRS the file names (LAS headers may; text files do not)."""
    name = os.fspath(path)
    if name.lower().endswith((".las", ".laz")):
        return _read_las(name)
    try:
        with open(name, newline="", encoding="utf-8-sig") as f:
            text = f.read()
    except FileNotFoundError:
        raise SourceError(f"{name}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{name}: cannot read ({exc})") from None
    lines = text.splitlines()
    first = next((ln for ln in lines if ln.strip()), "")
    if not first:
        raise SourceError(f"{name}: no points (the file is empty)")
    header = [c.strip().lower() for c in first.split(",")]
    rows: list[tuple[int, list[str]]] = []
    if "x" in header and "y" in header and "z" in header:
        cols = [header.index(k) for k in ("x", "y", "z")]
        reader = csv.reader(lines)
        next(reader)
        for number, row in enumerate(reader, start=2):
            if not any(c.strip() for c in row):
                continue
            if max(cols) >= len(row):
                raise SourceError(f"{name}: row {number}: expected x, y and z, got {row!r}")
            rows.append((number, [row[c] for c in cols]))
    elif any(c.isalpha() for c in first.replace("e", "").replace("E", "")):
        raise SourceError(
            f"{name}: the header {first.strip()!r} has no x, y and z columns (CSV needs an "
            "x,y,z header; XYZ text needs three numbers a line and no header)"
        )
    else:
        for number, line in enumerate(lines, start=1):
            parts = line.replace(",", " ").split()
            if not parts:
                continue
            if len(parts) < 3:
                raise SourceError(f"{name}: row {number}: expected x y z, got {line.strip()!r}")
            rows.append((number, parts[:3]))
    values = np.empty((len(rows), 3), dtype=np.float64)
    for i, (number, fields) in enumerate(rows):
        try:
            values[i] = [float(v) for v in fields]
        except ValueError:
            raise SourceError(
                f"{name}: row {number}: {','.join(fields)!r} is not three numbers"
            ) from None
        if not np.isfinite(values[i]).all():
            raise SourceError(f"{name}: row {number}: {','.join(fields)!r} is not finite")
    return values[:, 0], values[:, 1], values[:, 2], None


def _read_las(name: str) -> tuple[F64, F64, F64, CRS | None]:
    """A LAS or LAZ point cloud through laspy: its ground points (class 2) where it classifies
    them, otherwise all of them."""
    try:
        import laspy
    except ImportError:
        raise SourceError(
            f"{name}: reading LAS/LAZ needs laspy: pip install 'lodscape[las]'"
        ) from None
    if not os.path.exists(name):
        raise SourceError(f"{name}: no such file")
    try:
        las = laspy.read(name)
        x, y, z = (np.asarray(getattr(las, c), dtype=np.float64) for c in "xyz")
        cls = np.asarray(las.classification)
        crs = las.header.parse_crs()
    except Exception as exc:  # laspy raises its own errors, lazrs and OSError others
        raise SourceError(f"{name}: not a LAS/LAZ file laspy can read ({exc})") from None
    ground = cls == 2
    if ground.any():
        x, y, z = x[ground], y[ground], z[ground]
    return x, y, z, None if crs is None else CRS.from_user_input(crs)


def grid_points(
    x: F64, y: F64, z: F64, *, name: str, resolution: float | None = None
) -> tuple[NDArray[np.float32], Affine]:
    """Heights on a regular grid (row 0 north, NaN outside the hull) and its transform."""
    if x.size < 3:
        raise SourceError(f"{name}: {x.size} point(s); a surface needs at least three")
    xy = np.column_stack([x, y])
    # the same location twice: keep its first height (a TIN has one height per vertex)
    xy, first = np.unique(xy, axis=0, return_index=True)
    z = z[first]
    if len(xy) < 3:
        raise SourceError(f"{name}: fewer than three distinct points")
    try:
        tri = Delaunay(xy)
    except QhullError:
        raise SourceError(
            f"{name}: all points lie on one line; they do not span a surface"
        ) from None
    if resolution is None:
        dist, _ = cKDTree(xy).query(xy, k=2)
        resolution = float(np.median(dist[:, 1]))
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise SourceError(f"{name}: cannot work out a grid resolution; give --resolution")
    x0, y0 = xy.min(axis=0)
    x1, y1 = xy.max(axis=0)
    cols = math.floor((x1 - x0) / resolution) + 1
    rows = math.floor((y1 - y0) / resolution) + 1
    if cols * rows > MAX_CELLS:
        raise SourceError(
            f"{name}: a grid of {cols}×{rows} cells at {resolution:g} is too large; "
            "give a coarser --resolution"
        )
    if cols < 2 or rows < 2:
        raise SourceError(f"{name}: the points span less than two cells at {resolution:g}")
    # cell centres, so the points' corner ones land on the grid's first and last
    xs = x0 + resolution * np.arange(cols)
    ys = y1 - resolution * np.arange(rows)
    gx, gy = np.meshgrid(xs, ys)
    heights = LinearNDInterpolator(tri, z)(gx, gy).astype(np.float32)
    transform = Affine(resolution, 0.0, x0 - resolution / 2, 0.0, -resolution, y1 + resolution / 2)
    return heights, transform


def write_grid(
    path: str | os.PathLike[str], heights: NDArray[np.float32], transform: Affine, crs: CRS
) -> None:
    """A tiled, compressed float32 GeoTIFF with NaN as nodata, written whole or not at all."""
    import rasterio

    target = Path(path)
    tmp = temp_beside(target)
    profile = {
        "driver": "GTiff",
        "height": heights.shape[0],
        "width": heights.shape[1],
        "count": 1,
        "dtype": "float32",
        "crs": crs.to_wkt(),
        "transform": transform,
        "nodata": float("nan"),
        "compress": "deflate",
        "tiled": heights.shape[0] >= 256 and heights.shape[1] >= 256,
    }
    try:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(heights, 1)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
