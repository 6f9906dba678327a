"""Drawing: uploads tile meshes to OpenGL and renders colour and view distance offscreen.

Imports moderngl, so the pure layers (``lodscape.geo``, ``lodscape.lod``) never import this.
"""

from __future__ import annotations

from lodscape.render._context import create_context
from lodscape.render.terrain_pass import DrawItem, DrawStats, Renderer

__all__ = ["DrawItem", "DrawStats", "Renderer", "create_context"]
