"""What a tileset file is, read without the rest of the store: its magic bytes, its manifest and
its error type (the tileset and the city store both read them)."""

from __future__ import annotations

import json
import os
import sqlite3
from typing import Any

from lodscape.errors import LodscapeError

__all__ = ["TilesetError", "is_tileset", "read_manifest"]

_MAGIC = b"SQLite format 3\x00"


class TilesetError(LodscapeError):
    """A tileset file that cannot be used: not one, another version, incomplete, damaged."""


def read_manifest(db: sqlite3.Connection, name: str) -> dict[str, Any]:
    """The tileset's manifest (its ``lodscape`` metadata); ``TilesetError`` naming ``name`` if
    the file is not a lodscape tileset."""
    try:
        row = db.execute("SELECT value FROM metadata WHERE name = 'lodscape'").fetchone()
    except sqlite3.Error as exc:
        raise TilesetError(f"{name}: not a lodscape tileset ({exc})") from None
    if row is None:
        raise TilesetError(f"{name}: an SQLite file, but not a lodscape tileset")
    manifest: dict[str, Any] = json.loads(row[0])
    return manifest


def is_tileset(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is an SQLite file (a tileset, or something to refuse as one)."""
    try:
        with open(path, "rb") as f:
            return f.read(16) == _MAGIC
    except OSError:
        return False
