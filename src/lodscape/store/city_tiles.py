"""A tileset's cities as 3D Tiles, made when a city is stored (``lodscape city add``/``remove``)
and kept in the file beside it, so ``serve`` answers its first ``/3dtiles/tileset.json`` at
once (made on that request it took over a minute, past a proxy's timeout) and ``export`` copies
them.

Table ``city_3dtiles`` (name, data): ``tileset.json``, ``{i}.glb`` and ``signature``, what the
stored cities were when they were made (each city's name, source and counts). A reader whose
cities have another signature (a city stored by an older lodscape, or by ``add_city`` without
``store_city_tiles``) makes them itself.
"""

from __future__ import annotations

import json
import sqlite3
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.store.city import read_city
from lodscape.store.tileset import TilesetProvider

__all__ = ["city_tiles", "make_city_tiles", "store_city_tiles"]

_SCHEMA = "CREATE TABLE IF NOT EXISTS city_3dtiles (name TEXT PRIMARY KEY, data BLOB NOT NULL)"

Made = tuple[bytes, list[bytes]]


def _signature(db: sqlite3.Connection) -> str | None:
    """The stored cities, as what they were made from (None: no city table)."""
    if not _has(db, "city_sets"):
        return None
    rows = db.execute("SELECT name, source, report FROM city_sets ORDER BY name").fetchall()
    return json.dumps(rows)


def _has(db: sqlite3.Connection, table: str) -> bool:
    row = db.execute(
        "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = ?", (table,)
    ).fetchone()
    return row is not None


def make_city_tiles(db: sqlite3.Connection, provider: TilesetProvider) -> Made | None:
    """(tileset.json, glb contents) of the cities ``db`` holds (a connection to the tileset,
    perhaps inside the transaction that stores them), standing on ``provider``'s ground; None
    without a city."""
    city = read_city(db, provider.name)
    if city is None:
        return None
    from lodscape.city.model import build_city
    from lodscape.store.tiles3d import city_tileset

    def ground(lon: Any, lat: Any) -> NDArray[np.float64]:
        # the finest stored meshes, every point at once (a tile read once per call)
        out: NDArray[np.float64] = provider.heights(np.ravel(lon), np.ravel(lat))
        return out.reshape(np.shape(lon))

    tileset, contents = city_tileset(build_city(city, ground))
    return json.dumps(tileset).encode(), contents


def store_city_tiles(db: sqlite3.Connection, provider: TilesetProvider) -> int:
    """Make the cities' 3D Tiles and keep them in the tileset, through ``db`` (inside the
    caller's transaction); returns how many contents."""
    db.execute(_SCHEMA)
    db.execute("DELETE FROM city_3dtiles")
    made = make_city_tiles(db, provider)
    if made is None:
        return 0
    rows = [("tileset.json", made[0])] + [(f"{i}.glb", c) for i, c in enumerate(made[1])]
    rows.append(("signature", (_signature(db) or "").encode()))
    db.executemany("INSERT INTO city_3dtiles VALUES (?, ?)", rows)
    return len(made[1])


def city_tiles(provider: TilesetProvider) -> Made | None:
    """The tileset's cities as 3D Tiles: those stored with them where they are the current
    cities', else made now; None without a city."""
    db = provider.connection()
    signature = _signature(db)
    if signature is None:
        return None
    if _has(db, "city_3dtiles"):
        stored = dict(db.execute("SELECT name, data FROM city_3dtiles").fetchall())
        if bytes(stored.get("signature", b"")).decode() == signature and "tileset.json" in stored:
            count = sum(1 for k in stored if k.endswith(".glb"))
            return bytes(stored["tileset.json"]), [bytes(stored[f"{i}.glb"]) for i in range(count)]
    return make_city_tiles(db, provider)
