"""Temporary names beside an output, renamed into place when it is whole: ``.NAME.PID.tmp``.

A run that is killed cannot remove its own; the next run for the same output removes those whose
process is gone (never a live one's: two runs may write beside each other).
"""

from __future__ import annotations

import os
import re
import shutil
from pathlib import Path

__all__ = ["temp_beside"]


def temp_beside(target: Path, suffix: str = "", kind: str = "tmp") -> Path:
    """A temporary name for ``target`` in its folder (``suffix`` kept last, for tools that read
    the format from it), after removing what killed runs left for the same target."""
    folder = target.parent if str(target.parent) else Path(".")
    pattern = re.compile(rf"^\.{re.escape(target.name)}\.(\d+)\.{kind}")
    try:
        names = os.listdir(folder)
    except OSError:
        names = []
    for name in names:
        m = pattern.match(name)
        if m is None or int(m[1]) == os.getpid() or _alive(int(m[1])):
            continue
        stale = folder / name
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale, ignore_errors=True)
        else:
            stale.unlink(missing_ok=True)
    return folder / f".{target.name}.{os.getpid()}.{kind}{suffix}"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (PermissionError), or not ours to judge
        return True
    return True
