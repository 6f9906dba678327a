"""A local orthophoto as an imagery layer: any GDAL raster (GeoTIFF, COG, JPEG2000…) in any CRS,
cut into Web Mercator z/x/y tiles on demand.

Each tile reads only the window of the raster under it, decimated by GDAL with an averaging
filter (a COG's overviews serve the coarse levels), then sampled bilinearly at the tile's Web
Mercator texel centres (pyproj, vectorised; colours premultiplied by coverage). The raster's
mask (nodata, an alpha band, a per-dataset mask) becomes the tile's alpha, as does everything
outside the raster. RGB(A) rasters keep their bands; a
palette raster is expanded through its colour table before it is filtered; a single band is grey.
Bands that are not bytes are stretched between the 2nd and 98th percentiles of a coarse read.

Its finest level is the raster's own: the level whose texels are as fine as its pixels.
"""

from __future__ import annotations

import math
import os
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.tiles import ORIGIN, Bbox, Tile, xy_bounds
from lodscape.imagery.sources import ImageryError

__all__ = ["RasterImagery"]

_MERCATOR = "EPSG:3857"
#: Texels per tile side.
TILE = 256


class RasterImagery:
    """z/x/y tiles cut from a georeferenced raster (``ImageryFetcher``)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        max_zoom: int | None = None,
        bands: tuple[int, ...] | None = None,
    ) -> None:
        import rasterio
        from rasterio.errors import RasterioIOError
        from rasterio.warp import transform_bounds

        self.name = os.fspath(path)
        self._local = threading.local()
        try:
            src = rasterio.open(self.name)
        except RasterioIOError as exc:
            raise ImageryError(f"{self.name}: not a raster GDAL can read ({exc})") from None
        with src:
            #: One line on where the raster's place came from, where it states no grid (None).
            self.place_note: str | None = None
            self.crs, self._transform = src.crs, src.transform
            if src.crs is None:
                self._place_by_gcps(src)
            if src.count < 1:
                raise ImageryError(f"{self.name}: the raster has no bands")
            #: One line on the bands drawn as red, green and blue where they were guessed.
            self.band_note: str | None = None
            if bands is not None:
                if len(bands) != 3 or not all(1 <= b <= src.count for b in bands):
                    raise ImageryError(
                        f"{self.name}: --imagery-bands needs three bands of 1..{src.count} "
                        f"(red, green, blue), got {','.join(map(str, bands))}"
                    )
                self._bands, self._palette = [b - 1 for b in bands], None
            else:
                self._bands, self._palette = _band_plan(src)
                if src.count > 3 and self._palette is None and not _has_rgb(src):
                    drawn = ",".join(str(b + 1) for b in self._bands)
                    self.band_note = (
                        f"{self.name}: {src.count} bands and none says red, green or blue: "
                        f"bands {drawn} drawn as red, green, blue (--imagery-bands R,G,B picks "
                        "others, e.g. 4,3,2 for Landsat 8)"
                    )
            t, cw, ch = self._transform, src.width, src.height
            xs = [t.a * c + t.b * r + t.c for c in (0, cw) for r in (0, ch)]
            ys = [t.d * c + t.e * r + t.f for c in (0, cw) for r in (0, ch)]
            box = (min(xs), min(ys), max(xs), max(ys))
            try:
                w, s, e, n = transform_bounds(self.crs, "EPSG:4326", *box, densify_pts=21)
                left, bottom, right, top = transform_bounds(
                    self.crs, _MERCATOR, *box, densify_pts=21
                )
            except Exception as exc:  # GDAL's projection errors come in several classes
                raise ImageryError(
                    f"{self.name}: its georeference cannot be placed in Web Mercator ({exc})"
                ) from None
            if not all(map(math.isfinite, (left, bottom, right, top))) or right <= left:
                raise ImageryError(f"{self.name}: its georeference lies outside Web Mercator")
            self.bounds_lonlat = (w, s, e, n)
            self.bounds_merc = Bbox(
                max(left, -ORIGIN), max(bottom, -ORIGIN), min(right, ORIGIN), min(top, ORIGIN)
            )
            #: Web Mercator metres per pixel at the raster's middle.
            self.resolution_merc = _merc_resolution(src, self._transform, self.crs)
            try:
                self._stretch = _stretch(src, self._bands) if src.dtypes[0] != "uint8" else None
            except ImageryError:
                raise
            except Exception as exc:  # a damaged or truncated file fails at its first read
                raise ImageryError(f"{self.name}: cannot be read ({_cause(exc)})") from None
            self.size = (src.width, src.height)
            #: A large raster with no overviews: its coarse levels read all of it, slowly.
            self.needs_overviews = max(src.width, src.height) > 4096 and not src.overviews(1)
        native = math.log2(2.0 * ORIGIN / (TILE * self.resolution_merc))
        # the level whose texels are as fine as the pixels (a third of a level of slack, so a
        # 0.6 m orthophoto does not ask for a level that is all magnification)
        self.max_zoom = int(max(0, min(24, math.ceil(native - 0.33))))
        if max_zoom is not None:
            self.max_zoom = int(max_zoom)
        self.min_zoom = 0

    def _place_by_gcps(self, src: Any) -> None:
        """A raster with no grid of its own placed on its ground control points' affine fit,
        where it holds them all within ``GCP_TOLERANCE`` pixels (what gdalwarp's first order
        makes of them); else refused, as one with no place at all."""
        from lodscape.errors import SourceError
        from lodscape.terrain.source import gcp_placement

        gcps, gcp_crs = src.gcps
        if not gcps or gcp_crs is None:
            raise ImageryError(f"{self.name}: the raster has no CRS (it cannot be placed)")
        try:
            self._transform, self.place_note = gcp_placement(self.name, gcps, gcp_crs)
        except SourceError as exc:
            raise ImageryError(str(exc)) from None
        self.crs = gcp_crs

    def _dataset(self) -> Any:
        src = getattr(self._local, "src", None)
        if src is None:
            import rasterio

            src = self._local.src = rasterio.open(self.name)
        return src

    def covers(self, z: int, x: int, y: int) -> bool:
        left, bottom, right, top = xy_bounds(Tile(x, y, z))
        b = self.bounds_merc
        return bool(left < b.right and right > b.left and bottom < b.top and top > b.bottom)

    def fetch(self, z: int, x: int, y: int) -> bytes:
        """The tile's RGBA texels, raw (TILE·TILE·4 bytes); b"" where the raster has nothing."""
        if not self.covers(z, x, y):
            return b""
        try:
            rgba = self._tile(z, x, y)
        except ImageryError:
            raise
        except Exception as exc:  # a damaged block, a read error: name the file and the tile
            raise ImageryError(
                f"{self.name}: tile {z}/{x}/{y} could not be read ({_cause(exc)})", "read"
            ) from None
        return b"" if rgba is None else rgba.tobytes()

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        if not data:
            return np.zeros((1, 1, 4), np.uint8)
        return np.frombuffer(data, np.uint8).reshape(TILE, TILE, 4)

    def _tile(self, z: int, x: int, y: int) -> NDArray[np.uint8] | None:
        from affine import Affine
        from rasterio.enums import Resampling
        from rasterio.warp import transform_bounds
        from rasterio.windows import Window, from_bounds
        from scipy.ndimage import map_coordinates

        src = self._dataset()
        left, bottom, right, top = xy_bounds(Tile(x, y, z))
        texel = (right - left) / TILE
        # the tile's footprint in the raster, a few texels wider so the filter has neighbours
        pad = 2.0 * texel
        sb = transform_bounds(
            _MERCATOR, self.crs, left - pad, bottom - pad, right + pad, top + pad, densify_pts=21
        )
        win = from_bounds(*sb, transform=self._transform)
        full = Window(0, 0, src.width, src.height)
        try:
            win = win.intersection(full)
        except Exception:  # rasterio raises WindowError when they do not meet
            return None
        col0, row0 = math.floor(win.col_off), math.floor(win.row_off)
        col1 = min(math.ceil(win.col_off + win.width), src.width)
        row1 = min(math.ceil(win.row_off + win.height), src.height)
        if col1 <= col0 or row1 <= row0:
            return None
        win = Window(col0, row0, col1 - col0, row1 - row0)
        # read no finer than ~2 source pixels per texel: GDAL averages (or takes an overview)
        span = max(sb[2] - sb[0], sb[3] - sb[1])
        want = (
            (TILE + 4)
            * 2.0
            * max(win.width, win.height)
            * abs(self._transform.a)
            / max(span, 1e-12)
        )
        f = max(1.0, max(win.width, win.height) / max(want, 1.0))
        out_w, out_h = max(1, round(win.width / f)), max(1, round(win.height / f))
        data = src.read(
            [b + 1 for b in self._bands],
            window=win,
            out_shape=(len(self._bands), out_h, out_w),
            resampling=Resampling.average if f > 1.0 else Resampling.nearest,
        )
        mask = src.read_masks(
            1, window=win, out_shape=(out_h, out_w), resampling=Resampling.nearest
        )
        cover = (mask > 0).astype(np.float32)
        # colours premultiplied by their coverage, so no-data never bleeds into the filter
        planes = np.concatenate([self._colours(data) * cover, cover[None]])
        t = (
            self._transform
            @ Affine.translation(win.col_off, win.row_off)
            @ Affine.scale(win.width / out_w, win.height / out_h)
        )
        # every texel centre of the tile, in the raster's CRS, then in the read's pixels
        sx, sy = self._texel_centres(z, left, top, texel)
        inv = ~t
        cols = inv.a * sx + inv.b * sy + inv.c - 0.5
        rows = inv.d * sx + inv.e * sy + inv.f - 0.5
        coords = np.stack([rows, cols])
        out = np.stack(
            [map_coordinates(p, coords, order=1, mode="constant", cval=0.0) for p in planes]
        )
        alpha = out[3]
        if not (alpha > 1e-3).any():
            return None
        # the coverage divided back out of the colours
        colour = out[:3] / np.where(alpha > 1e-3, alpha, 1.0)
        rgba = np.empty((TILE, TILE, 4), np.uint8)
        rgba[..., :3] = np.clip(np.moveaxis(colour, 0, -1) + 0.5, 0, 255)
        rgba[..., 3] = np.clip(alpha * 255.0 + 0.5, 0, 255)
        return rgba

    def _texel_centres(
        self, z: int, left: float, top: float, texel: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The tile's texel centres in the raster's CRS. From level 8 on, a 17² lattice of them
        is transformed and the rest interpolated (as GDAL's approximate transformer does): over
        a tile that small a projection bends far less than a texel, and pyproj does 256 times
        less work."""
        from scipy.ndimage import map_coordinates

        tf = self._to_source()
        if z < 8:
            c = (np.arange(TILE) + 0.5) * texel
            mx, my = np.meshgrid(left + c, top - c)
            sx, sy = tf.transform(mx, my)
            return np.asarray(sx), np.asarray(sy)
        k = 17
        c = np.linspace(0.5, TILE - 0.5, k) * texel
        mx, my = np.meshgrid(left + c, top - c)
        lx, ly = (np.asarray(v, np.float64) for v in tf.transform(mx, my))
        f = np.arange(TILE) * ((k - 1) / (TILE - 1))
        rows, cols = np.meshgrid(f, f, indexing="ij")
        at = np.stack([rows, cols])
        return (
            map_coordinates(lx, at, order=1, mode="nearest"),
            map_coordinates(ly, at, order=1, mode="nearest"),
        )

    def _to_source(self) -> Any:
        """This thread's transformer from Web Mercator to the raster's CRS."""
        tf = getattr(self._local, "tf", None)
        if tf is None:
            from pyproj import CRS, Transformer

            tf = self._local.tf = Transformer.from_crs(
                CRS.from_epsg(3857), CRS.from_wkt(self.crs.to_wkt()), always_xy=True
            )
        return tf

    def _colours(self, data: NDArray[Any]) -> NDArray[np.float32]:
        """(3, H, W) colours 0..255 from the bands read, premultiplied by nothing."""
        if self._palette is not None:
            lut = self._palette
            rgb: NDArray[np.float32] = np.moveaxis(
                lut[np.clip(data[0].astype(np.int64), 0, 255)], -1, 0
            )[:3].astype(np.float32)
            return rgb
        d = data.astype(np.float32)
        if self._stretch is not None:
            lo, hi = self._stretch
            d = (d - lo[:, None, None]) / np.maximum(hi - lo, 1e-12)[:, None, None] * 255.0
            d = np.clip(d, 0.0, 255.0)
        if d.shape[0] == 1:
            d = np.repeat(d, 3, axis=0)
        return d

    def close(self) -> None:
        src = getattr(self._local, "src", None)
        if src is not None:
            src.close()
            self._local.src = None


def _band_plan(src: Any) -> tuple[list[int], NDArray[np.uint8] | None]:
    """Which bands (0-based) make the colours, and a palette's lookup table (256, 4)."""
    from rasterio.enums import ColorInterp

    interp = list(src.colorinterp)
    if src.count == 1 and interp[0] == ColorInterp.palette:
        cmap = src.colormap(1)
        lut = np.zeros((256, 4), np.uint8)
        for i, c in cmap.items():
            if 0 <= i < 256:
                lut[i] = c
        return [0], lut
    if all(c in interp for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)):
        return [
            interp.index(c) for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue)
        ], None
    colour = [i for i, c in enumerate(interp) if c != ColorInterp.alpha]
    if len(colour) >= 3:
        return colour[:3], None
    return colour[:1] or [0], None


