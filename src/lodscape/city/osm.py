"""City objects from an OpenStreetMap file's attributes (paper 001): buildings and street objects.

Buildings come from closed ways and multipolygon relations tagged ``building`` (pyosmium's area
assembler builds the rings; holes are kept). Heights follow OSM's conventions: ``height`` is the
whole height above the ground, roof included; without it ``building:levels`` × 3 m gives the walls
and the roof sits on top; without either a documented default per building type (``DEFAULTS``).
``min_height`` / ``building:min_level`` lift the walls' base (bridges, overhangs). ``roof:shape``
flat, gabled, hipped and pyramidal are built; other shapes are drawn flat and counted.

Footprints that are not valid polygons are repaired (shapely ``make_valid``, counted); those that
cannot be (no area, a missing node, fewer than three points) are skipped with a count per reason,
never an exception. Trees (``natural=tree``), street lamps (``highway=street_lamp``) and benches
(``amenity=bench`` / ``leisure=picnic_table``) become instances of a few shared models.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import shapely
from shapely.geometry import MultiPolygon, Polygon

from lodscape.errors import CityError

__all__ = [
    "DEFAULTS",
    "LEVEL_HEIGHT",
    "Building",
    "City",
    "Feature",
    "parse_length",
    "parse_levels",
    "read_osm",
]

#: Metres per storey.
LEVEL_HEIGHT = 3.0
#: Storeys (walls only) of a building without height or levels, by its ``building`` value.
DEFAULTS: dict[str, float] = {
    "yes": 3,
    "house": 2,
    "detached": 2,
    "semidetached_house": 2,
    "terrace": 2,
    "residential": 4,
    "apartments": 5,
    "dormitory": 4,
    "hotel": 6,
    "commercial": 4,
    "office": 5,
    "retail": 2,
    "supermarket": 1.5,
    "industrial": 3,
    "warehouse": 3,
    "school": 3,
    "university": 4,
    "hospital": 5,
    "public": 4,
    "civic": 3,
    "government": 4,
    "church": 5,
    "chapel": 2,
    "cathedral": 8,
    "mosque": 4,
    "temple": 3,
    "train_station": 3,
    "transportation": 2,
    "garage": 1,
    "garages": 1,
    "carport": 1,
    "shed": 1,
    "hut": 1,
    "cabin": 1,
    "kiosk": 1,
    "toilets": 1,
    "service": 1,
    "utility": 1,
    "roof": 1.5,
    "pavilion": 1,
    "greenhouse": 1,
    "glasshouse": 1,
    "tower": 10,
    "block": 4,
    "atrium": 4,
}
#: Wall material by building type (everything else is "plaster").
WALLS: dict[str, str] = {
    "church": "stone",
    "chapel": "stone",
    "cathedral": "stone",
    "industrial": "metal",
    "warehouse": "metal",
    "garage": "concrete",
    "garages": "concrete",
    "shed": "wood",
    "hut": "wood",
    "cabin": "wood",
    "kiosk": "wood",
    "house": "brick",
    "detached": "brick",
    "terrace": "brick",
    "office": "glass",
    "commercial": "glass",
    "greenhouse": "glass",
    "glasshouse": "glass",
}
#: building:material / roof:material values, folded into the materials lodscape draws.
MATERIAL_ALIASES: dict[str, str] = {
    "brick": "brick",
    "stone": "stone",
    "sandstone": "stone",
    "limestone": "stone",
    "granite": "stone",
    "concrete": "concrete",
    "cement_block": "concrete",
    "plaster": "plaster",
    "stucco": "plaster",
    "glass": "glass",
    "mirror": "glass",
    "metal": "metal",
    "steel": "metal",
    "copper": "copper",
    "tin": "metal",
    "zinc": "metal",
    "wood": "wood",
    "timber_framing": "wood",
    "roof_tiles": "tiles",
    "tiles": "tiles",
    "tile": "tiles",
    "slate": "slate",
    "gravel": "concrete",
    "tar_paper": "roofing",
    "asphalt": "roofing",
    "eternit": "roofing",
}
ROOF_SHAPES = ("flat", "gabled", "hipped", "pyramidal")
#: Street objects: (key, value) → the model they are drawn with.
FEATURES: dict[tuple[str, str], str] = {
    ("natural", "tree"): "tree",
    ("highway", "street_lamp"): "street_lamp",
    ("amenity", "bench"): "bench",
    ("leisure", "picnic_table"): "bench",
}


@dataclass(frozen=True, eq=False)
class Building:
    """One building: its footprint (lon/lat degrees, holes kept) and what its tags say."""

    osm_id: str
    footprint: Polygon
    #: Metres from the ground to the top of the roof.
    height: float
    #: Metres from the ground to the bottom of the walls.
    min_height: float
    roof_shape: str
    #: Metres from the eaves to the top of the roof (0 for flat roofs).
    roof_height: float
    kind: str
    wall_material: str
    roof_material: str
    #: Where the height came from: "height", "levels" or "default".
    height_from: str


@dataclass(frozen=True)
class Feature:
    """A street object drawn as an instance of a shared model."""

    kind: str
    lon: float
    lat: float
    #: Metres, when tagged.
    height: float | None = None


@dataclass
class City:
    """Everything read from one OSM file, and what had to be repaired or skipped."""

    name: str
    buildings: list[Building]
    features: list[Feature]
    repaired: int = 0
    skipped: Counter[str] = field(default_factory=Counter)
    multipolygons: int = 0
    holes: int = 0
    #: Roof shapes tagged but not built (drawn flat), by shape.
    other_roofs: Counter[str] = field(default_factory=Counter)

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north) of every object, degrees."""
        xs: list[float] = []
        ys: list[float] = []
        for b in self.buildings:
            w, s, e, n = b.footprint.bounds
            xs += [w, e]
            ys += [s, n]
        xs += [f.lon for f in self.features]
        ys += [f.lat for f in self.features]
        if not xs:
            raise CityError(f"{self.name}: no buildings, trees, lamps or benches in the file")
        return min(xs), min(ys), max(xs), max(ys)

    def merged(self, other: City) -> City:
        """This city and ``other`` as one (their counts added)."""
        return City(
            f"{self.name} + {other.name}",
            self.buildings + other.buildings,
            self.features + other.features,
            self.repaired + other.repaired,
            self.skipped + other.skipped,
            self.multipolygons + other.multipolygons,
            self.holes + other.holes,
            self.other_roofs + other.other_roofs,
        )

    def skipped_note(self) -> str | None:
        """One line saying what was skipped and why (None: nothing was)."""
        n = sum(self.skipped.values())
        if not n:
            return None
        why = ", ".join(f"{reason}: {k}" for reason, k in self.skipped.most_common())
        return f"{self.name}: {n} OSM object{'s' if n > 1 else ''} skipped ({why})"

    def report(self) -> dict[str, object]:
        kinds = Counter(f.kind for f in self.features)
        return {
            "buildings": len(self.buildings),
            "multipolygons": self.multipolygons,
            "holes": self.holes,
            "repaired": self.repaired,
            "skipped": dict(self.skipped),
            "heights": dict(Counter(b.height_from for b in self.buildings)),
            "roofs": dict(Counter(b.roof_shape for b in self.buildings)),
            "roofs_drawn_flat": dict(self.other_roofs),
            **{k: v for k, v in sorted(kinds.items())},
        }


