"""One frame, many layers, with no GL: the loop every picture goes through.

    loop = FrameLoop(loader, [(globe, globe_pass), (terrain, terrain_pass), (city, city_pass)],
                     target)
    rgb, dist, stats = loop.run(camera, blocking=True)

A ``Layer`` plans what it draws for a camera (a pure selection over what is resident) and says
what it will draw once the loads are served; a ``Pass`` draws that into the frame's ``Target``.
One ``Loader`` serves every layer's plan at once (one budget, one set of workers, a tile that two
layers use loaded once), and a layer whose loads taught it something (a server's tree that learns
its levels as its tiles come, the statistics of a raster made as views reach them) plans again,
in blocking frames, until nothing new is learnt. The passes then draw in the order given into one
target with one depth test, the target is read back once, and what the frame drew stays on the
GPU while the budget frees the rest (``Loader.finish``).

The seams are protocols so that the real loop runs in tests with stand-ins for the GPU
(``stream.gpu.GpuResources``), the passes and the target, frame by frame, as cesium-native tests
its selection (``TestTilesetSelectionAlgorithm.cpp``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape.lod.camera import Camera
from lodscape.stream.loader import Loader, LoadReport, Plan

__all__ = ["SKY", "FrameLoop", "FrameStats", "Layer", "LoadPlan", "Pass", "Target"]

U64 = NDArray[np.uint64]
Rgb = tuple[float, float, float]

#: The sky's colour (RGB, 0..1): a scene's background, and the globe's low down.
SKY = (0.62, 0.75, 0.88)

#: Plans a blocking frame makes over layers that learn as their tiles come (a level of a
#: server's terrain each), at most.
MAX_LEARNING_ROUNDS = 32


class Layer(Protocol):
    """One kind of content of a frame (the globe's facets, its imagery, the terrain, the city,
    the ellipsoid): what it would draw, and what it needs loaded for that."""

    #: The layer's section in the frame's figures.
    name: str

    def plan(self, camera: Camera, resident: U64, *, blocking: bool) -> Plan | None:
        """What ``camera`` needs (``stream.loader.Plan``) given the ``resident`` keys (sorted);
        None: nothing to load."""
        ...

    def learned(self) -> bool:
        """Whether the loads since the last ``plan`` taught the layer something a new plan
        would use (blocking frames plan again)."""
        ...

    def draws(self, report: LoadReport, loader: Loader) -> Any:
        """What the layer's pass draws this frame, once its loads are served."""
        ...

    def figures(self) -> dict[str, float]:
        """The frame's figures of this layer (its section of ``FrameStats``)."""
        ...


class Target(Protocol):
    """Where a frame is drawn: one colour, one distance along the view axis, one depth."""

    def begin(self, camera: Camera, *, background: Rgb | None = None) -> Any:
        """Start a frame of ``camera``'s size, cleared to ``background``."""
        ...

    def end(self, camera: Camera) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """End the frame: RGB (H, W, 3) and distance (H, W), read back once (empty arrays where
        the target is shown where it is, a window's)."""
        ...


class Pass(Protocol):
    """Draws one layer's ``draws`` into the frame's target (GL state lives in ``render``); the
    target is the loop's, whose kind the pass knows (the renderer's, or a test's fake)."""

    def draw(self, draws: Any, target: Any) -> None: ...

    def figures(self) -> dict[str, Any]:
        """What the pass drew this frame (merged into its layer's section)."""
        ...


@dataclass(frozen=True)
class LoadPlan:
    """Several layers' plans as one for the loader: their required keys and their loads in
    the layers' order (each key once), what all of them draw."""

    camera: Camera
    required: list[int]
    loads: U64
    drawn: frozenset[int]

    @classmethod
    def of(cls, camera: Camera, plans: Sequence[Plan]) -> LoadPlan:
        if len(plans) == 1:
            p = plans[0]
            return cls(camera, list(p.required), p.loads, p.drawn)
        required = list(dict.fromkeys(k for p in plans for k in p.required))
        loads = np.concatenate([np.asarray(p.loads, np.uint64) for p in plans] or [_NONE])
        _, first = np.unique(loads, return_index=True)
        drawn = frozenset().union(*(p.drawn for p in plans))
        return cls(camera, required, loads[np.sort(first)], drawn)


_NONE = np.zeros(0, np.uint64)


