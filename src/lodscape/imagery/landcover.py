"""Ground coloured from a land-cover mask (paper 001): OpenStreetMap land use and natural areas,
and roads as strips of their width, rasterised per tile into 8-bit class masks; the renderer
picks and blends a few small repeating ground materials by the mask (``render`` holds the
material array), so the ground needs one byte per texel instead of a pre-baked colour image.

Classes are painted in ``CLASSES`` order, later over earlier (water over grass, roads over
everything); within a class, smaller areas over larger. Texel value 0 is plain ground (nothing
mapped); ``NODATA`` where the terrain has no data.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
from numpy.typing import NDArray

from lodscape.errors import SourceError
from lodscape.geo.tiles import Tile, lonlat_to_merc, xy_bounds

__all__ = ["CLASSES", "NODATA", "ROAD_WIDTHS", "Landcover", "classify", "read_landcover"]

#: Class names by mask value, in painting order (value 0: nothing mapped).
CLASSES: tuple[str, ...] = (
    "ground",
    "residential",
    "industrial",
    "farmland",
    "grass",
    "forest",
    "wetland",
    "sand",
    "rock",
    "water",
    "paved",
    "road",
)
#: Mask value where the terrain has no data.
NODATA = 255

_TAGS: dict[tuple[str, str], str] = {}
for _cls, _pairs in {
    "residential": [("landuse", v) for v in ("residential", "retail", "commercial", "education")],
    "industrial": [
        ("landuse", v) for v in ("industrial", "railway", "construction", "brownfield", "port")
    ],
    "farmland": [
        ("landuse", v)
        for v in (
            "farmland",
            "orchard",
            "vineyard",
            "allotments",
            "farmyard",
            "greenhouse_horticulture",
        )
    ],
    "grass": [("landuse", v) for v in ("grass", "meadow", "village_green", "recreation_ground")]
    + [("leisure", v) for v in ("park", "garden", "golf_course", "pitch", "playground", "dog_park")]
    + [("natural", v) for v in ("grassland", "heath", "scrub", "fell")]
    + [("landuse", "cemetery")],
    "forest": [("landuse", "forest"), ("natural", "wood")],
    "wetland": [("natural", "wetland")],
    "sand": [("natural", "sand"), ("natural", "beach"), ("leisure", "beach_resort")],
    "rock": [("natural", v) for v in ("bare_rock", "scree", "shingle", "glacier")]
    + [("landuse", "quarry")],
    "water": [
        ("natural", "water"),
        ("waterway", "riverbank"),
        ("landuse", "reservoir"),
        ("landuse", "basin"),
        ("natural", "bay"),
    ],
    "paved": [
        ("amenity", "parking"),
        ("highway", "pedestrian"),
        ("place", "square"),
        ("area:highway", "yes"),
        ("amenity", "marketplace"),
        ("aeroway", "apron"),
    ],
}.items():
    for _pair in _pairs:
        _TAGS[_pair] = _cls

#: Metres of road surface by ``highway`` value (lines; ``width`` wins where tagged). Paths and
#: footways are painted as paved.
ROAD_WIDTHS: dict[str, float] = {
    "motorway": 14.0,
    "trunk": 12.0,
    "primary": 10.0,
    "secondary": 9.0,
    "tertiary": 8.0,
    "unclassified": 6.0,
    "residential": 6.0,
    "service": 4.0,
    "living_street": 5.0,
    "motorway_link": 7.0,
    "trunk_link": 7.0,
    "primary_link": 7.0,
    "secondary_link": 6.0,
    "tertiary_link": 6.0,
    "pedestrian": 6.0,
    "footway": 2.5,
    "path": 2.0,
    "cycleway": 2.5,
    "track": 3.0,
    "steps": 2.0,
}
_PAVED_LINES = {"pedestrian", "footway", "path", "cycleway", "steps"}


def classify(tags: dict[str, str]) -> str | None:
    """The land-cover class of an area's tags, or None."""
    for (k, v), cls in _TAGS.items():
        if tags.get(k) == v:
            return cls
    if "water" in tags and tags.get("natural") != "dry":
        return "water"
    return None


