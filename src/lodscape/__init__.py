"""lodscape: huge 3D landscapes in real time, by choosing every frame the detail each tile needs.

The pure layers (``geo``, ``lod``) import without rasterio or OpenGL; the scene, which needs both,
loads on first use of ``lodscape.open`` or ``lodscape.Scene``.
"""

from __future__ import annotations

import os as _os
import typing as _typing

#: GDAL's block cache, in MB, unless the user chose one: GDAL's own default is 5 % of the RAM
#: (1.2 GB on a 24 GB machine), which a flight over new ground fills a block at a time, so the
#: process grows for the whole flight. Set before GDAL first reads it (at its first raster).
#: Tiles read small windows (of overviews, the file's or sidecar ones): 64 MB costs no time
#: on a 16385² DEM against 256 MB, and keeps 190 MB out of the peak.
_os.environ.setdefault("GDAL_CACHEMAX", "64")

from lodscape.errors import CameraError, LodscapeError, SourceError
from lodscape.lod.camera import Camera
from lodscape.lod.select import Selection, SelectOptions, select

if _typing.TYPE_CHECKING:
    from lodscape.globe import Globe, GlobeOptions
    from lodscape.scene import FrameStats, Picture, Scene, SceneOptions
    from lodscape.sources import open

__version__ = "0.1.0"

__all__ = [
    "Camera",
    "CameraError",
    "FrameStats",
    "Globe",
    "GlobeOptions",
    "LodscapeError",
    "Picture",
    "Scene",
    "SceneOptions",
    "SelectOptions",
    "Selection",
    "SourceError",
    "__version__",
    "open",
    "select",
]

_LAZY = {"FrameStats", "Picture", "Scene", "SceneOptions", "open"}


def __getattr__(name: str) -> _typing.Any:
    if name == "open":
        from lodscape import sources

        return sources.open
    if name in _LAZY:
        from lodscape import scene

        return getattr(scene, name)
    if name in ("Globe", "GlobeOptions"):
        from lodscape import globe

        return getattr(globe, name)
    raise AttributeError(f"module 'lodscape' has no attribute {name!r}")
