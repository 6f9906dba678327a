"""One loader for every frame: the streamer's cache and memory stages, the GPU stage, and the
prefetch along the camera's velocity, serving a ``FramePlan`` with one of two policies.

- **blocking** (one-shot renders): every key the plan requires is fetched and decoded on the
  workers at once, then uploaded; nothing else is asked for.
- **streaming** (flights, the viewer): what the plan requires (roots with nothing above them) is
  taken at once and counted as a stall; its loads are requested up to the memory stage, the
  prefetch asks for what the camera will want, and the loads that are decoded are uploaded within
  a time slice, most urgent first. What goes up shows from the next frame on. Prefetched
  resources wait decoded in the memory stage until a frame wants them: on the GPU, where only
  what was drawn is safe from eviction, they would be freed before their turn (and were, once:
  a flight fell back more than one level in 119 of 300 frames).

After the frame is drawn, ``finish`` marks what it drew and frees what the GPU budget cannot keep,
never one of those.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.frames import ecef_to_geodetic
from lodscape.lod.camera import Camera
from lodscape.lod.view import FramePlan
from lodscape.stream.gpu import GpuResources, GpuStage, Made
from lodscape.stream.streamer import Clock, Source, Streamer, StreamOptions, StreamStats

__all__ = ["LoadReport", "Loader"]

#: Seconds (on the loader's clock) between predictions of where the camera is going.
PREDICT_EVERY = 0.15

Stage = Literal["memory", "cache"]
#: The keys a fitted camera would draw, or None where it cannot be (under the ground).
Predict = Callable[[Camera], "list[int] | None"]


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
    ) -> None:
        self.options = options
        self.streamer = Streamer(source, options, clock, prepare=gpu.prepare)
        self.gpu = GpuStage(gpu, gpu_budget_bytes)
        self._predict = predict
        self._motion: tuple[float, NDArray[np.float64]] | None = None
        self._predicted_at = -math.inf
        self._predicted: Future[list[tuple[Stage, list[int]]]] | None = None
        self._before: StreamStats = self.streamer.stats.snapshot()

    @property
    def clock(self) -> Clock:
        return self.streamer.clock

    def resident(self) -> NDArray[np.uint64]:
        """The keys on the GPU, sorted."""
        return self.gpu.keys()

    def serve(self, plan: FramePlan, *, blocking: bool) -> LoadReport:
        """Bring what ``plan`` requires onto the GPU, and (streaming) move the rest along."""
        t0 = time.perf_counter()
        self._before = self.streamer.stats.snapshot()
        on_gpu = self.gpu.__contains__
        taken = 0
        stall = 0.0
        if plan.required:
            made = self.streamer.take_many(plan.required)
            for key, m in zip(plan.required, made, strict=True):
                self.gpu.upload(key, m)
            taken = len(plan.required)
            stall = (time.perf_counter() - t0) * 1e3
        uploaded = 0
        if not blocking:
            s = self.streamer
            s.request((int(k) for k in plan.loads), "memory", on_gpu)
            self._prefetch(plan.camera, on_gpu)
            s.collect()
            keys = [int(k) for k in plan.loads]
            tu = time.perf_counter()
            uploaded = self.gpu.upload_within(self._ready(keys), self.options.upload_ms)
            s.stats.upload_ms += (time.perf_counter() - tu) * 1e3
            s.stats.uploaded += uploaded
        self.streamer.stats.uploaded += taken
        return LoadReport(taken + uploaded, stall, (time.perf_counter() - t0) * 1e3)

    def _ready(self, keys: list[int]) -> Iterator[tuple[int, Made]]:
        """(key, resource) for the ``keys`` in the memory stage, taken out as they are used."""
        for key in keys:
            made = self.streamer.pop(key)
            if made is not None:
                yield key, made

    def finish(self, plan: FramePlan) -> None:
        """After the frame is drawn: what it drew stays, the rest fits the GPU budget."""
        self.gpu.drawn(plan.drawn)
        self.gpu.evict(plan.drawn)

    def stream_stats(self) -> dict[str, float]:
        """The pipeline's figures since the last ``serve``, and the bytes each stage holds."""
        stages = self.streamer.resident()
        return {
            **self.streamer.stats.since(self._before),
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
        if pending is not None and pending.done():
            self._predicted = None
            for stage, keys in pending.result():
                self.streamer.request(keys, stage, on_gpu)
        now = self.clock.now()
        pos = cam.position
        last, self._motion = self._motion, (now, pos)
        ahead = self.options.ahead
        if self._predict is None or last is None or not ahead or self._predicted is not None:
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
    ) -> list[tuple[Stage, list[int]]]:
        assert self._predict is not None
        out: list[tuple[Stage, list[int]]] = []
        for i, seconds in enumerate(ahead):
            lon, lat, alt = ecef_to_geodetic(pos + velocity * seconds)
            keys = self._predict(cam.moved(lon=float(lon), lat=float(lat), alt=float(alt)))
            if keys is not None:  # None: the path would go under the ground
                out.append(("memory" if i == 0 else "cache", keys))
        return out

    def close(self) -> None:
        self.streamer.close()