_NUMBER = re.compile(r"^\s*([-+]?\d+(?:[.,]\d+)?)\s*(m|meters?|metres?|ft|feet|')?\s*$", re.I)
_FEET_INCHES = re.compile(r"^\s*(\d+)\s*'\s*(\d+(?:\.\d+)?)\s*\"\s*$")


def parse_length(value: str | None) -> float | None:
    """An OSM length in metres ("12", "12.5 m", "12,5", "40 ft", "40'", "6'5\"");
    None when absent, unparsable, negative or absurd (over 1,000 m)."""
    if value is None:
        return None
    m = _FEET_INCHES.match(value)
    if m:
        out = (float(m.group(1)) * 12.0 + float(m.group(2))) * 0.0254
    else:
        m = _NUMBER.match(value)
        if not m:
            return None
        out = float(m.group(1).replace(",", "."))
        if m.group(2) and m.group(2).lower() in ("ft", "feet", "'"):
            out *= 0.3048
    return out if 0.0 <= out <= 1000.0 and math.isfinite(out) else None


def parse_levels(value: str | None) -> float | None:
    """A storey count ("3", "3.5", "2;4": the largest); None when absent or unparsable."""
    if value is None:
        return None
    best = None
    for part in value.replace(",", ";").split(";"):
        try:
            v = float(part.strip())
        except ValueError:
            continue
        if 0.0 <= v <= 300.0 and (best is None or v > best):
            best = v
    return best


