"""One loader for every frame: the streamer's cache and memory stages, the GPU stage, and the
prefetch along the camera's velocity, serving a ``FramePlan`` with one of two policies.

- **blocking** (one-shot renders): every key the plan requires is fetched and decoded on the
  workers at once, then uploaded; nothing else is asked for. Imagery (``optional`` keys) is
  waited for at most ``imagery_wait`` seconds over the loader's whole life: a server that never
  answers costs a render that long once, and the frame is drawn with what came.
- **streaming** (flights, the viewer): ``begin``, before the frame's one selection, uploads within
  a time slice what the last frame asked for and has been decoded since, most urgent first, and
  with what is left of the slice prefetched resources while the GPU budget has room for them;
  the selection then draws them. ``serve`` takes what the plan requires (roots with nothing
  above them) at once, counted as a stall, requests its loads up to the memory stage, and lets
  the prefetch ask for what the camera will want. Prefetched
  resources that do not fit wait decoded in the memory stage until a frame wants them: on a full
  GPU, where only what was drawn is safe from eviction, they would be freed before their turn
  (and were, once: a flight fell back more than one level in 119 of 300 frames).

After the frame is drawn, ``finish`` marks what it drew and frees what the GPU budget cannot keep,
never one of those.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import ecef_to_geodetic
from lodscape.lod.camera import Camera
from lodscape.stream.gpu import GpuResources, GpuStage, Made
from lodscape.stream.streamer import Clock, Source, Streamer, StreamOptions, StreamStats

__all__ = ["LoadReport", "Loader", "Plan"]

#: Seconds (on the loader's clock) between predictions of where the camera is going.
PREDICT_EVERY = 0.15

Stage = Literal["memory", "cache"]
#: The keys a fitted camera would draw, or None where it cannot be (under the ground).
Predict = Callable[[Camera], "list[int] | None"]
#: Paper 004's areas for a camera moving at a velocity (m/s, ECEF): the memory area's keys, the
#: cache area's, and how many chunks each holds; None where the camera cannot be.
Areas = Callable[
    [Camera, NDArray[np.float64]], "tuple[list[int], list[int], dict[str, int]] | None"
]


class Plan(Protocol):
    """What the loader needs of a frame's plan (``lod.view.FramePlan`` for the terrain, the
    globe's imagery tiles for the globe)."""

    @property
    def camera(self) -> Camera: ...

    @property
    def required(self) -> list[int]: ...

    @property
    def loads(self) -> NDArray[np.uint64]: ...

    @property
    def drawn(self) -> frozenset[int]: ...


@dataclass(frozen=True)
class LoadReport:
    """What the loader did for one frame."""

    #: Resources uploaded this frame (taken at once, or from the memory stage).
    loaded: int
    #: Milliseconds the frame waited for required resources.
    stall_ms: float
    #: Milliseconds spent in ``serve`` (the loader's share of the frame's CPU time).
    load_ms: float
    stream: dict[str, float] = field(default_factory=dict)
    #: Required keys a streaming frame is drawn without (their fetch failed; retried later).
    absent: frozenset[int] = frozenset()


