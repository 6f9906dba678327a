"""What a tileset file is, read without the rest of the store: its magic bytes, its manifest and
its error type (the tileset and the city store both read them)."""

from __future__ import annotations

import json
import os

try:
    import fcntl
except ImportError:  # Windows: no advisory file locks; a running build reads as stopped
    fcntl = None  # type: ignore[assignment]
import sqlite3
from pathlib import Path
from typing import Any

from lodscape._sqlite import readonly_uri
from lodscape.errors import LodscapeError

__all__ = [
    "TilesetError",
    "being_written",
    "connect_readonly",
    "fold_wal",
    "hold_for_writing",
    "is_tileset",
    "read_manifest",
]

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


def connect_readonly(path: str | os.PathLike[str]) -> sqlite3.Connection:
    """A read-only connection to the tileset at ``path`` (any thread may use it).

    A writer killed mid-transaction in rollback-journal mode leaves a hot journal that only a
    connection with write access can undo (a read-only one fails with "attempt to write a
    readonly database", for good): it is undone here first, once, with a short read-write
    connection. Writers today keep a write-ahead log instead, which readers need not undo."""
    p = Path(path).resolve()
    journal = p.with_name(p.name + "-journal")
    if journal.is_file() and journal.stat().st_size > 0:
        try:
            with sqlite3.connect(p, timeout=5.0) as rw:  # reading undoes the hot journal
                rw.execute("SELECT count(*) FROM sqlite_master").fetchone()
            rw.close()
        except sqlite3.Error as exc:
            raise TilesetError(
                f"{path}: a write to it was interrupted and its journal ({journal.name}) needs "
                f"write access to undo ({exc})"
            ) from None
    return sqlite3.connect(readonly_uri(p), uri=True, check_same_thread=False)


def fold_wal(db: sqlite3.Connection) -> None:
    """Fold a writer's write-ahead log back into the one file (a tileset is one file to copy).
    Another process holding the file open keeps it in WAL mode, which is complete and
    consistent; the log folds in at the next writer's end."""
    try:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        db.execute("PRAGMA journal_mode=DELETE")
    except sqlite3.OperationalError:
        pass


def hold_for_writing(path: str | os.PathLike[str]) -> Any:
    """Mark the tileset at ``path`` as being written by this process, until the returned file is
    closed or the process ends (an advisory ``flock``, which the kernel drops with the process,
    so a killed build never leaves a stale mark). Raises ``TilesetError`` when another process
    holds it."""
    f = open(path, "rb")  # noqa: SIM115  (held open for the writer's life)
    if fcntl is not None:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            raise TilesetError(
                f"{path}: another lodscape build is writing it now; wait for it to finish"
            ) from None
    return f


def being_written(path: str | os.PathLike[str]) -> bool:
    """Whether a running build holds the tileset at ``path`` (see ``hold_for_writing``)."""
    if fcntl is None:
        return False
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
            except OSError:
                return True
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)
    except OSError:
        return False
    return False
