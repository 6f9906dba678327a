"""SQLite file names as URIs, for every layer that opens a database read-only (a tileset, an
MBTiles file): it holds no state of a layer's."""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import quote

__all__ = ["readonly_uri"]


def readonly_uri(path: str | os.PathLike[str]) -> str:
    """SQLite's read-only URI of ``path``, percent-encoded: a "?", "#" or "%" in a folder's or
    file's name would otherwise end the path early, or name another file."""
    return f"file:{quote(Path(path).resolve().as_posix())}?mode=ro"