class Loader:
    """Moves resources disk → cache → memory → GPU for one source and one ``GpuResources``."""

    def __init__(
        self,
        source: Source,
        gpu: GpuResources,
        options: StreamOptions,
        clock: Clock,
        *,
        gpu_budget_bytes: float,
        predict: Predict | None = None,
        optional: Callable[[int], bool] | None = None,
        imagery_wait: float = 10.0,
        areas: Areas | None = None,
        remote: Callable[[int], bool] | None = None,
    ) -> None:
        """``optional`` keys (imagery) may be drawn without; ``remote`` ones come over the
        network (default: the optional ones) and get the streamer's network threads."""
        self.options = options
        self.streamer = Streamer(
            source, options, clock, prepare=gpu.prepare, remote=remote or optional
        )
        self._optional = optional
        #: Seconds blocking frames may still wait for optional keys (imagery), all together.
        self.imagery_wait = imagery_wait
        #: Optional keys blocking frames were drawn without (failed, or not there in time), and
        #: of those the ones still on their way when the wait was up.
        self.missed = 0
        self.late = 0
        self.gpu = GpuStage(gpu, gpu_budget_bytes)
        self._predict = predict
        self._areas = areas
        #: The last classification's chunks per area and resource units per state.
        self.units: dict[str, int] = {}
        self._motion: tuple[float, NDArray[np.float64]] | None = None
        self._predicted_at = -math.inf
        self._predicted: (
            Future[tuple[list[tuple[Stage, list[int]]], dict[str, int] | None]] | None
        ) = None
        self._before: StreamStats = self.streamer.stats.snapshot()
        #: The last plan's loads (most urgent first): what ``begin`` uploads first.
        self._wanted: list[int] = []
        #: What ``begin`` uploaded and how long it took, for the frame's report.
        self._begun: tuple[int, float] = (0, 0.0)

    @property
    def clock(self) -> Clock:
        return self.streamer.clock

    def resident(self) -> NDArray[np.uint64]:
        """The keys on the GPU, sorted."""
        return self.gpu.keys()

    def begin(self) -> None:
        """Before the frame's selection (streaming): move finished jobs into the stages and
        upload, within the time slice, what the last frame asked for, then prefetched resources
        while the GPU budget has room. The selection that follows sees them: what finished in
        time is drawn this frame, with one selection."""
        t0 = time.perf_counter()
        self._before = self.streamer.stats.snapshot()
        s = self.streamer
        s.collect()
        slice_ms = self.options.upload_ms
        n = self.gpu.upload_within(self._ready(self._wanted), slice_ms)
        spent = (time.perf_counter() - t0) * 1e3
        if spent < slice_ms:
            n += self.gpu.upload_within(self._spare(), slice_ms - spent)
        s.stats.upload_ms += (time.perf_counter() - t0) * 1e3
        s.stats.uploaded += n
        self._begun = (n, (time.perf_counter() - t0) * 1e3)

    def serve(self, plan: Plan, *, blocking: bool) -> LoadReport:
        """Bring what ``plan`` requires onto the GPU, and (streaming) ask for its loads and the
        prefetch's; ``begin`` uploads them in the frames that follow."""
        t0 = time.perf_counter()
        if blocking:
            self._before = self.streamer.stats.snapshot()
        uploaded, begin_ms = self._begun
        self._begun = (0, 0.0)
        taken = 0
        stall = 0.0
        absent: set[int] = set()
        if plan.required:
            opt = self._optional
            must = [k for k in plan.required if opt is None or not opt(k)]
            extra = [k for k in plan.required if opt is not None and opt(k)]
            if blocking:
                made: list[Made | None] = list(self.streamer.take_many(must))
            else:
                # a flight goes on without a root a server failed: retried, with backoff
                made = self.streamer.take_available(must)
            for key, m in zip(must, made, strict=True):
                if m is None:
                    absent.add(key)
                    continue
                self.gpu.upload(key, m)
                taken += 1
            if extra:
                t1 = time.perf_counter()
                got = self.streamer.take_within(extra, self.imagery_wait)
                self.imagery_wait = max(0.0, self.imagery_wait - (time.perf_counter() - t1))
                for key, g in zip(extra, got, strict=True):
                    if g is None:
                        self.missed += 1
                        self.late += self.streamer.running(key)
                        continue
                    self.gpu.upload(key, g)
                    taken += 1
            stall = (time.perf_counter() - t0) * 1e3
            self.streamer.stats.uploaded += taken
        if not blocking:
            on_gpu = self.gpu.__contains__
            self.streamer.request((int(k) for k in plan.loads), "memory", on_gpu)
            self._wanted = [int(k) for k in plan.loads]
            self.streamer.wanted = frozenset(self._wanted)
            self._prefetch(plan.camera, on_gpu)
        load_ms = begin_ms + (time.perf_counter() - t0) * 1e3
        return LoadReport(taken + uploaded, stall, load_ms, absent=frozenset(absent))

    def _ready(self, keys: list[int]) -> Iterator[tuple[int, Made]]:
        """(key, resource) for the ``keys`` in the memory stage, taken out as they are used."""
        for key in keys:
            made = self.streamer.pop(key)
            if made is not None:
                yield key, made

    def _spare(self) -> Iterator[tuple[int, Made]]:
        """Prefetched resources from the memory stage, most recently asked for first, while the
        GPU budget has room for them (what it has no room for waits in memory: uploaded, it
        would be evicted before its turn)."""
        memory = self.streamer.memory
        for key in reversed(list(memory)):
            if self.gpu.nbytes + memory.size(key) > self.gpu.budget_bytes:
                return
            made = self.streamer.pop(key)
            if made is not None:
                yield key, made

    def finish(self, plan: Plan) -> None:
        """After the frame is drawn: what it drew stays, the rest fits the GPU budget."""
        self.gpu.drawn(plan.drawn)
        self.gpu.evict(plan.drawn)

    def stream_stats(self) -> dict[str, float]:
        """The pipeline's figures since the last ``serve``, and the bytes each stage holds."""
        stages = self.streamer.resident()
        return {
            **self.streamer.stats.since(self._before),
            **self.units,
            "gpu_bytes": self.gpu.nbytes,
            "memory_bytes": stages["memory"],
            "cache_bytes": stages["cache"],
            "in_flight": self.streamer.in_flight(),
        }

    # --- prefetch (paper 004's radii along the velocity) -------------------------------------

    def _prefetch(self, cam: Camera, on_gpu: Callable[[int], bool]) -> None:
        """The memory and cache radii: what the camera will want ``ahead`` seconds on along its
        velocity. The predicted selections run on a worker (a few milliseconds each), and their
        keys are asked for once they are ready; what they ask for then may be a frame stale."""
        pending = self._predicted
        # on a simulated clock the prediction is used when the next one is due (waited for if
        # it has not finished): its keys then reach the workers at the same simulated time on
        # any machine, and a frame seldom waits
        simulated = bool(getattr(self.clock, "simulated", False))
        due = self.clock.now() - self._predicted_at >= PREDICT_EVERY
        if pending is not None and (pending.done() if not simulated else due):
            self._predicted = None
            t = time.perf_counter()
            predicted, counts = pending.result()
            if simulated:  # waited for a worker, not the frame's own work
                self.streamer.stats.sim_wait_ms += (time.perf_counter() - t) * 1e3
            # half the workers' places stay for what the frames themselves want; the radii's
            # and the velocity's keys share one half of each stage's budget (asked for apart,
            # they filled a stage and pushed out what the frames had loaded)
            room = max(1, self.options.in_flight // 2)
            for stage in ("memory", "cache"):
                lists = [keys for st, keys in predicted if st == stage]
                keys = self._within_budget(_interleave(lists), stage)
                self.streamer.request(keys, stage, on_gpu, room, prefetch=True)
            if counts is not None:
                self.units = {**counts, **self._states(predicted)}
        now = self.clock.now()
        pos = cam.position
        last, self._motion = self._motion, (now, pos)
        ahead = self.options.ahead
        radii = self._areas is not None and self.options.radii is not None
        if last is None or self._predicted is not None:
            return
        if not radii and (self._predict is None or not ahead):
            return
        # a few times a second is enough: the radii move little in a tenth of a second
        if now <= last[0] or now - self._predicted_at < PREDICT_EVERY:
            return
        self._predicted_at = now
        velocity = (pos - last[1]) / (now - last[0])
        self._predicted = self.streamer.submit(self._predictions, cam, pos, velocity, ahead)

    def _predictions(
        self,
        cam: Camera,
        pos: NDArray[np.float64],
        velocity: NDArray[np.float64],
        ahead: tuple[float, ...],
    ) -> tuple[list[tuple[Stage, list[int]]], dict[str, int] | None]:
        """On a worker: the areas around the camera (paper 004's radii), then the selections of
        the camera moved along its velocity; the keys to ask for by stage, most urgent first,
        and the areas' chunk counts."""
        out: list[tuple[Stage, list[int]]] = []
        counts = None
        if self._areas is not None and self.options.radii is not None:
            got = self._areas(cam, velocity)
            if got is not None:
                memory, cache, counts = got
                out += [("memory", memory), ("cache", cache)]
        if self._predict is not None:
            for i, seconds in enumerate(ahead):
                lon, lat, alt = ecef_to_geodetic(pos + velocity * seconds)
                keys = self._predict(cam.moved(lon=float(lon), lat=float(lat), alt=float(alt)))
                if keys is not None:  # None: the path would go under the ground
                    out.append(("memory" if i == 0 else "cache", keys))
        return out, counts

    def _within_budget(self, keys: list[int], stage: Stage) -> list[int]:
        """The most urgent of ``keys`` that half the ``stage``'s budget holds (at the stage's
        own mean bytes a resource, 64 KiB before it has any): asking for more would only make
        the prefetched resources push each other out."""
        lru = self.streamer.memory if stage == "memory" else self.streamer.cache
        budget = (self.options.memory_mb if stage == "memory" else self.options.cache_mb) * 2**20
        mean = lru.nbytes / len(lru) if len(lru) else 65536.0
        return keys[: max(1, int(0.5 * budget / max(mean, 1.0)))]

    def _states(self, predicted: list[tuple[Stage, list[int]]]) -> dict[str, int]:
        """Paper 004's resource units (the keys the areas hold) by state: on disk (or a
        server), in the cache stage, in memory, on the GPU (counted where each stands now)."""
        s = self.streamer
        n = {"units_disk": 0, "units_cached": 0, "units_memory": 0, "units_gpu": 0}
        for key in {k for _, keys in predicted for k in keys}:
            if key in self.gpu:
                n["units_gpu"] += 1
            elif key in s.memory:
                n["units_memory"] += 1
            elif key in s.cache:
                n["units_cached"] += 1
            else:
                n["units_disk"] += 1
        return n

    def close(self) -> None:
        self.streamer.close()


def _interleave(lists: list[list[int]]) -> list[int]:
    """The lists' keys taken in turn (each most urgent first), each key once."""
    out: list[int] = []
    seen: set[int] = set()
    for group in itertools.zip_longest(*lists):
        for key in group:
            if key is not None and key not in seen:
                seen.add(key)
                out.append(key)
    return out
