"""The exceptions lodscape raises for bad input; the CLI prints their message as one line."""

from __future__ import annotations

__all__ = ["CameraError", "CityError", "LodscapeError", "SourceError"]


class LodscapeError(Exception):
    """Base of every error caused by the user's input (files, cameras, options)."""


class SourceError(LodscapeError, ValueError):
    """A height or imagery source cannot be opened or read; the message names the input."""


class CameraError(LodscapeError, ValueError):
    """A camera is invalid (NaN, under the ground, zero-sized viewport…)."""


class CityError(LodscapeError, ValueError):
    """A city file (OpenStreetMap .osm.pbf / .osm) cannot be read; the message names it."""
