"""The GLSL of the passes, shipped as files beside the package (``render/shaders/*.glsl``)."""

from __future__ import annotations

import functools
from importlib import resources

__all__ = ["shader"]


@functools.cache
def shader(name: str) -> str:
    """The source of ``shaders/NAME`` (read once a process)."""
    return (resources.files("lodscape.render") / "shaders" / name).read_text(encoding="utf-8")
