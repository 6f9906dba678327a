"""Cities kept in a tileset (paper 000's relational store holds objects beside tiles).

Tables, made by the first ``add_city``:
- ``city_sets`` (name, source, report): each city added, the file it came from and what reading
  it found (repairs, skips);
- ``city_buildings``: one row per building, its footprint as WKB (lon/lat degrees) and its tags
  as read (heights, roof, materials);
- ``city_features``: one row per street object (kind, lon, lat, height);
- ``city_building_index`` / ``city_feature_index``: SQLite R*Tree indexes of their bounds, so
  ``read_city`` with a box reads only what lies in it.

Objects are stored as read, not placed: their bases are found on whichever terrain the tileset
draws when the city is loaded. Each add or remove is one transaction: a city is in the file
whole or not at all.
"""

from __future__ import annotations

import json
import os
import sqlite3
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import shapely
from shapely.geometry import Polygon

from lodscape.city.osm import Building, City, Feature
from lodscape.store.manifest import (
    TilesetError,
    connect_readonly,
    fold_wal,
    is_tileset,
    read_manifest,
)

__all__ = ["add_city", "list_cities", "read_city", "remove_city"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS city_sets (
    name TEXT PRIMARY KEY, source TEXT NOT NULL, report TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS city_buildings (
    id INTEGER PRIMARY KEY, city TEXT NOT NULL, osm_id TEXT NOT NULL, footprint BLOB NOT NULL,
    height REAL NOT NULL, min_height REAL NOT NULL, roof_shape TEXT NOT NULL,
    roof_height REAL NOT NULL, kind TEXT NOT NULL, wall_material TEXT NOT NULL,
    roof_material TEXT NOT NULL, height_from TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS city_features (
    id INTEGER PRIMARY KEY, city TEXT NOT NULL, kind TEXT NOT NULL, lon REAL NOT NULL,
    lat REAL NOT NULL, height REAL);
CREATE VIRTUAL TABLE IF NOT EXISTS city_building_index USING rtree(id, w, e, s, n);
CREATE VIRTUAL TABLE IF NOT EXISTS city_feature_index USING rtree(id, w, e, s, n);
CREATE INDEX IF NOT EXISTS city_buildings_city ON city_buildings (city);
CREATE INDEX IF NOT EXISTS city_features_city ON city_features (city);
"""

Box = tuple[float, float, float, float]


def _open_rw(path: str | os.PathLike[str]) -> sqlite3.Connection:
    p = Path(path)
    if not p.is_file():
        raise TilesetError(f"{p}: no such file")
    if not is_tileset(p):
        raise TilesetError(f"{p}: not a lodscape tileset (not an SQLite file)")
    connect_readonly(p).close()  # undoes a hot journal an older lodscape may have left
    db = sqlite3.connect(p, isolation_level=None, timeout=30.0)
    try:
        manifest = read_manifest(db, str(p))
    except TilesetError:
        db.close()
        raise
    if not manifest.get("complete"):
        db.close()
        raise TilesetError(f"{p}: its build has not finished; finish it before adding a city")
    # a write-ahead log while writing: readers (a running serve) never wait for the writer, and
    # a writer killed mid-transaction leaves nothing a read-only reader must undo
    db.execute("PRAGMA journal_mode=WAL")
    return db


@contextmanager
def _transaction(db: sqlite3.Connection) -> Iterator[None]:
    """BEGIN IMMEDIATE … COMMIT, rolled back on any error."""
    db.execute("BEGIN IMMEDIATE")
    try:
        yield
        db.execute("COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        raise


def _has_tables(db: sqlite3.Connection) -> bool:
    row = db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'city_sets'"
    ).fetchone()
    return row is not None


def add_city(
    path: str | os.PathLike[str],
    city: City,
    *,
    name: str | None = None,
    replace: bool = False,
    bounds: Box | None = None,
    then: Callable[[sqlite3.Connection], object] | None = None,
) -> dict[str, int]:
    """Store ``city`` in the tileset at ``path`` under ``name`` (its file's name by default),
    all in one transaction. With ``bounds`` (west, south, east, north) only objects that touch
    it are kept, and a city wholly outside is refused. ``then(db)`` runs inside the
    transaction once the city is in (``store.city_tiles.store_city_tiles``: its 3D Tiles made
    and kept with it). Returns what was stored."""
    name = name or Path(city.name).name
    db = _open_rw(path)
    try:
        kept_b = city.buildings
        kept_f = city.features
        if bounds is not None:
            w, s, e, n = bounds
            box = shapely.box(w, s, e, n)
            kept_b = [b for b in kept_b if b.footprint.intersects(box)]
            kept_f = [f for f in kept_f if w <= f.lon <= e and s <= f.lat <= n]
            if not kept_b and not kept_f:
                raise TilesetError(
                    f"{city.name}: no object lies inside {Path(path).name}'s bounds "
                    f"({w:.5f}, {s:.5f}, {e:.5f}, {n:.5f}); is it the right place?"
                )
        outside = len(city.buildings) - len(kept_b) + len(city.features) - len(kept_f)
        report = {**city.report(), "outside_tileset": outside}
        with _transaction(db):
            # one statement at a time: executescript would commit the transaction first
            for statement in _SCHEMA.split(";"):
                if statement.strip():
                    db.execute(statement)
            exists = db.execute("SELECT 1 FROM city_sets WHERE name = ?", (name,)).fetchone()
            if exists and not replace:
                raise TilesetError(
                    f"{path}: already holds a city named {name!r}; "
                    "use --replace, or --name for another"
                )
            if exists:
                _delete(db, name)
            db.execute(
                "INSERT INTO city_sets VALUES (?, ?, ?)",
                (name, str(city.name), json.dumps(report, sort_keys=True)),
            )
            for b in kept_b:
                cur = db.execute(
                    "INSERT INTO city_buildings (city, osm_id, footprint, height, min_height, "
                    "roof_shape, roof_height, kind, wall_material, roof_material, height_from) "
                    "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        name,
                        b.osm_id,
                        shapely.to_wkb(b.footprint),
                        b.height,
                        b.min_height,
                        b.roof_shape,
                        b.roof_height,
                        b.kind,
                        b.wall_material,
                        b.roof_material,
                        b.height_from,
                    ),
                )
                bw, bs, be, bn = b.footprint.bounds
                db.execute(
                    "INSERT INTO city_building_index VALUES (?, ?, ?, ?, ?)",
                    (cur.lastrowid, bw, be, bs, bn),
                )
            for f in kept_f:
                cur = db.execute(
                    "INSERT INTO city_features (city, kind, lon, lat, height) "
                    "VALUES (?, ?, ?, ?, ?)",
                    (name, f.kind, f.lon, f.lat, f.height),
                )
                db.execute(
                    "INSERT INTO city_feature_index VALUES (?, ?, ?, ?, ?)",
                    (cur.lastrowid, f.lon, f.lon, f.lat, f.lat),
                )
            if then is not None:
                then(db)
    except sqlite3.Error as exc:
        raise TilesetError(f"{path}: cannot store the city ({exc})") from None
    finally:
        fold_wal(db)
        db.close()
    return {
        "buildings": len(kept_b),
        "features": len(kept_f),
        "outside": outside,
    }


def _delete(db: sqlite3.Connection, name: str) -> None:
    db.execute(
        "DELETE FROM city_building_index "
        "WHERE id IN (SELECT id FROM city_buildings WHERE city = ?)",
        (name,),
    )
    db.execute(
        "DELETE FROM city_feature_index WHERE id IN (SELECT id FROM city_features WHERE city = ?)",
        (name,),
    )
    db.execute("DELETE FROM city_buildings WHERE city = ?", (name,))
    db.execute("DELETE FROM city_features WHERE city = ?", (name,))
    db.execute("DELETE FROM city_sets WHERE name = ?", (name,))


def remove_city(
    path: str | os.PathLike[str],
    name: str,
    then: Callable[[sqlite3.Connection], object] | None = None,
) -> None:
    """Remove the city ``name`` from the tileset, in one transaction (``then(db)`` inside it,
    once the city is out, as ``add_city``'s)."""
    db = _open_rw(path)
    try:
        if (
            not _has_tables(db)
            or not db.execute("SELECT 1 FROM city_sets WHERE name = ?", (name,)).fetchone()
        ):
            raise TilesetError(f"{path}: holds no city named {name!r}")
        with _transaction(db):
            _delete(db, name)
            if then is not None:
                then(db)
    except sqlite3.Error as exc:
        raise TilesetError(f"{path}: cannot remove the city ({exc})") from None
    finally:
        fold_wal(db)
        db.close()


def list_cities(db: sqlite3.Connection) -> list[dict[str, object]]:
    """The cities a tileset holds: name, source file, counts and what reading found."""
    if not _has_tables(db):
        return []
    out: list[dict[str, object]] = []
    for name, source, report in db.execute(
        "SELECT name, source, report FROM city_sets ORDER BY name"
    ):
        nb = db.execute("SELECT COUNT(*) FROM city_buildings WHERE city = ?", (name,)).fetchone()
        nf = db.execute("SELECT COUNT(*) FROM city_features WHERE city = ?", (name,)).fetchone()
        out.append(
            {
                "name": name,
                "source": source,
                "buildings": int(nb[0]),
                "features": int(nf[0]),
                "report": json.loads(report),
            }
        )
    return out


def read_city(
    db: sqlite3.Connection, label: str, *, names: list[str] | None = None, box: Box | None = None
) -> City | None:
    """Every stored city (or those in ``names``) as one ``City``, only objects touching ``box``
    (west, south, east, north) when given; None when the tileset holds none."""
    if not _has_tables(db):
        return None
    sets = [r[0] for r in db.execute("SELECT name FROM city_sets ORDER BY name")]
    if names is not None:
        missing = sorted(set(names) - set(sets))
        if missing:
            raise TilesetError(f"{label}: holds no city named {missing[0]!r}")
        sets = [s for s in sets if s in names]
    if not sets:
        return None
    marks = ",".join("?" * len(sets))
    where_b = f"b.city IN ({marks})"
    where_f = f"f.city IN ({marks})"
    args: list[object] = list(sets)
    join_b = join_f = ""
    if box is not None:
        w, s, e, n = box
        join_b = " JOIN city_building_index i ON i.id = b.id"
        join_f = " JOIN city_feature_index i ON i.id = f.id"
        cond = " AND i.w <= ? AND i.e >= ? AND i.s <= ? AND i.n >= ?"
        where_b += cond
        where_f += cond
        args += [e, w, n, s]
    buildings = []
    for row in db.execute(
        "SELECT b.osm_id, b.footprint, b.height, b.min_height, b.roof_shape, b.roof_height, "
        "b.kind, b.wall_material, b.roof_material, b.height_from "
        f"FROM city_buildings b{join_b} WHERE {where_b} ORDER BY b.id",
        args,
    ):
        fp = shapely.from_wkb(row[1])
        if not isinstance(fp, Polygon):
            raise TilesetError(f"{label}: building {row[0]} is stored damaged")
        buildings.append(
            Building(row[0], fp, row[2], row[3], row[4], row[5], row[6], row[7], row[8], row[9])
        )
    features = [
        Feature(k, lon, lat, h)
        for k, lon, lat, h in db.execute(
            f"SELECT f.kind, f.lon, f.lat, f.height FROM city_features f{join_f} "
            f"WHERE {where_f} ORDER BY f.id",
            args,
        )
    ]
    city = City(f"{label} ({', '.join(sets)})", buildings, features)
    for (report,) in db.execute(f"SELECT report FROM city_sets WHERE name IN ({marks})", sets):
        r = json.loads(report)
        city.repaired += int(r.get("repaired", 0))
        city.multipolygons += int(r.get("multipolygons", 0))
        city.holes += int(r.get("holes", 0))
        city.skipped.update(Counter(r.get("skipped", {})))
        city.other_roofs.update(Counter(r.get("roofs_drawn_flat", {})))
    return city