def _has_rgb(src: Any) -> bool:
    from rasterio.enums import ColorInterp

    interp = list(src.colorinterp)
    return all(c in interp for c in (ColorInterp.red, ColorInterp.green, ColorInterp.blue))


def parse_bands(text: str) -> tuple[int, int, int]:
    """``--imagery-bands R,G,B``: three 1-based band numbers."""
    try:
        bands = tuple(int(v) for v in text.split(","))
    except ValueError:
        bands = ()
    if len(bands) != 3 or min(bands) < 1:
        raise ImageryError(f"--imagery-bands must be three band numbers R,G,B, got {text!r}")
    return bands  # type: ignore[return-value]


def _cause(exc: BaseException) -> str:
    """GDAL's own reason, in one line (rasterio's "Read failed. See previous exception" chains
    it as the cause)."""
    cause = exc.__cause__ or exc.__context__ or exc
    return " ".join(str(cause).split())


def _stretch(src: Any, bands: list[int]) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per band the 2nd and 98th percentiles of the valid pixels of a coarse read."""
    from rasterio.enums import Resampling

    f = max(1, max(src.width, src.height) // 512)
    shape = (max(1, src.height // f), max(1, src.width // f))
    data = src.read(
        [b + 1 for b in bands], out_shape=(len(bands), *shape), resampling=Resampling.nearest
    ).astype(np.float64)
    ok = src.read_masks(1, out_shape=shape, resampling=Resampling.nearest) > 0
    ok &= np.isfinite(data).all(axis=0)
    if not ok.any():
        raise ImageryError(f"{src.name}: no valid pixels (nodata everywhere)")
    lo = np.array([np.percentile(b[ok], 2) for b in data], np.float32)
    hi = np.array([np.percentile(b[ok], 98) for b in data], np.float32)
    return lo, hi


def _merc_resolution(src: Any, grid: Any, crs: Any) -> float:
    """Web Mercator metres per pixel at the raster's middle (the square root of a pixel's
    area there), its pixels placed by ``grid`` (an affine map) in ``crs``."""
    from rasterio.warp import transform

    c, r = src.width / 2.0, src.height / 2.0
    cols, rows = [c, c + 1.0, c], [r, r, r + 1.0]
    xs, ys = zip(*(grid @ (cc, rr) for cc, rr in zip(cols, rows, strict=True)), strict=True)
    mx, my = transform(crs, _MERCATOR, list(xs), list(ys))
    ax, ay = mx[1] - mx[0], my[1] - my[0]
    bx, by = mx[2] - mx[0], my[2] - my[0]
    area = abs(ax * by - ay * bx)
    if not math.isfinite(area) or area <= 0.0:
        raise ImageryError(f"{src.name}: its pixels have no size in Web Mercator")
    return math.sqrt(area)
