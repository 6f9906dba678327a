"""Imagery layers: the user's imagery at its own levels, apart from the terrain's tiles.

A layer wraps an ``ImageryFetcher`` (a tile server, an MBTiles file, a folder, a local raster)
with what a frame needs to know of it: its levels, and what went wrong. Every failure is counted
by kind, and the first of each kind is said once on stderr with the tile's URL or file, so a
server that answers 404, 500, HTML or nothing at all is never silently replaced by the tint. A
server that times out or cannot be reached is left alone for ``cooldown`` seconds (its tiles
fail at once meanwhile, counted): one hung server costs a render one timeout, not one per tile.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from lodscape.imagery.sources import (
    DirectorySource,
    HttpSource,
    ImageryError,
    ImageryFetcher,
    MBTilesSource,
    TileCache,
)

__all__ = ["MAX_OVERLAYS", "ImageryLayer", "open_layer", "server_figures", "warn_stderr"]

#: Imagery layers a scene can draw over the terrain's own texture (the terrain shaders' units).
MAX_OVERLAYS = 4

#: What each failure kind is called in a warning.
KINDS = {
    "missing": "tiles missing (404 / not stored)",
    "http": "error answers",
    "not-image": "answers that are not images",
    "cut-short": "answers cut short",
    "unreachable": "cannot connect",
    "timeout": "no answer in time",
    "read": "read errors",
    "error": "errors",
}


def warn_stderr(message: str) -> None:
    print(f"lodscape: {message}", file=sys.stderr, flush=True)


class ImageryLayer:
    """One imagery layer: its fetcher, its levels, and its failures. Thread-safe."""

    def __init__(
        self,
        fetcher: ImageryFetcher,
        *,
        index: int,
        warn: Callable[[str], None] = warn_stderr,
        cooldown: float = 30.0,
    ) -> None:
        self.fetcher = fetcher
        #: Its key layer (1..MAX_LAYERS), bottom to top.
        self.index = index
        self.name = fetcher.name
        self.min_zoom = int(fetcher.min_zoom)
        self.max_zoom = int(fetcher.max_zoom)
        self.warn = warn
        self.cooldown = cooldown
        #: Failed tiles by kind since the layer was opened.
        self.failures: Counter[str] = Counter()
        #: Tiles drawn without this layer's own (an ancestor's, or none) because it failed.
        self._lock = threading.Lock()
        self._down: tuple[float, str, str] | None = None

    def fetch(self, z: int, x: int, y: int) -> bytes:
        """The tile's bytes (b"": nothing there, drawn transparent); ImageryError, counted and
        said once per kind, when it cannot be had."""
        if z < self.min_zoom or not self.fetcher.covers(z, x, y):
            return b""
        down = self._down
        if down is not None and time.monotonic() < down[0]:
            self._failed(down[1], f"{self.name}: skipped, {down[2]}")
            raise ImageryError(f"{self.name}: {down[2]}", down[1])
        try:
            return self.fetcher.fetch(z, x, y)
        except ImageryError as exc:
            if exc.kind in ("timeout", "unreachable"):
                self._down = (
                    time.monotonic() + self.cooldown,
                    exc.kind,
                    f"{KINDS[exc.kind]} (tiles skipped for {self.cooldown:g} s)",
                )
            self._failed(exc.kind, str(exc))
            raise

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        if not data:
            return np.zeros((1, 1, 4), np.uint8)
        try:
            return self.fetcher.decode(data, size)
        except ImageryError:
            raise
        except Exception as exc:  # Pillow's decoding errors come in several classes
            self._failed("not-image", f"{self.name}: {exc}")
            raise ImageryError(f"{self.name}: not an image ({exc})", "not-image") from None

    def _failed(self, kind: str, message: str) -> None:
        with self._lock:
            first = self.failures[kind] == 0
            self.failures[kind] += 1
        if first:
            self.warn(
                f"imagery layer {self.index} ({self.name}): {KINDS.get(kind, kind)}: {message}; "
                "an ancestor's tile or the layer below is drawn there (counted in --stats)"
            )

    @property
    def failed(self) -> int:
        return sum(self.failures.values())

    def close(self) -> None:
        self.fetcher.close()


def server_figures(layers: Sequence[ImageryLayer]) -> dict[str, int]:
    """Failed tiles, all layers together, and a tile server's own HTTP requests and retries
    (timeouts, 5xx, cut-short bodies: what the streamer's counts of tiles never see)."""
    fetchers = [layer.fetcher for layer in layers]
    return {
        "imagery_failed": sum(layer.failed for layer in layers),
        "http_requests": sum(int(getattr(f, "requests", 0)) for f in fetchers),
        "http_retries": sum(int(getattr(f, "retried", 0)) for f in fetchers),
    }


def open_layer(
    spec: str,
    index: int,
    *,
    cache_dir: str | os.PathLike[str] | None = None,
    max_zoom: int | None = None,
    timeout: float = 10.0,
    warn: Callable[[str], None] = warn_stderr,
    bands: tuple[int, ...] | None = None,
) -> ImageryLayer:
    """A layer from what a user typed: an XYZ URL template, an .mbtiles file, a folder of z/x/y
    tiles or a georeferenced raster (GeoTIFF…). ``max_zoom`` caps its levels (a template's
    default: 19); ``timeout`` is the seconds one tile of a server may take; ``bands`` (1-based
    red, green, blue) picks a raster's colour bands (default: its colour interpretation, else
    its first three, said once)."""
    fetcher: ImageryFetcher
    if spec.startswith(("http://", "https://")):
        cache = None if cache_dir is None else TileCache(Path(cache_dir) / "imagery-cache.sqlite")
        fetcher = HttpSource(
            spec,
            cache=cache,
            timeout=timeout,
            deadline=timeout,
            max_zoom=19 if max_zoom is None else max_zoom,
        )
    elif spec.lower().endswith((".mbtiles", ".lods")):
        fetcher = MBTilesSource(spec)
    elif os.path.isdir(spec):
        fetcher = DirectorySource(spec)
    elif os.path.exists(spec):
        from lodscape.imagery.raster import RasterImagery

        raster = RasterImagery(spec, bands=bands)
        for note in (raster.place_note, raster.band_note):
            if note is not None:
                warn(f"imagery layer {index}: {note}")
        if raster.needs_overviews:
            warn(
                f"imagery layer {index} ({spec}): a large raster without overviews; its coarse "
                f"levels read all of it, slowly (gdaladdo -r average {spec} adds them)"
            )
        fetcher = raster
    else:
        raise ImageryError(
            f"--imagery {spec!r}: no such file or folder, and not an http(s) URL template "
            "with {z}/{x}/{y}"
        )
    if max_zoom is not None:
        fetcher.max_zoom = min(int(fetcher.max_zoom), int(max_zoom))
    return ImageryLayer(fetcher, index=index, warn=warn)
