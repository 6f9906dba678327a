"""Frame by frame with no GL: the real frame loop (``lodscape.frame.FrameLoop``) over the terrain
layer, its loads served through a fake GPU (the ``GpuResources`` seam), a fake pass and a fake
target, on a simulated clock, over an in-memory height source; as cesium-native tests its
selection (``TestTilesetSelectionAlgorithm.cpp``). The Scene runs the same loop with the GL
passes."""

from __future__ import annotations

import numpy as np
import pytest

from _synthetic import fbm_heights
from lodscape.frame import FrameLoop
from lodscape.frame.terrain import TerrainDraws, TerrainLayer
from lodscape.geo.keys import is_texture
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.lod.camera import Camera
from lodscape.lod.view import FramePlan, TerrainView
from lodscape.store.provider import RasterProvider
from lodscape.stream import SimClock, StreamOptions
from lodscape.stream.gpu import Made
from lodscape.stream.loader import Loader, LoadReport
from lodscape.terrain.source import ArraySource


class FakeGpu:
    """The renderer's half of the GPU seam, keeping sizes instead of GL objects."""

    def __init__(self) -> None:
        self.live: dict[int, int] = {}
        self.uploads: list[int] = []
        self.released: list[int] = []

    def prepare(self, key: int, made: Made) -> Made:
        return made

    def upload_resource(self, key: int, made: Made) -> int:
        assert key not in self.live, f"key {key} uploaded twice"
        assert is_texture(key) == (not hasattr(made, "vertices"))
        self.live[key] = int(made.nbytes)
        self.uploads.append(key)
        return int(made.nbytes)

    def release(self, key: int) -> None:
        del self.live[key]
        self.released.append(key)


@pytest.fixture(scope="module")
def provider() -> RasterProvider:
    """10 km of fBm relief in UTM 16N, held in memory."""
    heights = fbm_heights(513, seed=3)
    return RasterProvider(
        ArraySource(heights, (20.0, 0, 700000.0, 0, -20.0, 4060000.0), "EPSG:32616")
    )


def _camera(provider: RasterProvider) -> Camera:
    """South of the data's centre, looking north over it from above its highest point."""
    b = provider.bounds_merc
    (lon, _), (lat, _) = merc_to_lonlat([(b.left + b.right) / 2, 0], [(b.bottom + b.top) / 2, 0])
    hi = provider.tree.height_range[1]
    return Camera(float(lon), float(lat) - 0.03, hi + 1200.0, pitch=-20, width=640, height=360)


@pytest.fixture(scope="module")
def cam(provider: RasterProvider) -> Camera:
    return _camera(provider)


