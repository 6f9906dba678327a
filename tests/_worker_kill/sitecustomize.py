"""Loaded by every Python process started with this folder on PYTHONPATH: in a build's worker
process (never the build itself), when LODSCAPE_TEST_KILL_WORKER_AT=Z, the worker SIGKILLs
itself as it is about to put in place a block's shard holding a tile of level Z: a worker
killed mid-task, for real."""

import os
import sys

_AT = os.environ.get("LODSCAPE_TEST_KILL_WORKER_AT")

# a process multiprocessing spawned (a pool's worker, a Dask worker), not the build itself
if _AT is not None and "--multiprocessing-fork" in sys.orig_argv:
    import signal

    from lodscape.build import blocks

    _close = blocks._Shard.close

    def _closing(self: blocks._Shard) -> None:
        if self.db.execute("SELECT 1 FROM plan WHERE z = ? LIMIT 1", (int(_AT),)).fetchone():
            os.kill(os.getpid(), signal.SIGKILL)
        _close(self)

    blocks._Shard.close = _closing  # type: ignore[method-assign]
