"""The staged resource pipeline: see the package docstring."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FuturesTimeout
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape._lru import ByteLRU
from lodscape.errors import LodscapeError
from lodscape.lod.radii import RadiiOptions
from lodscape.terrain.mesh import TileMesh

__all__ = ["RealClock", "SimClock", "StreamOptions", "StreamStats", "Streamer"]

Made = TileMesh | NDArray[np.uint8]
Stage = Literal["memory", "cache"]


class Source(Protocol):
    """What the streamer reads: a Provider's two halves. A source may also declare what a key
    costs on a simulated clock, ``cost(key) -> seconds`` (see the package docstring)."""

    def fetch(self, key: int) -> bytes: ...

    def decode(self, key: int, data: bytes) -> Made: ...


class Clock(Protocol):
    def now(self) -> float: ...


class RealClock:
    """Wall-clock seconds: a result is usable as soon as it is ready."""

    simulated = False

    def now(self) -> float:
        return time.monotonic()


class SimClock:
    """Simulated seconds, advanced by the caller one frame at a time."""

    simulated = True

    def __init__(self, start: float = 0.0) -> None:
        self.t = start

    def now(self) -> float:
        return self.t

    def advance(self, seconds: float) -> None:
        self.t += seconds


@dataclass(frozen=True)
class StreamOptions:
    """Budgets and limits of the pipeline; the defaults suit a desktop viewer."""

    #: Bytes of fetched tiles kept in RAM (the cache stage).
    cache_mb: float = 128.0
    #: Bytes of decoded, upload-ready tiles kept in RAM (the memory stage).
    memory_mb: float = 128.0
    #: GL-thread time per frame for uploads, milliseconds.
    upload_ms: float = 6.0
    #: Jobs (fetch and/or decode) in flight at once.
    in_flight: int = 16
    #: Worker threads.
    workers: int = 4
    #: Seconds ahead along the velocity the predicted selections look (memory, then cache);
    #: () turns that prediction off.
    ahead: tuple[float, ...] = (1.0, 3.0)
    #: Paper 004's memory and cache radii around the camera (``lod.radii``); None turns them
    #: off (the velocity's predictions alone).
    radii: RadiiOptions | None = field(default_factory=RadiiOptions)
    #: First retry delay after a failed fetch (doubling, up to ``max_backoff``), seconds.
    backoff: float = 0.25
    max_backoff: float = 8.0

    def __post_init__(self) -> None:
        for name in ("cache_mb", "memory_mb", "upload_ms", "backoff", "max_backoff"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"Expected a positive {name}, got {getattr(self, name)}")
        if self.in_flight < 1 or self.workers < 1:
            raise ValueError("Expected at least one worker and one job in flight")


@dataclass
class StreamStats:
    """Running totals; a frame's figures are the difference of two snapshots."""

    requested: int = 0
    fetched: int = 0
    decoded: int = 0
    uploaded: int = 0
    failed: int = 0
    retried: int = 0
    cache_hits: int = 0
    memory_hits: int = 0
    upload_ms: float = 0.0
    #: Bytes fetched from the source (disk, a server), not from the cache stage.
    fetched_bytes: int = 0
    #: Milliseconds a simulated clock waited for local jobs in ``collect`` (real time the
    #: workers took that the simulated frame already gave them: not the frame's own work).
    sim_wait_ms: float = 0.0

    def snapshot(self) -> StreamStats:
        return StreamStats(**self.__dict__)

    def since(self, before: StreamStats) -> dict[str, float]:
        return {k: round(v - getattr(before, k), 3) for k, v in self.__dict__.items()}


@dataclass
class _Job:
    key: int
    decode: bool
    submitted: float
    future: Future[tuple[bytes | None, Made | None, float]]
    #: 0 the terrain's workers, 1 the imagery's, 2 the prefetch's, 3 the prefetch's imagery.
    lane: int = 0
    #: Simulated completion, once known.
    done_at: float | None = None


#: Longest a simulated clock waits for one local job (a fetch and decode) in ``collect``.
SIM_WAIT_S = 60.0

#: Threads that fetch imagery layers' tiles (network waits, raster reads), apart from the
#: terrain's workers.
NET_THREADS = 8


@dataclass
class _Failure:
    attempts: int
    retry_at: float
    message: str = ""


