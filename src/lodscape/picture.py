"""What a frame gives back to Python: a ``Picture`` (a notebook shows it inline) and a dataset's
``Capture`` (the picture with its depth, normals and labels)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.lod.camera import Camera

__all__ = ["Capture", "Picture"]


@dataclass(frozen=True, eq=False)
class Picture:
    """One rendered view: RGB (H, W, 3) uint8, its distance (H, W) float32 metres (inf: sky)
    and the camera. In a notebook it shows itself inline (``_repr_png_``)."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32]
    camera: Camera

    def png(self) -> bytes:
        """The picture as PNG bytes."""
        import io

        from PIL import Image

        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(self.rgb), "RGB").save(buf, "PNG")
        return buf.getvalue()

    def _repr_png_(self) -> bytes:
        return self.png()

    def __repr__(self) -> str:
        h, w = self.rgb.shape[:2]
        ground = float(np.isfinite(self.depth).mean()) if self.depth.size else 0.0
        c = self.camera
        return (
            f"Picture({w}x{h}, lon {c.lon:.5f} lat {c.lat:.5f} alt {c.alt:,.0f} m, "
            f"heading {c.heading:.0f} pitch {c.pitch:.0f}, ground {ground:.0%})"
        )


@dataclass(frozen=True, eq=False)
class Capture:
    """One view for a dataset (``Scene.capture``): RGB (H, W, 3) uint8; depth (H, W) float32,
    metres along the optical axis (inf: sky); normals (H, W, 3) float32, unit, in the camera's
    OpenCV frame (x right, y down, z ahead), facing the camera (0 where nothing is drawn);
    labels (H, W) uint8 (``render.labels.LABELS``); and the camera, its clip planes fitted."""

    rgb: NDArray[np.uint8]
    depth: NDArray[np.float32]
    normals: NDArray[np.float32]
    labels: NDArray[np.uint8]
    camera: Camera
