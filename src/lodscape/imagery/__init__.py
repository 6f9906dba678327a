"""Imagery sources: one RGB texture per OSM tile z/x/y. The offline default tints the heights."""

from lodscape.imagery.tint import HeightSourceLike, TintImagery

__all__ = ["HeightSourceLike", "TintImagery"]