@dataclass
class Landcover:
    """Land-cover shapes in Web Mercator metres, by class, and a spatial index over them."""

    name: str
    #: (shape, class value) in painting order.
    shapes: list[tuple[shapely.Geometry, int]]
    counts: dict[str, int] = field(default_factory=dict)
    skipped: int = 0

    def __post_init__(self) -> None:
        self._tree = shapely.STRtree([g for g, _ in self.shapes])
        self._tree.query(shapely.box(0, 0, 0, 0))  # GEOS builds the tree on first query: here
        self._local = threading.local()

    def _prepared(self, i: int) -> shapely.Geometry:
        """Shape ``i`` prepared for this thread. GEOS builds a prepared shape's point index
        lazily on first use, and two threads doing that at once corrupt the heap (shapely
        releases the GIL), so each thread tests points against its own prepared copy."""
        mine: dict[int, shapely.Geometry] | None = getattr(self._local, "shapes", None)
        if mine is None:
            mine = self._local.shapes = {}
        geom = mine.get(i)
        if geom is None:
            geom = mine[i] = shapely.from_wkb(shapely.to_wkb(self.shapes[i][0]))
            shapely.prepare(geom)
        return geom

    def mask(self, z: int, x: int, y: int, size: int = 256) -> NDArray[np.uint8]:
        """(size, size) class values of tile z/x/y (row 0 north): each texel the last shape in
        painting order that holds its centre."""
        b = xy_bounds(Tile(x, y, z))
        hits = self._tree.query(shapely.box(b.left, b.bottom, b.right, b.top))
        out = np.zeros((size, size), np.uint8)
        res = (b.right - b.left) / size
        for i in np.sort(hits):  # painting order
            geom, value = self.shapes[i]
            w, s_, e, n = geom.bounds
            # the texels whose centres the shape's box can hold
            c0 = max(int(np.floor((w - b.left) / res - 0.5)) + 1, 0)
            c1 = min(int(np.floor((e - b.left) / res - 0.5)), size - 1)
            r0 = max(int(np.floor((b.top - n) / res - 0.5)) + 1, 0)
            r1 = min(int(np.floor((b.top - s_) / res - 0.5)), size - 1)
            if c0 > c1 or r0 > r1:
                continue
            xs = b.left + (np.arange(c0, c1 + 1) + 0.5) * res
            ys = b.top - (np.arange(r0, r1 + 1) + 0.5) * res
            inside = shapely.contains_xy(self._prepared(int(i)), xs[None, :], ys[:, None])
            out[r0 : r1 + 1, c0 : c1 + 1][inside] = value
        return out


def _merc(geom: shapely.Geometry) -> shapely.Geometry:
    def fn(c: NDArray[np.float64]) -> NDArray[np.float64]:
        xm, ym = lonlat_to_merc(c[:, 0], c[:, 1])
        return np.column_stack([xm, ym])

    return shapely.transform(geom, fn)


def _width(tags: dict[str, str], kind: str) -> float:
    w = tags.get("width")
    if w:
        try:
            v = float(w.replace(",", ".").replace("m", "").strip())
            if 0.5 <= v <= 100.0:
                return v
        except ValueError:
            pass
    return ROAD_WIDTHS[kind]


