"""Where lodscape keeps what it fetches and builds between runs (HTTP tiles, sidecar
overviews): ``$LODSCAPE_CACHE``, else ``$XDG_CACHE_HOME/lodscape``, else ``~/.cache/lodscape``."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["user_cache"]


def user_cache() -> Path:
    """The cache folder (not created here)."""
    own = os.environ.get("LODSCAPE_CACHE")
    if own:
        return Path(own)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache")
    return Path(base) / "lodscape"