def _material(value: str | None, fallback: str) -> str:
    if value is None:
        return fallback
    return MATERIAL_ALIASES.get(value.strip().lower(), fallback)


def building_from_tags(osm_id: str, footprint: Polygon, tags: dict[str, str]) -> Building:
    """A building's heights, roof and materials from its tags (OSM's Simple 3D Buildings)."""
    kind = tags.get("building", "yes")
    shape = (tags.get("roof:shape") or "flat").strip().lower()
    height = parse_length(tags.get("height"))
    levels = parse_levels(tags.get("building:levels"))
    roof_levels = parse_levels(tags.get("roof:levels"))
    roof_h = parse_length(tags.get("roof:height"))
    min_h = parse_length(tags.get("min_height"))
    if min_h is None:
        min_level = parse_levels(tags.get("building:min_level"))
        min_h = min_level * LEVEL_HEIGHT if min_level is not None else 0.0
    sloped = shape in ("gabled", "hipped", "pyramidal")
    if roof_h is None and roof_levels is not None:
        roof_h = roof_levels * LEVEL_HEIGHT
    if roof_h is None and sloped:
        # a 30° pitch over the footprint's narrow side: half of it times tan 30°
        rect = footprint_rectangle_metres(footprint)
        roof_h = 0.5 * min(rect) * math.tan(math.radians(30.0))
    roof_h = roof_h if sloped and roof_h is not None else 0.0
    if height is not None:
        source = "height"
    elif levels is not None:
        source = "levels"
        height = levels * LEVEL_HEIGHT + roof_h
    else:
        source = "default"
        height = DEFAULTS.get(kind, 3.0) * LEVEL_HEIGHT + roof_h
    height = max(height, min_h + 0.5)
    roof_h = min(roof_h, 0.9 * (height - min_h))
    if shape not in ROOF_SHAPES:
        shape = "flat"
    walls = _material(tags.get("building:material"), WALLS.get(kind, "plaster"))
    default_roof = "tiles" if sloped else "roofing"
    roof = _material(tags.get("roof:material"), default_roof)
    return Building(osm_id, footprint, height, min_h, shape, roof_h, kind, walls, roof, source)


def footprint_rectangle_metres(footprint: Polygon) -> tuple[float, float]:
    """Sides (metres) of the footprint's smallest rotated rectangle (lon/lat scaled locally)."""
    lat = footprint.centroid.y
    k = 111_320.0
    scaled = shapely.affinity.scale(
        footprint, k * math.cos(math.radians(lat)), k, origin=(0.0, 0.0)
    )
    rect = shapely.minimum_rotated_rectangle(scaled)
    c = list(rect.exterior.coords) if isinstance(rect, Polygon) else [(0.0, 0.0)] * 3
    a = math.dist(c[0], c[1])
    b = math.dist(c[1], c[2])
    return (a, b) if a >= b else (b, a)


def _polygons(geom: shapely.Geometry) -> list[Polygon]:
    if isinstance(geom, Polygon):
        return [geom]
    if isinstance(geom, MultiPolygon):
        return list(geom.geoms)
    if hasattr(geom, "geoms"):
        out: list[Polygon] = []
        for g in geom.geoms:
            out += _polygons(g)
        return out
    return []