def read_landcover(path: str | Path) -> Landcover:
    """Land use, natural areas and roads of an OSM file (.osm.pbf, .osm)."""
    import osmium

    p = Path(path)
    name = str(path)
    if not p.is_file():
        raise SourceError(f"{name}: no such file")
    wkb = osmium.geom.WKBFactory()
    found: list[tuple[int, float, shapely.Geometry]] = []
    counts: dict[str, int] = {}
    skipped = 0
    value = {c: i for i, c in enumerate(CLASSES)}

    class _Handler(osmium.SimpleHandler):  # type: ignore[misc]
        def area(self, a: osmium.osm.Area) -> None:
            nonlocal skipped
            tags = {t.k: t.v for t in a.tags}
            cls = classify(tags)
            if cls is None:
                return
            try:
                geom = shapely.from_wkb(bytes.fromhex(wkb.create_multipolygon(a)))
            except (RuntimeError, shapely.errors.GEOSException):
                skipped += 1
                return
            if not geom.is_valid:
                geom = shapely.make_valid(geom)
            geom = _merc(geom)
            found.append((value[cls], -float(geom.area), geom))
            counts[cls] = counts.get(cls, 0) + 1

        def way(self, w: osmium.osm.Way) -> None:
            nonlocal skipped
            kind = w.tags.get("highway")
            if kind not in ROAD_WIDTHS or w.tags.get("area") == "yes":
                return
            try:
                coords = [(n.lon, n.lat) for n in w.nodes]
            except osmium.InvalidLocationError:
                skipped += 1
                return
            if len(coords) < 2:
                return
            tags = {t.k: t.v for t in w.tags}
            lat = coords[0][1]
            line = _merc(shapely.LineString(coords))
            # metres on the ground are 1/cos(lat) Mercator metres
            half = 0.5 * _width(tags, kind) / max(math.cos(math.radians(lat)), 0.01)
            cls = "paved" if kind in _PAVED_LINES else "road"
            found.append((value[cls], 0.0, line.buffer(half, cap_style="flat")))
            counts[cls] = counts.get(cls, 0) + 1

    try:
        _Handler().apply_file(str(p), locations=True, idx="flex_mem")
    except RuntimeError as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SourceError(f"{name}: not a readable OpenStreetMap file ({msg})") from None
    if not found:
        raise SourceError(f"{name}: no land use, natural areas or roads in the file")
    found.sort(key=lambda t: (t[0], t[1]))
    return Landcover(name, [(g, v) for v, _, g in found], counts, skipped)


#: Per class: base colour (0..1) and the pattern of its ground material.
GROUND: dict[str, tuple[tuple[float, float, float], str]] = {
    "ground": ((0.55, 0.55, 0.40), "mottled"),
    "residential": ((0.62, 0.62, 0.55), "mottled"),
    "industrial": ((0.58, 0.57, 0.55), "slabs"),
    "farmland": ((0.62, 0.58, 0.36), "furrows"),
    "grass": ((0.36, 0.55, 0.26), "blades"),
    "forest": ((0.18, 0.34, 0.16), "canopy"),
    "wetland": ((0.30, 0.42, 0.32), "mottled"),
    "sand": ((0.86, 0.79, 0.60), "grain"),
    "rock": ((0.55, 0.54, 0.52), "canopy"),
    "water": ((0.20, 0.36, 0.52), "ripples"),
    "paved": ((0.66, 0.65, 0.63), "slabs"),
    "road": ((0.30, 0.30, 0.32), "grain"),
}


def ground_layers(size: int = 128) -> NDArray[np.uint8]:
    """(len(CLASSES), size, size, 4) RGBA ground materials, one layer per class, tileable:
    generated from a few rules (seeded noise, slabs, furrows, ripples), the same every run."""
    import zlib

    out = np.empty((len(CLASSES), size, size, 4), np.uint8)
    v, u = (np.mgrid[0:size, 0:size] + 0.5) / size
    for i, name in enumerate(CLASSES):
        colour, pattern = GROUND[name]
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        noise = np.zeros((size, size))
        for f in (1, 2, 4, 8, 16, 32):
            ph = rng.uniform(0.0, 2.0 * np.pi, 4)
            noise += (
                np.sin(2 * np.pi * f * u + ph[0]) * np.sin(2 * np.pi * f * v + ph[1])
                + np.sin(2 * np.pi * f * (u + v) + ph[2])
            ) / f
        noise /= max(float(np.abs(noise).max()), 1e-9)
        shade = 1.0 + 0.12 * noise
        if pattern == "slabs":
            shade *= np.where(
                (np.abs((u * 4 + 0.5) % 1 - 0.5) < 0.03) | (np.abs((v * 4 + 0.5) % 1 - 0.5) < 0.03),
                0.85,
                1.0,
            )
        elif pattern == "furrows":
            shade *= 0.9 + 0.1 * np.cos(2 * np.pi * 16 * u)
        elif pattern == "blades":
            shade *= 1.0 + 0.08 * np.sin(2 * np.pi * 32 * (u + 0.3 * noise))
        elif pattern == "canopy":
            shade = 1.0 + 0.25 * noise
        elif pattern == "ripples":
            shade *= 1.0 + 0.05 * np.sin(2 * np.pi * (8 * v + 2 * noise))
        rgb = np.asarray(colour)[None, None, :] * shade[..., None]
        out[i, ..., :3] = np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
        out[i, ..., 3] = 255
    return out
