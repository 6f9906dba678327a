"""Run ``lodscape build`` and SIGKILL it at one phase (a real kill, at a known point):

    python _kill_build.py PHASE PIDS_FILE -- BUILD ARGS...

PHASE: ``plan`` (the first row of blocks planned, no tile made), ``level:Z`` (just after the
first block holding a tile of level Z is merged into the file), ``spawn`` (the first task
handed to a process pool, its workers still starting), ``fold`` (the build marked complete,
its log not yet folded), ``never``. Before the kill, the build's descendants are written to
PIDS_FILE, one pid a line, for the test to see that none outlives it.
"""

from __future__ import annotations

import os
import signal
import sqlite3
import sys
import time
from pathlib import Path

from lodscape.store import tileset


def _descendants(pid: int) -> set[int]:
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(fields[1])
    out: set[int] = set()
    frontier = {pid}
    while frontier:
        frontier = {c for c, p in parents.items() if p in frontier} - out
        out |= frontier
    return out


def _die(pids_file: str) -> None:
    # the workers of a process executor are up by now: see them before the kill
    time.sleep(0.2)
    Path(pids_file).write_text("".join(f"{p}\n" for p in _descendants(os.getpid())))
    os.kill(os.getpid(), signal.SIGKILL)


def main() -> None:
    phase, pids_file = sys.argv[1], sys.argv[2]
    argv = sys.argv[sys.argv.index("--") + 1 :]
    writer = tileset.TilesetWriter
    if phase == "plan":
        planned = writer.blocks_done

        def first_row(self: tileset.TilesetWriter, z: int, y: int) -> set[int]:
            planned(self, z, y)
            _die(pids_file)
            return set()

        writer.blocks_done = first_row  # type: ignore[method-assign]
    elif phase.startswith("level:"):
        z = int(phase.split(":")[1])
        merge = writer.merge

        def merged(self: tileset.TilesetWriter, shard: Path, block: tuple[int, int, int]) -> int:
            with sqlite3.connect(f"file:{shard}?mode=ro", uri=True) as db:
                has = db.execute("SELECT 1 FROM plan WHERE z = ? LIMIT 1", (z,)).fetchone()
            db.close()
            n = merge(self, shard, block)
            if has:
                _die(pids_file)
            return n

        writer.merge = merged  # type: ignore[method-assign]
    elif phase == "fold":
        fold = tileset.fold_wal

        def folding(db: object) -> None:
            _die(pids_file)
            fold(db)  # type: ignore[arg-type]

        tileset.fold_wal = folding  # type: ignore[assignment]
    elif phase == "spawn":
        from concurrent.futures import ProcessPoolExecutor

        submit = ProcessPoolExecutor.submit

        def submitted(self: ProcessPoolExecutor, *args: object, **kwargs: object) -> object:
            future = submit(self, *args, **kwargs)  # type: ignore[arg-type]
            _die(pids_file)
            return future

        ProcessPoolExecutor.submit = submitted  # type: ignore[assignment,method-assign]
    elif phase != "never":
        raise SystemExit(f"unknown phase {phase!r}")
    from lodscape.cli import main as cli

    cli(argv)


if __name__ == "__main__":
    main()
