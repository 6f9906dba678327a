"""Analytic terrain for tests that must not depend on files: heights are a function of position."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.tiles import Bbox, lonlat_to_merc


class AnalyticSource:
    """Ridges and valleys over a lon/lat box, defined everywhere, valid inside the box."""

    name = "analytic"
    crs_wkt = "EPSG:3857"

    def __init__(
        self,
        west: float = -84.4,
        south: float = 36.45,
        east: float = -84.1,
        north: float = 36.73,
        resolution: float = 20.0,
        relief: float = 300.0,
    ) -> None:
        (left, right), (bottom, top) = lonlat_to_merc([west, east], [south, north])
        self.bounds_merc = Bbox(float(left), float(bottom), float(right), float(top))
        self.resolution_merc = resolution
        self.relief = relief

    def sample(
        self, xm: NDArray[np.float64], ym: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        xm, ym = np.asarray(xm, np.float64), np.asarray(ym, np.float64)
        h = (
            500.0
            + self.relief * np.sin(xm / 3000.0) * np.cos(ym / 2500.0)
            + 0.3 * self.relief * np.abs(np.sin(xm / 700.0 + ym / 900.0))
            + 0.05 * self.relief * np.sin(xm / 150.0) * np.sin(ym / 170.0)
        )
        b = self.bounds_merc
        valid = (xm >= b.left) & (xm <= b.right) & (ym >= b.bottom) & (ym <= b.top)
        return h.astype(np.float32), valid

    def sample_grid(
        self, xs: NDArray[np.float64], ys: NDArray[np.float64], spacing: float
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        xx, yy = np.meshgrid(xs, ys)
        return self.sample(xx, yy, spacing)

    def read(
        self, bounds: Bbox, shape: tuple[int, int]
    ) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
        rows, cols = shape
        xs = np.linspace(bounds.left, bounds.right, cols)
        ys = np.linspace(bounds.top, bounds.bottom, rows)
        xx, yy = np.meshgrid(xs, ys)
        return self.sample(xx, yy, (bounds.right - bounds.left) / (cols - 1))

    def close(self) -> None:
        pass


def fbm_heights(size: int, seed: int = 7, relief: float = 900.0) -> NDArray[np.float32]:
    """Rough, realistic-looking relief: octaves of smooth noise (a test fixture, not data)."""
    from scipy.ndimage import zoom

    rng = np.random.default_rng(seed)
    out = np.zeros((size, size), dtype=np.float64)
    amp = 1.0
    cells = 4
    while cells < size:
        coarse = rng.standard_normal((cells + 3, cells + 3))
        fine = zoom(coarse, (size + 3 * size / cells) / (cells + 3), order=3)[:size, :size]
        out += amp * fine
        amp *= 0.55
        cells *= 2
    out -= out.min()
    return (300.0 + relief * out / out.max()).astype(np.float32)


def write_dem(
    path: str,
    heights: NDArray[np.floating],
    *,
    crs: str | None,
    west: float,
    north: float,
    res: float,
    nodata: float | None = None,
    unit: str | None = None,
) -> str:
    """A real GeoTIFF on disk through rasterio (``unit``: its band's unit metadata)."""
    import rasterio
    from rasterio.transform import Affine

    profile = {
        "driver": "GTiff",
        "height": heights.shape[0],
        "width": heights.shape[1],
        "count": 1,
        "dtype": str(heights.dtype),
        "transform": Affine(res, 0.0, west, 0.0, -res, north),
    }
    if crs is not None:
        profile["crs"] = crs
    if nodata is not None:
        profile["nodata"] = nodata
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(heights, 1)
        if unit is not None:
            dst.units = (unit,)
    return path


def run_cli(argv: list[str], capsys: object) -> tuple[int, str, str]:
    """Run the ``lodscape`` command in-process: (exit status, stdout, stderr)."""
    from lodscape.cli import main

    try:
        main(argv)
        code = 0
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()  # type: ignore[attr-defined]
    return code, out, err


def fbm_tileset(
    folder: Path,
    seed: int,
    n: int = 513,
    west: float = 500_000.0,
    north: float = 4_000_000.0,
    fill: str = "interpolate",
) -> Path:
    """A tileset built from an n² fBm DEM (10 m pixels, UTM 17N): what the streaming tests fly."""
    from lodscape.build import BuildOptions, build

    dem = write_dem(
        str(folder / "dem.tif"),
        fbm_heights(n, seed=seed),
        crs="EPSG:32617",
        west=west,
        north=north,
        res=10.0,
    )
    out = folder / "site.lods"
    build([dem], out, BuildOptions(fill=fill))
    return out


def helsinki_tileset(folder: Path) -> Path:
    """A tileset over the west part of the bundled Helsinki extract (a low fBm DEM, 10 m): what
    the city store and the server are tested on."""
    from lodscape.cli import main

    heights = fbm_heights(257, seed=5, relief=40.0)[:, :160] - 290.0
    dem = write_dem(
        str(folder / "helsinki_dem.tif"),
        np.ascontiguousarray(heights),
        crs="EPSG:4326",
        west=24.930,
        north=60.182,
        res=0.0001,
    )
    out = folder / "site.lods"
    main(["build", dem, "-o", str(out), "-q"])
    return out


def magenta_cracks(rgb: NDArray[np.uint8]) -> int:
    """Magenta pixels below the terrain's silhouette: holes through the surface."""
    magenta = np.all(rgb == (255, 0, 255), axis=2)
    seen_above = np.maximum.accumulate(~magenta, axis=0)
    return int((magenta & seen_above).sum())


def spine_views(scene: Any, width: int, height: int) -> dict[str, Any]:
    """The spine's four test views of a scene: straight down, oblique, low and grazing, and
    steep and near, about the centre of its data."""
    from lodscape import Camera
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.source.bounds_merc
    lon, lat = (float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2))
    g = scene.ground_height(lon, lat) or 0.0
    hi = scene.tree.height_range[1]
    size = {"width": width, "height": height}
    return {
        "down": Camera(lon, lat, g + 2500.0, pitch=-90, **size),
        "oblique": Camera(lon, lat - 0.02, hi + 800.0, heading=10, pitch=-30, **size),
        "low": Camera(lon - 0.01, lat - 0.015, hi + 150.0, heading=35, pitch=-12, **size),
        "steep-near": Camera(lon, lat, g + 300.0, heading=200, pitch=-55, **size),
    }