@dataclass
class Streamer:
    """Owns the cache and memory stages and the worker jobs that fill them."""

    source: Source
    options: StreamOptions = field(default_factory=StreamOptions)
    clock: Clock = field(default_factory=RealClock)
    #: What a worker does to a decoded resource before it goes to the memory stage (the GPU
    #: terrain mode makes height textures there, off the GL thread); None: nothing.
    prepare: Callable[[int, Made], Made] | None = None
    #: Which keys come over the network (imagery layers): they get their own threads, so a slow
    #: server never holds the workers that mesh the terrain; None: none do.
    remote: Callable[[int], bool] | None = None

    def __post_init__(self) -> None:
        self.cache: ByteLRU[int, bytes] = ByteLRU()
        self.memory: ByteLRU[int, Made] = ByteLRU()
        self.stats = StreamStats()
        self._jobs: dict[int, _Job] = {}
        self._failures: dict[int, _Failure] = {}
        self._pool = ThreadPoolExecutor(self.options.workers, thread_name_prefix="lodscape-io")
        #: The prefetch's own threads (half the workers', at least one): what the camera will
        #: want never queues ahead of what the frame wants now.
        pre = max(1, self.options.workers // 2)
        self._pre = ThreadPoolExecutor(pre, thread_name_prefix="lodscape-prefetch")
        self._net: ThreadPoolExecutor | None = None
        #: The prefetch's network threads: a prefetched imagery tile never queues ahead of one
        #: a frame wants (half the imagery's threads).
        self._pre_net: ThreadPoolExecutor | None = None
        if self.remote is not None:
            self._net = ThreadPoolExecutor(NET_THREADS, thread_name_prefix="lodscape-net")
            self._pre_net = ThreadPoolExecutor(
                NET_THREADS // 2, thread_name_prefix="lodscape-prefetch-net"
            )
        #: Per lane (``_Job.lane``): its threads, and their simulated worker slots (when each
        #: is free next on a simulated clock).
        self._lane_pools = (self._pool, self._net, self._pre, self._pre_net)
        self._lane_slots = [
            [-math.inf] * n for n in (self.options.workers, NET_THREADS, pre, NET_THREADS // 2)
        ]
        self._pinned: set[int] = set()
        #: Keys the frame on screen wants (``Loader`` sets them): a prefetched resource never
        #: pushes one of them out of the memory stage before it is uploaded.
        self.wanted: frozenset[int] = frozenset()

    # --- requests ----------------------------------------------------------------------------

    def request(
        self,
        keys: Iterable[int],
        stage: Stage,
        skip: Callable[[int], bool],
        limit: int | None = None,
        prefetch: bool = False,
    ) -> None:
        """Ask for ``keys`` (most urgent first) up to ``stage``; ``skip`` says which are already
        on the GPU. Stops at the in-flight limit (or ``limit``, lower, for a prefetch that must
        leave room for what frames want): less urgent classes wait their turn. Terrain and
        imagery (``remote``) keys have a limit each, so a slow imagery source never takes the
        terrain's places; a ``prefetch``'s keys go to the prefetch's own threads (terrain and
        network apart), so they never queue ahead of what a frame wants."""
        now = self.clock.now()
        busy = [0, 0, 0, 0]
        for running in self._jobs.values():
            busy[running.lane] += 1
        limit = self.options.in_flight if limit is None else min(limit, self.options.in_flight)
        for key in keys:
            if skip(key):
                continue
            if key in self.memory:
                self.memory.touch(key)
                continue
            job = self._jobs.get(key)
            if job is not None:
                continue
            cached = self.cache.get(key)
            if cached is not None and stage == "cache":
                continue
            failure = self._failures.get(key)
            if failure is not None and now < failure.retry_at:
                continue
            lane = self._lane(key)
            if prefetch:
                lane += 2
            if busy[lane] >= limit:
                usable = [2, 3] if prefetch else [0, 1]
                if self._net is None:
                    usable = usable[:1]
                if all(busy[i] >= limit for i in usable):
                    return
                continue
            busy[lane] += 1
            if failure is not None:
                self.stats.retried += 1
            self.stats.requested += 1
            decode = stage == "memory"
            pool = self._lane_pools[lane]
            assert pool is not None  # the network's lanes are only taken when it has threads
            future = pool.submit(self._work, key, cached, decode)
            self._jobs[key] = _Job(key, decode, now, future, lane)

    def _lane(self, key: int) -> int:
        """1 for keys of the imagery's own threads, 0 for the terrain's."""
        return int(self._net is not None and self.remote is not None and self.remote(key))

    def _pool_for(self, key: int) -> ThreadPoolExecutor:
        if self._net is not None and self._lane(key):
            return self._net
        return self._pool

    def _work(
        self, key: int, cached: bytes | None, decode: bool
    ) -> tuple[bytes | None, Made | None, float]:
        """On a worker: fetch (unless cached) and decode (if asked); returns what it made and
        what it cost: the source's declared cost of a fetch, else (or when the bytes came from
        the cache) this thread's CPU seconds (not wall time: see the package docstring)."""
        t = time.thread_time()
        data = cached if cached is not None else self.source.fetch(key)
        made = self._decode(key, data) if decode else None
        took = time.thread_time() - t
        declared = getattr(self.source, "cost", None)
        if declared is not None and cached is None:  # a fetch's declared cost
            took = float(declared(key))
        return (None if cached is not None else data), made, took

    def _decode(self, key: int, data: bytes) -> Made:
        made = self.source.decode(key, data)
        return made if self.prepare is None else self.prepare(key, made)

    # --- results -----------------------------------------------------------------------------

    def collect(self) -> None:
        """Move finished jobs whose results the clock allows into the cache and memory."""
        now = self.clock.now()
        simulated = bool(getattr(self.clock, "simulated", False))
        for key, job in list(self._jobs.items()):
            if not job.future.done():
                if not simulated or job.lane in (1, 3):
                    continue
                # on a simulated clock local work is waited for: its cost on the clock, not how
                # soon this machine's threads got to it, says when it is usable (the network's
                # jobs are not: a server that hangs must not hold the frame)
                t = time.perf_counter()
                try:
                    job.future.exception(timeout=SIM_WAIT_S)
                except FuturesTimeout:
                    continue
                finally:
                    self.stats.sim_wait_ms += (time.perf_counter() - t) * 1e3
            exc = job.future.exception()
            if job.done_at is None:
                took = 0.0 if exc is not None else job.future.result()[2]
                if simulated:
                    # the worker slot that frees first takes the job
                    slots = self._lane_slots[job.lane]
                    slot = int(np.argmin(slots))
                    start = max(job.submitted, slots[slot])
                    job.done_at = slots[slot] = start + took
                else:
                    job.done_at = now
            if job.done_at > now:
                continue
            del self._jobs[key]
            made = self._settle(key, job.future, now)
            if made is not None:
                self._put_memory(key, made)

    def _settle(
        self, key: int, future: Future[tuple[bytes | None, Made | None, float]], now: float
    ) -> Made | None:
        """A finished job into the accounts: its failure recorded (for the backoff), or its
        fetched bytes cached; returns what it decoded (None: it failed, or only fetched)."""
        exc = future.exception()
        if exc is not None:
            self._fail(key, exc, now)
            return None
        data, made, _ = future.result()
        self._failures.pop(key, None)
        if data is not None:
            self.stats.fetched += 1
            self.stats.fetched_bytes += len(data)
            self._put_cache(key, data)
        else:
            self.stats.cache_hits += 1
        if made is not None:
            self.stats.decoded += 1
        return made

    def _fail(self, key: int, exc: BaseException, now: float) -> None:
        if not isinstance(exc, LodscapeError | OSError | ValueError):
            raise exc
        self.stats.failed += 1
        old = self._failures.get(key)
        attempts = 1 if old is None else old.attempts + 1
        delay = min(self.options.backoff * 2.0 ** (attempts - 1), self.options.max_backoff)
        self._failures[key] = _Failure(attempts, now + delay, str(exc))

    def failures(self) -> dict[int, str]:
        """Keys whose last attempt failed, with its message."""
        return {k: f.message for k, f in self._failures.items()}

    # --- handing over -----------------------------------------------------------------------

    def pop(self, key: int) -> Made | None:
        """A decoded resource out of the memory stage (to go to the GPU), or None."""
        return self.memory.pop(key)

    def take(self, key: int) -> Made:
        """A resource now, whatever it costs (the frame cannot be drawn without it): from
        memory, from the cache, or fetched on this thread."""
        return self.take_many([key])[0]

    def take_many(self, keys: Sequence[int]) -> list[Made]:
        """Resources now, fetched and decoded on the workers at once (a frame that must wait
        waits for the slowest, not the sum): each from memory, the cache, or the source."""
        return [m for m in self._take_now(keys, lenient=False) if m is not None]

    def take_available(self, keys: Sequence[int]) -> list[Made | None]:
        """``take_many`` for a frame that can be drawn without some of them (a streaming
        frame's roots, the ellipsoid drawn where one is missing): a key whose last attempt
        failed is skipped until its retry is due, and a failure is recorded (retried later,
        with backoff) instead of raised; None for those."""
        return self._take_now(keys, lenient=True)

    def _take_now(self, keys: Sequence[int], *, lenient: bool) -> list[Made | None]:
        now = self.clock.now()
        out: list[Made | None] = [self.memory.pop(k) for k in keys]
        self.stats.memory_hits += sum(m is not None for m in out)
        todo = []
        for i, m in enumerate(out):
            failure = self._failures.get(keys[i]) if lenient else None
            if m is None and (failure is None or now >= failure.retry_at):
                todo.append(i)
        cached = [self.cache.get(keys[i]) for i in todo]
        work = [
            self._pool_for(keys[i]).submit(self._take, keys[i], c)
            for i, c in zip(todo, cached, strict=True)
        ]
        for i, c, job in zip(todo, cached, work, strict=True):
            exc = job.exception()
            if exc is not None:
                if not lenient:
                    raise exc
                self._fail(keys[i], exc, now)
                continue
            data, made = job.result()
            self._failures.pop(keys[i], None)
            if c is None and data is not None:
                self.stats.fetched += 1
                self.stats.fetched_bytes += len(data)
                self._put_cache(keys[i], data)
            elif c is not None:
                self.stats.cache_hits += 1
            self.stats.decoded += 1
            out[i] = made
        return out

    def _take(self, key: int, cached: bytes | None) -> tuple[bytes | None, Made]:
        """On a worker: what ``take_many`` needs of one key."""
        if cached is not None:
            return cached, self._decode(key, cached)
        data = self.source.fetch(key)
        return data, self._decode(key, data)

    def take_within(self, keys: Sequence[int], seconds: float) -> list[Made | None]:
        """Resources a frame would like but can be drawn without (imagery): what arrives within
        ``seconds``, None for the rest. A failure is recorded (and retried later, with backoff);
        a job still running at the deadline goes on, and ``collect`` keeps what it brings."""
        from concurrent.futures import wait

        out: list[Made | None] = [self.memory.pop(k) for k in keys]
        self.stats.memory_hits += sum(m is not None for m in out)
        now = self.clock.now()
        jobs: dict[int, Future[tuple[bytes | None, Made | None, float]]] = {}
        for i, key in enumerate(keys):
            if out[i] is not None:
                continue
            job = self._jobs.get(key)
            if job is not None and job.decode:
                jobs[i] = job.future
                continue
            failure = self._failures.get(key)
            if failure is not None and now < failure.retry_at:
                continue
            cached = self.cache.get(key)
            self.stats.requested += 1
            jobs[i] = self._pool_for(key).submit(self._work, key, cached, True)
        if jobs:
            wait(list(jobs.values()), timeout=max(seconds, 0.0))
        for i, future in jobs.items():
            key = keys[i]
            if not future.done():
                # the frame goes on without it; a later frame collects it
                if key not in self._jobs:
                    self._jobs[key] = _Job(key, True, now, future, self._lane(key))
                continue
            self._jobs.pop(key, None)
            out[i] = self._settle(key, future, now)
        return out

    # --- budgets -----------------------------------------------------------------------------

    def _put_cache(self, key: int, data: bytes) -> None:
        self.cache.put(key, data, len(data))
        self.cache.shrink(self.options.cache_mb * 2**20, keep={key})

    def _put_memory(self, key: int, made: Made) -> None:
        self.memory.put(key, made, _nbytes(made))
        self.memory.shrink(self.options.memory_mb * 2**20, keep=self.wanted | {key})

    @property
    def cache_bytes(self) -> int:
        return self.cache.nbytes

    @property
    def memory_bytes(self) -> int:
        return self.memory.nbytes

    def resident(self) -> dict[str, int]:
        """Bytes held now in each of the streamer's stages."""
        return {"cache": self.cache.nbytes, "memory": self.memory.nbytes}

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        """Run ``fn`` on the workers (the prefetch's predicted selections)."""
        return self._pool.submit(fn, *args)

    def in_flight(self) -> int:
        return len(self._jobs)

    def running(self, key: int) -> bool:
        """Whether a job for ``key`` is on its way."""
        return key in self._jobs

    def drain(self, timeout: float = 30.0) -> None:
        """Wait for every job in flight (tests, and the end of a flight)."""
        for job in list(self._jobs.values()):
            job.future.exception(timeout=timeout)

    def close(self) -> None:
        for net in (self._net, self._pre_net):
            if net is not None:
                # a server that never answers must not hold the close: its requests time out
                # alone
                net.shutdown(wait=False, cancel_futures=True)
        self._pre.shutdown(wait=True, cancel_futures=True)
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._jobs.clear()


def _nbytes(made: Any) -> int:
    return int(made.nbytes)
