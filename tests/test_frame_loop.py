"""The frame loop with several layers and no GL: the globe's facets and its imagery layers, and
stand-in layers, through one loader into a fake GPU, drawn by fake passes into a fake target,
frame by frame on a simulated clock."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from lodscape.frame import FrameLoop, FrameStats, LoadPlan
from lodscape.frame.globe import (
    GlobeDraws,
    GlobeImageryLayer,
    GlobeLayer,
    GlobeOptions,
    ImageryDraws,
    LayerSource,
)
from lodscape.geo.keys import layer_of, tile_of
from lodscape.lod.camera import Camera
from lodscape.stream import SimClock, StreamOptions
from lodscape.stream.loader import Loader, LoadReport


class Gpu:
    """The GPU seam keeping sizes: what is live, what went up, what was freed."""

    def __init__(self) -> None:
        self.live: dict[int, int] = {}
        self.uploads: list[int] = []

    def prepare(self, key: int, made: Any) -> Any:
        return made

    def upload_resource(self, key: int, made: Any) -> int:
        assert key not in self.live, f"key {key} uploaded twice"
        self.live[key] = int(made.nbytes)
        self.uploads.append(key)
        return int(made.nbytes)

    def release(self, key: int) -> None:
        del self.live[key]


class Layer:
    """An imagery layer served from memory: every tile to its max zoom, a flat colour each."""

    def __init__(self, index: int, max_zoom: int = 6) -> None:
        self.index = index
        self.max_zoom = max_zoom
        self.fetched: list[tuple[int, int, int]] = []

    def fetch(self, z: int, x: int, y: int) -> bytes:
        self.fetched.append((z, x, y))
        return bytes([z, x % 256, y % 256])

    def decode(self, data: bytes, size: int) -> np.ndarray:
        return np.full((8, 8, 4), data[0], np.uint8)


@dataclass
class Target:
    labelled = False
    log: list[str] = field(default_factory=list)

    def begin(self, camera: Camera, *, background: Any = None) -> None:
        self.log.append("begin")

    def end(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        self.log.append("end")
        h, w = camera.height, camera.width
        return np.zeros((h, w, 3), np.uint8), np.full((h, w), np.inf, np.float32)


class Pass:
    """Records its draws in the target's log; checks every image it would draw is on the GPU."""

    def __init__(self, name: str, gpu: Gpu) -> None:
        self.name = name
        self.gpu = gpu
        self.last: Any = None

    def draw(self, draws: Any, target: Target) -> None:
        target.log.append(self.name)
        self.last = draws
        if isinstance(draws, ImageryDraws):
            keys = {k for layer in draws.layers for k in layer.keys}
            assert keys <= set(self.gpu.live), "an image drawn that is not on the GPU"

    def figures(self) -> dict[str, Any]:
        return {f"{self.name}_drawn": 1}


def _globe_loop(
    layers: list[Layer], *, stream: bool, budget: float = 1e12
) -> tuple[FrameLoop, Gpu, SimClock, Target]:
    gpu, clock, target = Gpu(), SimClock(), Target()
    options = StreamOptions(ahead=()) if stream else StreamOptions(cache_mb=8.0, ahead=())
    loader = Loader(
        LayerSource(layers), gpu, options, clock, gpu_budget_bytes=budget, optional=lambda k: True
    )
    globe = GlobeLayer(GlobeOptions())
    imagery = GlobeImageryLayer(layers, globe)
    stages = [(globe, Pass("globe", gpu)), (imagery, Pass("imagery", gpu))]
    return FrameLoop(loader, stages, target), gpu, clock, target


CAM = Camera(10.0, 45.0, 2.0e6, pitch=-90.0, width=320, height=240)


def test_a_blocking_globe_frame_loads_every_layer_tile_once_and_draws_in_order() -> None:
    layers = [Layer(1), Layer(2, max_zoom=3)]
    loop, gpu, _, target = _globe_loop(layers, stream=False)
    try:
        loop.run(CAM, blocking=True)
        assert target.log == ["begin", "globe", "imagery", "end"]
        draws = loop.stages[1][1].last  # type: ignore[attr-defined]
        assert isinstance(draws, ImageryDraws)
        assert len(draws.layers) == 2
        # each layer at its own levels, never past its max zoom, and every tile fetched once
        for layer, drawn in zip(layers, draws.layers, strict=True):
            assert {layer_of(k) for k in drawn.keys} == {layer.index}
            assert max(tile_of(k).z for k in drawn.keys) <= layer.max_zoom
            assert len(layer.fetched) == len(set(layer.fetched))
        assert isinstance(loop.stages[0][1].last, GlobeDraws)  # type: ignore[attr-defined]
        stats = loop.last
        assert stats is not None
        assert stats.plans == 2
        assert stats.section("globe")["facets"] > 0
        assert stats.section("globe_imagery")["imagery_missing"] == 0
        flat = stats.as_dict()
        assert flat["globe_drawn"] == 1
        assert flat["imagery_tiles"] > 0
        # the same view again: nothing to load
        before = len(gpu.uploads)
        loop.run(CAM, blocking=True)
        assert len(gpu.uploads) == before
    finally:
        loop.loader.close()