#: Footprints smaller than this (square degrees ~ 0.5 m² at the equator) are noise.
_MIN_AREA = 4e-11


def read_osm(path: str | Path) -> City:
    """Buildings and street objects of an OSM file (.osm.pbf, .osm, .osm.bz2…)."""
    import osmium

    p = Path(path)
    name = str(path)
    if not p.is_file():
        raise CityError(f"{name}: no such file")
    city = City(name, [], [])
    wkb = osmium.geom.WKBFactory()
    building_relations: set[int] = set()
    assembled: set[int] = set()

    class _Handler(osmium.SimpleHandler):  # type: ignore[misc]
        def node(self, n: osmium.osm.Node) -> None:
            for (k, v), kind in FEATURES.items():
                if n.tags.get(k) == v:
                    if not n.location.valid():
                        city.skipped["feature without a location"] += 1
                        return
                    h = parse_length(n.tags.get("height"))
                    city.features.append(Feature(kind, n.location.lon, n.location.lat, h))
                    return

        def relation(self, r: osmium.osm.Relation) -> None:
            if r.tags.get("type") == "multipolygon" and "building" in r.tags:
                building_relations.add(r.id)

        def way(self, w: osmium.osm.Way) -> None:
            # closed ways are read here, not by the area assembler, which drops the rings it
            # cannot assemble (a bow-tie) where make_valid can still save them
            tags = {t.k: t.v for t in w.tags}
            if "building" not in tags or tags.get("building") == "no":
                return
            nodes = w.nodes
            if len(nodes) < 4 or nodes[0].ref != nodes[len(nodes) - 1].ref:
                city.skipped["not a closed ring"] += 1
                return
            try:
                coords = [(n.lon, n.lat) for n in nodes]
            except osmium.InvalidLocationError:
                city.skipped["missing node"] += 1
                return
            _add_building(city, f"w{w.id}", Polygon(coords), tags, multipolygon=False)

        def area(self, a: osmium.osm.Area) -> None:
            if a.from_way():
                return
            tags = {t.k: t.v for t in a.tags}
            if "building" not in tags or tags.get("building") == "no":
                return
            osm_id = f"r{a.orig_id()}"
            assembled.add(a.orig_id())
            try:
                geom = shapely.from_wkb(bytes.fromhex(wkb.create_multipolygon(a)))
            except (RuntimeError, shapely.errors.GEOSException):
                city.skipped["broken ring"] += 1
                return
            _add_building(city, osm_id, geom, tags, multipolygon=not a.from_way())

    handler = _Handler()
    try:
        handler.apply_file(str(p), locations=True, idx="flex_mem")
    except RuntimeError as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CityError(f"{name}: not a readable OpenStreetMap file ({msg})") from None
    lost = len(building_relations - assembled)
    if lost:
        city.skipped["multipolygon that does not close"] += lost
    if not city.buildings and not city.features:
        raise CityError(f"{name}: no buildings, trees, street lamps or benches in the file")
    return city


def _add_building(
    city: City, osm_id: str, geom: shapely.Geometry, tags: dict[str, str], *, multipolygon: bool
) -> None:
    if geom.is_empty:
        city.skipped["empty footprint"] += 1
        return
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
        city.repaired += 1
    parts = [g for g in _polygons(geom) if g.area > _MIN_AREA]
    if not parts:
        city.skipped["no area"] += 1
        return
    if multipolygon:
        city.multipolygons += 1
    shape = (tags.get("roof:shape") or "flat").strip().lower()
    if shape not in ROOF_SHAPES:
        city.other_roofs[shape] += 1
    for i, part in enumerate(parts):
        part = shapely.geometry.polygon.orient(part, 1.0)
        city.holes += len(part.interiors)
        pid = osm_id if len(parts) == 1 else f"{osm_id}.{i}"
        city.buildings.append(building_from_tags(pid, part, tags))