def write_ortho(
    path: str,
    rgb: NDArray[np.uint8],
    *,
    crs: str,
    west: float,
    north: float,
    res: float,
    alpha: NDArray[np.uint8] | None = None,
) -> str:
    """An orthophoto GeoTIFF (RGB, or RGBA with ``alpha``) on disk through rasterio."""
    import rasterio
    from rasterio.enums import ColorInterp
    from rasterio.transform import Affine

    bands = [rgb[..., 0], rgb[..., 1], rgb[..., 2]] + ([alpha] if alpha is not None else [])
    profile = {
        "driver": "GTiff",
        "height": rgb.shape[0],
        "width": rgb.shape[1],
        "count": len(bands),
        "dtype": "uint8",
        "crs": crs,
        "transform": Affine(res, 0.0, west, 0.0, -res, north),
        "photometric": "RGB",
        "tiled": True,
    }
    with rasterio.open(path, "w", **profile) as dst:
        for i, band in enumerate(bands):
            dst.write(band, i + 1)
        interp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
        dst.colorinterp = interp + ([ColorInterp.alpha] if alpha is not None else [])
    return path


def sky_share(png: str | os.PathLike[str]) -> float:
    """The share of a rendered picture's pixels that are the sky's colour (``lodscape.scene.SKY``,
    within 2 levels): what a picture that shows the data must have little of."""
    from PIL import Image

    from lodscape.scene import SKY

    with Image.open(png) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    sky = np.all(np.abs(rgb - np.array(SKY) * 255) <= 2, axis=2)
    return float(sky.mean())


def changed_share(a: str | os.PathLike[str], b: str | os.PathLike[str], levels: int = 30) -> float:
    """The share of pixels whose colours differ by more than ``levels`` (summed over R, G, B)
    between two pictures of the same size."""
    from PIL import Image

    with Image.open(a) as ia, Image.open(b) as ib:
        pa = np.asarray(ia.convert("RGB")).astype(int)
        pb = np.asarray(ib.convert("RGB")).astype(int)
    return float((np.abs(pa - pb).sum(axis=2) > levels).mean())


def reprojected_jump(d0: np.ndarray, c0: Any, d1: np.ndarray, c1: Any) -> np.ndarray:
    """Per pixel of frame 0 seen again in frame 1, how far (pixels) the surface there moved:
    frame 0's point projected into camera 1, its depth compared with frame 1's there, scaled
    to pixels at that distance. NaN where either frame sees no ground or it fell off screen."""
    with np.errstate(invalid="ignore"):
        return _reprojected(d0, c0, d1, c1)


