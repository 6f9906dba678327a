"""Camera, frustum, screen-space size and error, tile selection. Pure: no IO, no GL, no threads."""

from lodscape.lod.camera import Camera

__all__ = ["Camera"]