@dataclass(frozen=True, kw_only=True)
class FrameStats:
    """What one frame drew and how long its stages took: the loop's own figures, and a section
    per layer (``layers``; ``as_dict`` flattens them, the terrain's under their plain names)."""

    #: Resources uploaded this frame, and the MiB the GPU keeps.
    loaded: int
    resident_mb: float
    #: Milliseconds of the layers' plans, of the loads (``serve``, and ``begin``'s uploads when
    #: streaming), and of the draws: the layers' last steps, the passes and the read-back.
    select_ms: float
    load_ms: float
    draw_ms: float
    #: Plans made: one per layer, more where a layer learnt from its loads.
    plans: int = 1
    #: The streaming pipeline's figures for this frame (empty when not streaming).
    stream: dict[str, float] = field(default_factory=dict)
    #: Each layer's figures by its name.
    layers: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, float | int]:
        """Every figure by name, flat (a section's sub-sections too; words left out)."""
        out: dict[str, float | int] = {}
        for section in self.layers.values():
            _flatten(section, out)
        out.update(
            loaded=self.loaded,
            resident_mb=round(self.resident_mb, 2),
            select_ms=round(self.select_ms, 2),
            load_ms=round(self.load_ms, 2),
            draw_ms=round(self.draw_ms, 2),
        )
        out.update(self.stream)
        return out

    def with_section(self, name: str, figures: dict[str, Any]) -> FrameStats:
        """These statistics with one more section (the scene's imagery figures)."""
        return replace(self, layers={**self.layers, name: figures})

    def section(self, name: str) -> dict[str, Any]:
        """A layer's figures (empty where the frame had no such layer)."""
        return self.layers.get(name, {})

    # the terrain's, the city's and the imagery's figures by their names of old

    @property
    def selection(self) -> dict[str, float | int]:
        """The terrain's selection (``lod.select.Selection.stats``)."""
        return dict(self.section("terrain").get("selection", {}))

    @property
    def triangles(self) -> int:
        """Triangles the terrain's pass drew, skirts included."""
        return int(self.section("terrain").get("triangles", 0))

    @property
    def draw_calls(self) -> int:
        return int(self.section("terrain").get("draw_calls", 0))

    @property
    def submit_ms(self) -> float:
        """Milliseconds the CPU spent issuing the terrain's draws (no GPU wait)."""
        return float(self.section("terrain").get("submit_ms", 0.0))

    @property
    def backfacing(self) -> int:
        """Patches skipped as facing away from the camera, and the triangles they held."""
        return int(self.section("terrain").get("backfacing", 0))

    @property
    def backfacing_triangles(self) -> int:
        return int(self.section("terrain").get("backfacing_triangles", 0))

    @property
    def terrain_mode(self) -> str:
        return str(self.section("terrain").get("terrain_mode", "cpu"))

    @property
    def city(self) -> dict[str, int]:
        """The city pass's figures (draw calls, triangles, objects culled…)."""
        return dict(self.section("city"))

    @property
    def imagery(self) -> dict[str, int]:
        """Imagery layers' failed tiles by kind, tiles drawn without their layer tile, the
        servers' requests (``Scene`` adds them)."""
        return dict(self.section("imagery"))


def _flatten(section: dict[str, Any], out: dict[str, float | int]) -> None:
    for key, value in section.items():
        if isinstance(value, dict):
            _flatten(value, out)
        elif isinstance(value, int | float | np.integer | np.floating):
            out[key] = value.item() if isinstance(value, np.generic) else value


class FrameLoop:
    """Layers, each drawn by its pass, into one target, their loads served by one loader."""

    def __init__(
        self,
        loader: Loader,
        stages: Sequence[tuple[Layer, Pass]],
        target: Target,
        *,
        rounds: int = MAX_LEARNING_ROUNDS,
    ) -> None:
        self.loader = loader
        self.stages = list(stages)
        self.target = target
        self.rounds = rounds
        #: The last frame's merged plan, each stage's draws, and its statistics.
        self.plan: LoadPlan | None = None
        self.draws: list[Any] = []
        #: What the loader did for the last frame.
        self.report: LoadReport | None = None
        self.last: FrameStats | None = None

    def run(
        self,
        camera: Camera,
        *,
        blocking: bool,
        background: Rgb | None = None,
    ) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """One frame of ``camera``: plan, load (``blocking``: everything the plans require;
        else what came since the last frame, never waiting but for the roots), plan again
        while a layer learnt, draw the passes in order, read back, and keep what was drawn."""
        loader = self.loader
        t0 = time.perf_counter()
        if not blocking:
            loader.begin()
        layers = [layer for layer, _ in self.stages]
        plans = [layer.plan(camera, loader.resident(), blocking=blocking) for layer in layers]
        plan_s = time.perf_counter() - t0
        made = len(layers)
        report = loader.serve(self._merge(camera, plans), blocking=blocking)
        for _ in range(self.rounds if blocking else 0):
            again = [i for i, layer in enumerate(layers) if layer.learned()]
            if not again:
                break
            t1 = time.perf_counter()
            for i in again:
                plans[i] = layers[i].plan(camera, loader.resident(), blocking=True)
            plan_s += time.perf_counter() - t1
            made += len(again)
            report = loader.serve(self._merge(camera, plans), blocking=True)
        t2 = time.perf_counter()
        self.report = report
        draws = self.draws = [layer.draws(report, loader) for layer in layers]
        self.target.begin(camera, background=background)
        for (_, each), what in zip(self.stages, draws, strict=True):
            each.draw(what, self.target)
        rgb, dist = self.target.end(camera)
        t4 = time.perf_counter()
        # what the layers drew in place of what had not come stays too
        loader.finish(self._merge(camera, plans))
        stream: dict[str, float] = {}
        if not blocking:
            stream = loader.stream_stats()
            # a simulated clock's waits for the workers are not the frame's own work
            waited = float(stream.get("sim_wait_ms", 0.0))
            stream.update(
                stall_ms=round(report.stall_ms, 2),
                frame_cpu_ms=round(max((t2 - t0) * 1e3 - waited, 0.0), 2),
            )
        self.last = FrameStats(
            loaded=report.loaded,
            resident_mb=loader.gpu.nbytes / 2**20,
            select_ms=plan_s * 1e3,
            load_ms=report.load_ms,
            draw_ms=(t4 - t2) * 1e3,
            plans=made,
            stream=stream,
            layers={
                layer.name: {**layer.figures(), **each.figures()} for layer, each in self.stages
            },
        )
        return rgb, dist

    def _merge(self, camera: Camera, plans: Sequence[Plan | None]) -> LoadPlan:
        self.plan = LoadPlan.of(camera, [p for p in plans if p is not None])
        return self.plan