class FakeTarget:
    """The frame's target: counts frames; an empty picture of the camera's size."""

    labelled = False

    def __init__(self) -> None:
        self.frames = 0

    def begin(self, camera: Camera, *, background: object = None) -> None:
        self.frames += 1

    def end(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        h, w = camera.height, camera.width
        return np.zeros((h, w, 3), np.uint8), np.full((h, w), np.inf, np.float32)


class FakeTerrainPass:
    """What the real pass needs of the loop: every mesh and texture it draws on the GPU."""

    def __init__(self, gpu: FakeGpu) -> None:
        self.gpu = gpu
        self.frames = 0

    def draw(self, draws: TerrainDraws, target: FakeTarget) -> None:
        keys = {k for it in draws.items for k in (it.key, it.texture)}
        missing = keys - set(self.gpu.live)
        assert not missing, f"drawn but not uploaded: {sorted(missing)[:5]}"
        self.frames += 1

    def figures(self) -> dict[str, int]:
        return {"fake_frames": self.frames}


class Rig:
    """The real frame loop over one provider's terrain layer, with a fake GPU, pass and target,
    on a simulated clock, stepped one frame at a time."""

    def __init__(
        self,
        provider: RasterProvider,
        gpu_budget: float = 1e12,
        upload_ms: float = 6.0,
        ahead: tuple[float, ...] = (),
        texture_levels: tuple[int, ...] | None = None,
    ) -> None:
        self.view = TerrainView(provider.tree, texture_levels=texture_levels)
        self.gpu = FakeGpu()
        self.clock = SimClock()
        self.provider = provider
        self.layer = TerrainLayer(self.view, self.fit)
        self.use_loader(
            Loader(
                provider,
                self.gpu,
                StreamOptions(ahead=ahead, upload_ms=upload_ms),
                self.clock,
                gpu_budget_bytes=gpu_budget,
                predict=lambda c: self.view.predict(self.fit(c)),
            )
        )
        #: The last plan's loads, and the frames stepped.
        self.wanted: set[int] = set()
        self.steps = 0

    def use_loader(self, loader: Loader) -> None:
        self.loader = loader
        self.target = FakeTarget()
        self.steps = 0
        self.loop = FrameLoop(loader, [(self.layer, FakeTerrainPass(self.gpu))], self.target)

    def fit(self, cam: Camera) -> Camera:
        return self.view.fit(cam, self.provider.ground_height(cam.lon, cam.lat))

    def step(
        self, cam: Camera, *, blocking: bool = False, dt: float = 1 / 30
    ) -> tuple[FramePlan, LoadReport]:
        n = len(self.gpu.uploads)
        self.loop.run(cam, blocking=blocking)
        plan, report = self.layer.last, self.loop.report
        assert plan is not None
        assert report is not None
        # what goes up is what the last frame wanted, what this one requires, and prefetched
        # resources only into free budget
        extra = set(self.gpu.uploads[n:]) - self.wanted - set(plan.required)
        assert not extra or self.loader.gpu.nbytes <= self.loader.gpu.budget_bytes
        self.wanted = {int(k) for k in plan.loads}
        # one target begun and read a frame, and the pass drew in every one
        self.steps += 1
        assert self.target.frames == self.steps == self.loop.stages[0][1].frames
        self.loader.streamer.drain()
        self.clock.advance(dt)
        return plan, report

    def close(self) -> None:
        self.loader.close()


def _roots(rig: Rig) -> set[int]:
    return {int(k) for k in rig.view._roots}


def test_the_first_frame_stalls_on_the_roots_only(provider: RasterProvider, cam: Camera) -> None:
    rig = Rig(provider)
    try:
        plan, report = rig.step(cam)
        assert rig.view.selections == 1
        # with nothing resident, what is drawn is the roots, taken at once
        assert plan.required
        assert set(plan.required) <= _roots(rig)
        assert np.all(plan.selection.z == provider.tree.zmin)
        assert report.stall_ms > 0.0
        assert plan.loads.size > 0
        assert int(plan.selection.fallback.max()) > 0
        plan2, report2 = rig.step(cam)
        assert rig.view.selections == 2
        assert plan2.required == []
        assert report2.stall_ms == 0.0
    finally:
        rig.close()


def test_streaming_converges_to_the_blocking_selection(
    provider: RasterProvider, cam: Camera
) -> None:
    rig = Rig(provider)
    blocking = Rig(provider)
    try:
        want, _ = blocking.step(cam, blocking=True)
        assert want.selection.fallback.max() == 0
        falls = []
        for _ in range(60):
            plan, _ = rig.step(cam)
            falls.append(int(plan.selection.fallback.max()))
            if plan.loads.size == 0:
                break
        assert falls[0] > 0
        assert falls[-1] == 0, falls
        # never a hole: every frame drew only resident keys (checked in step), and at the end
        # the same tiles as a one-shot render
        assert set(plan.selection.keys.tolist()) == set(want.selection.keys.tolist())
        assert rig.view.selections == len(falls)
    finally:
        rig.close()
        blocking.close()


def test_uploads_keep_to_their_time_slice(provider: RasterProvider, cam: Camera) -> None:
    rig = Rig(provider, upload_ms=1e-9)
    try:
        rig.step(cam, dt=1.0)  # the roots
        counts = []
        for _ in range(8):
            before = len(rig.gpu.uploads)
            rig.step(cam, dt=1.0)  # a second a frame: the workers are never the limit
            counts.append(len(rig.gpu.uploads) - before)
        # a slice smaller than any upload lets one through per frame, never more
        assert max(counts) == 1
        assert sum(counts) == 8
    finally:
        rig.close()


def test_what_the_last_frame_drew_is_never_evicted(provider: RasterProvider, cam: Camera) -> None:
    rig = Rig(provider, gpu_budget=1.0)
    try:
        cams = [cam.moved(lon=cam.lon + 0.01 * i) for i in range(6)]
        for c in cams:
            n = len(rig.gpu.uploads)
            # a simulated second a frame: the loads finish however slow this machine is
            plan, _ = rig.step(c, dt=1.0)
            fresh = set(rig.gpu.uploads[n:])
            # a budget of one byte keeps exactly what this frame drew, and what it uploaded for
            # the next (it is not drawn yet: freeing it would only load it again)
            assert set(rig.gpu.live) == set(plan.drawn) | fresh
        # the budget did free what the frames before drew
        assert rig.gpu.released
    finally:
        rig.close()


def test_a_failing_source_is_retried_while_ancestors_stand_in(
    provider: RasterProvider, cam: Camera
) -> None:
    class Flaky:
        """The provider, with every texture below the roots failing for a while."""

        def __init__(self) -> None:
            self.failing = True
            self.tree = provider.tree

        def fetch(self, key: int) -> bytes:
            if self.failing and is_texture(key):
                from lodscape.geo.keys import tile_of

                if tile_of(key).z > provider.tree.zmin:
                    raise OSError("server answered 500")
            return provider.fetch(key)

        def decode(self, key: int, data: bytes) -> Made:
            return provider.decode(key, data)

    flaky = Flaky()
    rig = Rig(provider)
    rig.loader.close()
    rig.use_loader(
        Loader(flaky, rig.gpu, StreamOptions(ahead=()), rig.clock, gpu_budget_bytes=1e12)
    )
    try:
        for _ in range(10):
            plan, _ = rig.step(cam)
        # drawn from the roots' textures: nothing finer came, and nothing was left undrawn
        assert np.all(plan.selection.texture_up >= plan.selection.z - provider.tree.zmin)
        assert rig.loader.streamer.failures()
        flaky.failing = False
        for _ in range(80):
            rig.clock.advance(1.0)  # past the backoff
            plan, _ = rig.step(cam)
            if plan.loads.size == 0:
                break
        assert plan.loads.size == 0
        assert int(plan.selection.fallback.max()) == 0
    finally:
        rig.close()


def test_prefetched_resources_wait_in_memory(provider: RasterProvider, cam: Camera) -> None:
    """Flying north, the radii ahead fill the memory stage; with a full GPU none of it goes up
    before a frame wants it (``step`` checks every upload against the frame's plan), with room
    it does."""
    path = [cam.moved(lat=cam.lat + 0.0005 * i) for i in range(30)]
    full = Rig(provider, gpu_budget=1.0, ahead=(1.0, 3.0))
    roomy = Rig(provider, ahead=(1.0, 3.0))
    try:
        wanted: set[int] = set()
        held = 0
        for c in path:
            full.step(c, dt=0.1)
            plan, _ = roomy.step(c, dt=0.1)
            wanted |= {int(k) for k in plan.loads} | set(plan.required)
            memory = set(full.loader.streamer.memory)
            # at no frame is a prefetched tile in memory on the full GPU as well
            assert not memory & set(full.gpu.live)
            held = max(held, len(memory))
        assert full.view.selections == 30
        # the memory radius holds decoded tiles the frames have not wanted yet (how many at a
        # given frame follows how the selection changes ahead: counted over the flight)
        assert held > 0
        # with room on the GPU, prefetched tiles went up before any frame asked for them
        assert set(roomy.gpu.uploads) - wanted
    finally:
        full.close()
        roomy.close()


def test_the_blocking_policy_loads_everything_in_one_frame(
    provider: RasterProvider, cam: Camera
) -> None:
    rig = Rig(provider)
    try:
        plan, report = rig.step(cam, blocking=True)
        assert rig.view.selections == 1
        assert report.loaded == len(plan.drawn)
        assert set(plan.required) == set(plan.drawn)
        assert int(plan.selection.fallback.max()) == 0
        plan2, report2 = rig.step(cam, blocking=True)
        assert plan2.required == []
        assert report2.loaded == 0
    finally:
        rig.close()


def test_an_imagery_layer_is_loaded_at_its_own_levels_and_never_waited_for(
    provider: RasterProvider, cam: Camera
) -> None:
    """A layer whose finest level is one below the terrain's texture level: blocking frames
    require its tiles, at levels capped by its own; streaming frames never do (none, or an
    ancestor's, until they come), and converge to the blocking frame's."""
    from lodscape.geo.keys import is_overlay, layer_of_array
    from lodscape.lod.select import NO_TEXTURE

    own = provider.texture_levels[0]
    levels = (own, own + 1)
    near = cam.moved(alt=cam.alt - 900.0)
    blocking = Rig(provider, texture_levels=levels)
    rig = Rig(provider, texture_levels=levels)
    try:
        want, _ = blocking.step(near, blocking=True)
        sel = want.selection
        assert sel.layer_keys.shape == (1, sel.count)
        assert (layer_of_array(sel.layer_keys[0]) == 1).all()
        z_layer = sel.z - sel.layer_up[0]
        assert int(z_layer.max()) <= own + 1
        # the band asks for more than the terrain's own texture: tiles split below it
        assert int(z_layer.max()) == own + 1
        assert any(is_overlay(k) for k in want.required)
        first, report = rig.step(near)
        assert not any(is_overlay(k) for k in first.required)
        assert (first.selection.layer_keys == NO_TEXTURE).all()
        assert all(key == -1 for it in first.items for key, _ in it.layers)
        for _ in range(80):
            plan, report = rig.step(near)
            assert report.stall_ms == 0.0
            if plan.loads.size == 0:
                break
        assert plan.selection.layer_fallbacks == 0
        got = sorted(int(k) for k in plan.selection.layer_keys[0])
        assert got == sorted(int(k) for k in sel.layer_keys[0])
    finally:
        blocking.close()
        rig.close()


def test_a_still_camera_over_a_still_terrain_reuses_its_plan(
    provider: RasterProvider, cam: Camera
) -> None:
    """A frame whose camera, options, resident keys and tree are the last frame's, after a
    selection that made itself again from them, is planned as the last one was (as
    GeoMipTerrain's update is idle while its focal point stays): the selection a fresh one
    would make. A load that came, a camera that moved or geomorphing frames select again."""
    from lodscape.lod.select import select
    from lodscape.lod.view import _same_selection

    rig = Rig(provider)
    rig.view.morph = False  # a still picture's view
    try:
        reused = []
        for _ in range(40):
            plan, _ = rig.step(cam)
            reused.append(rig.view.reused)
        assert rig.view.selections == 40
        # streamed: frames select while loads come, then the plan stands
        assert reused[0] == 0
        assert 0 < reused[-1] < 40
        assert reused[-1] - reused[-5] == 4
        resident = rig.loader.resident()
        fresh = select(
            rig.view.select_options, plan.camera, provider.tree, rig.view.previous,
            np.union1d(resident, rig.view._roots), rig.view.texture_levels,
        )  # fmt: skip
        assert _same_selection(fresh, plan.selection)
        # moved: selected again
        n = rig.view.reused
        rig.step(cam.moved(lat=cam.lat + 1e-4))
        assert rig.view.reused == n
        # geomorphing frames never stand still (their tiles glide a step a frame)
        rig.view.morph = True
        for _ in range(4):
            rig.step(cam)
        assert rig.view.reused == n
    finally:
        rig.close()