def _reprojected(d0: np.ndarray, c0: Any, d1: np.ndarray, c1: Any) -> np.ndarray:
    h, w = d0.shape
    t = math.tan(math.radians(c0.fov_y) / 2)
    u = ((np.arange(w) + 0.5) / w * 2 - 1) * t * c0.aspect
    v = (1 - (np.arange(h) + 0.5) / h * 2) * t
    uu, vv = np.meshgrid(u, v)
    view = np.stack([uu * d0, vv * d0, -d0], axis=-1)  # camera 0's view space
    world = view @ c0.rotation + c0.position  # rows of the rotation are the view axes
    rel = (world - c1.position) @ c1.rotation.T
    z = -rel[..., 2]
    x = rel[..., 0] / (z * t * c1.aspect)
    y = rel[..., 1] / (z * t)
    # frame 1's depth at the point's sub-pixel place, bilinear between the four pixels round it
    # (where they agree: not across a silhouette)
    fx, fy = (x + 1) / 2 * w - 0.5, (1 - y) / 2 * h - 0.5
    fx, fy = np.nan_to_num(fx, nan=-1.0), np.nan_to_num(fy, nan=-1.0)
    c0, r0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    ok = np.isfinite(d0) & (z > 0) & (c0 >= 0) & (c0 < w - 1) & (r0 >= 0) & (r0 < h - 1)
    c, r, ax, ay = c0[ok], r0[ok], (fx - c0)[ok], (fy - r0)[ok]
    q = np.stack([d1[r, c], d1[r, c + 1], d1[r + 1, c], d1[r + 1, c + 1]])
    got = (q[0] * (1 - ax) + q[1] * ax) * (1 - ay) + (q[2] * (1 - ax) + q[3] * ax) * ay
    smooth = np.isfinite(q).all(axis=0) & (np.ptp(q, axis=0) < 0.02 * z[ok])
    out = np.full(d0.shape, np.nan)
    idx = np.nonzero(ok)
    out[idx[0][smooth], idx[1][smooth]] = np.abs(got - z[ok])[smooth] * c1.scale / z[ok][smooth]
    return out


def periodic_fbm(n: int, seed: int = 3, relief: float = 800.0) -> NDArray[np.float32]:
    """Spectral fBm of period n (Hurst 0.8), n + 1 samples a side (the first row and column
    repeated): copies side by side join without a seam."""
    rng = np.random.default_rng(seed)
    k = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n)))
    k[0, 0] = 1.0
    spectrum = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * k**-1.8
    spectrum[0, 0] = 0.0
    h = np.fft.ifft2(spectrum).real
    h = (h - h.min()) / (h.max() - h.min()) * relief + 200.0
    return np.pad(h, ((0, 1), (0, 1)), mode="wrap").astype(np.float32)


def mosaic_dem(folder: Path, copies: int, tile: int = 1024) -> Path:
    """A VRT of copies² copies of a seamless (tile + 1)² fBm GeoTIFF (2 m, UTM 17N): a raw DEM
    of (tile · copies + 1)² pixels, read through GDAL as any user's file, a few MB on disk."""
    from html import escape

    import rasterio

    base = folder / "tile.tif"
    write_dem(str(base), periodic_fbm(tile), crs="EPSG:32617", west=500000.0,
              north=4000000.0, res=2.0)  # fmt: skip
    with rasterio.open(base) as ds:
        wkt = ds.crs.to_wkt()
    size = tile * copies + 1
    sources = "".join(
        f'<SimpleSource><SourceFilename relativeToVRT="1">tile.tif</SourceFilename>'
        f"<SourceBand>1</SourceBand>"
        f'<SrcRect xOff="0" yOff="0" xSize="{tile + 1}" ySize="{tile + 1}"/>'
        f'<DstRect xOff="{i * tile}" yOff="{j * tile}" xSize="{tile + 1}" ySize="{tile + 1}"/>'
        "</SimpleSource>"
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


#: Run as ``python -c PEAK_PROBE DEM`` in a fresh process: open DEM, render its overview at
#: 320×200, print JSON of the process's own peak RSS (VmHWM: getrusage's maxrss keeps a
#: parent's peak across exec), the open and render times, the raster's shape and its sidecar.
PEAK_PROBE = """
import json, sys, time
import lodscape

def hwm():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024

t = time.perf_counter()
scene = lodscape.open(sys.argv[1])
opened = time.perf_counter() - t
t = time.perf_counter()
rgb, depth = scene.render(scene.overview_camera(320, 200))
src = scene.source.source
src = getattr(src, "source", src)  # the raster under its fill
print(json.dumps({
    "peak_mb": hwm(),
    "open_s": opened,
    "render_s": time.perf_counter() - t,
    "shape": list(src.shape),
    "sidecar": getattr(src, "sidecar", None),
    "ground": float((depth < 1e30).mean()),
    "tiles": scene.last.selection["tiles"],
}))
"""