def test_streaming_globe_imagery_never_waits_and_converges() -> None:
    layers = [Layer(1)]
    loop, _gpu, clock, target = _globe_loop(layers, stream=True)
    try:
        missing = []
        for _ in range(60):
            loop.run(CAM, blocking=False)
            assert loop.report is not None
            assert loop.report.stall_ms == 0.0
            missing.append(loop.last.section("globe_imagery")["imagery_missing"])  # type: ignore[union-attr]
            loop.loader.streamer.drain()
            clock.advance(1 / 30)
            if missing[-1] == 0 and not loop.plan.loads.size:  # type: ignore[union-attr]
                break
        assert missing[0] > 0  # the first frame had nothing: the globe showed there
        assert missing[-1] == 0
        assert target.log.count("begin") == len(missing)
    finally:
        loop.loader.close()


def test_what_a_frame_drew_stays_and_the_budget_frees_the_rest() -> None:
    layers = [Layer(1)]
    loop, gpu, _, _ = _globe_loop(layers, stream=False, budget=1.0)
    try:
        loop.run(CAM, blocking=True)
        first = set(gpu.live)
        far = CAM.moved(lon=CAM.lon + 120.0)
        loop.run(far, blocking=True)
        plan = loop.plan
        assert plan is not None
        # a one-byte budget keeps exactly what the last frame drew
        assert set(gpu.live) == set(plan.drawn)
        assert first - set(gpu.live)
    finally:
        loop.loader.close()


class Learner:
    """A layer that learns from each of its first ``n`` plans' loads (a server's tree)."""

    name = "learner"

    def __init__(self, n: int) -> None:
        self.n = n
        self.plans = 0

    def plan(self, camera: Camera, resident: np.ndarray, *, blocking: bool) -> LoadPlan:
        self.plans += 1
        return LoadPlan(camera, [], np.zeros(0, np.uint64), frozenset())

    def learned(self) -> bool:
        return self.plans <= self.n

    def draws(self, report: LoadReport, loader: Loader) -> int:
        return self.plans

    def figures(self) -> dict[str, Any]:
        return {"learner_plans": self.plans}


@pytest.mark.parametrize("n", [0, 3, 100])
def test_a_blocking_frame_plans_again_while_a_layer_learns(n: int) -> None:
    gpu, clock, target = Gpu(), SimClock(), Target()
    loader = Loader(LayerSource([]), gpu, StreamOptions(ahead=()), clock, gpu_budget_bytes=1e9)
    learner = Learner(n)
    loop = FrameLoop(loader, [(learner, Pass("learner", gpu))], target, rounds=8)
    try:
        loop.run(CAM, blocking=True)
        # once, then once per lesson, at most the loop's rounds
        assert learner.plans == 1 + min(n, 8)
        assert loop.last is not None
        assert loop.last.plans == learner.plans
        assert target.log.count("learner") == 1  # drawn once, from the last plan
        learner.plans = 0
        loop.run(CAM, blocking=False)  # a streamed frame never waits to learn
        assert learner.plans == 1
    finally:
        loader.close()


def test_frame_stats_are_by_keyword_with_a_section_per_layer() -> None:
    with pytest.raises(TypeError):
        FrameStats(1, 2.0, 3.0, 4.0, 5.0)  # type: ignore[misc]
    stats = FrameStats(
        loaded=1,
        resident_mb=2.0,
        select_ms=3.0,
        load_ms=4.0,
        draw_ms=5.0,
        layers={
            "terrain": {"selection": {"tiles": 7}, "triangles": 9, "terrain_mode": "cpu"},
            "city": {"city_triangles": 4},
        },
    )
    assert stats.selection == {"tiles": 7}
    assert stats.triangles == 9
    assert stats.terrain_mode == "cpu"
    assert stats.city == {"city_triangles": 4}
    flat = stats.as_dict()
    assert flat["tiles"] == 7
    assert flat["city_triangles"] == 4
    assert flat["loaded"] == 1
    assert "terrain_mode" not in flat  # words stay out of the numbers
