"""One executor interface for builds: threads (the default), processes, or a Dask cluster.

``imap(fn, args)`` runs ``fn(*a)`` for every ``a`` and yields results as they finish, keeping a
bounded number in flight so a continent's worth of tiles never sits in memory at once.
"""

from __future__ import annotations

import itertools
import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import (
    FIRST_COMPLETED,
    Executor,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
    wait,
)
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol, TypeVar

from lodscape.errors import LodscapeError

__all__ = ["BuildExecutor", "DaskExecutor", "PoolExecutor", "executor_for"]

R = TypeVar("R")

_WORKER_DIED = (
    "a build worker died (killed, or out of memory); what the others finished is kept: run "
    "the same build again to resume"
)


class BuildExecutor(Protocol):
    #: For messages and provenance: "threads ×4", "processes ×2", "dask tcp://…".
    label: str
    workers: int

    def imap(self, fn: Callable[..., R], args: Iterable[tuple[Any, ...]]) -> Iterator[R]: ...

    def close(self) -> None: ...


class PoolExecutor:
    """concurrent.futures threads or processes (spawned: safe beside GDAL's and numba's threads)."""

    def __init__(self, workers: int, *, processes: bool) -> None:
        if workers < 1:
            raise LodscapeError(f"--workers must be at least 1, got {workers}")
        self.workers = workers
        self.label = f"{'processes' if processes else 'threads'} ×{workers}"
        self._pool: Executor = (
            ProcessPoolExecutor(
                workers,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_die_with_parent,
                initargs=(os.getpid(),),
            )
            if processes
            else ThreadPoolExecutor(workers, thread_name_prefix="lodscape-build")
        )

    def imap(self, fn: Callable[..., R], args: Iterable[tuple[Any, ...]]) -> Iterator[R]:
        todo = iter(args)
        running: set[Future[R]] = set()
        limit = 4 * self.workers
        try:
            while True:
                for a in todo:
                    running.add(self._pool.submit(fn, *a))
                    if len(running) >= limit:
                        break
                if not running:
                    return
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for f in done:
                    try:
                        result = f.result()
                    except BrokenProcessPool:
                        raise LodscapeError(_WORKER_DIED) from None
                    yield result
        finally:
            for f in running:
                f.cancel()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def _die_with_parent(parent: int) -> None:
    """In a pool worker: end this process when the build that started it is gone (a SIGKILLed
    build cannot shut its pool down; its workers, each holding a DEM open and hundreds of MB,
    would otherwise live on, and multiprocessing's resource tracker with them). A daemon thread
    polls the parent's pid, which changes when the orphan is re-parented; portable, and, unlike
    PR_SET_PDEATHSIG, not tied to the parent thread that spawned the worker."""
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.2)
        os._exit(1)

    # a build killed while this worker was still importing (seconds, under spawn) is gone
    # already: the worker must end now, not skip its watch
    if os.getppid() != parent:
        os._exit(1)
    threading.Thread(target=watch, name="lodscape-parent-watch", daemon=True).start()


class DaskExecutor:
    """A Dask distributed cluster: the scheduler at ``address``, or a LocalCluster of
    ``workers`` single-threaded processes."""

    def __init__(self, address: str | None, workers: int = 2) -> None:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise LodscapeError(
                "--scheduler needs Dask distributed: pip install 'dask[distributed]'"
            ) from None
        self._cluster = None
        try:
            if address is None:
                self._cluster = LocalCluster(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    # an HTTP server always starts; on a free port, not beside a user's 8787
                    dashboard_address="127.0.0.1:0",
                )
                self.client = Client(self._cluster)
            else:
                self.client = Client(address, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise LodscapeError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
        self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))
        self.label = f"dask {address or 'LocalCluster'} ×{self.workers}"

    def imap(self, fn: Callable[..., R], args: Iterable[tuple[Any, ...]]) -> Iterator[R]:
        from distributed import KilledWorker, as_completed

        todo = iter(args)
        limit = 8 * self.workers
        first = [self.client.submit(fn, *a, pure=False) for a in itertools.islice(todo, limit)]
        queue = as_completed(first)
        for future in queue:
            try:
                result = future.result()
            except KilledWorker:
                raise LodscapeError(_WORKER_DIED) from None
            yield result
            nxt = next(todo, None)
            if nxt is not None:
                queue.add(self.client.submit(fn, *nxt, pure=False))

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def executor_for(workers: int | None = None, scheduler: str | None = None) -> BuildExecutor:
    """Threads by default (one per core); ``workers`` processes; a Dask cluster at ``scheduler``
    (``"local"`` starts a LocalCluster of ``workers`` processes)."""
    if scheduler is not None:
        return DaskExecutor(None if scheduler == "local" else scheduler, workers or 2)
    if workers is not None:
        return PoolExecutor(workers, processes=True)
    return PoolExecutor(os.cpu_count() or 1, processes=False)
