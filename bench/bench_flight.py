"""Flight benchmark (paper 004): fast and low over a terrain far larger than the memory budget,
the staged pipeline against loading when needed.

Terrain: a 4097² spectral fBm DEM (5 m, 20 km across, UTM 17N) built into a tileset. The flight
crosses it at 300 m/s, 300 m above the ground (smoothed), 30 frames/s, 640×360, on a simulated
clock (each frame gets the 33.3 ms a real-time viewer would give it). Budgets: 16 MiB per stage.

Three runs over the same cameras:
- staged: the pipeline with prefetch (the default StreamOptions: paper 004's radii and the
  velocity's predictions);
- async, no prefetch: the same pipeline asked only for what each frame wants;
- naive (paper 004's "load when it is needed"): every missing tile loaded before the frame is
  drawn, as ``lodscape render`` does; its loads count against the frame.

They run twice: on the local tileset alone, and with imagery from a loopback tile server that
answers each tile after ``--latency-ms`` (a remote server), where loading when needed hurts.
With ``--ortho``, instead, the staged pipeline flies with a local orthophoto 8× finer than
the DEM (0.625 m, a JPEG-compressed tiled GeoTIFF of 2-pixel cells with overviews, made here,
32,776² for the 4097² DEM) as an imagery layer at its own levels (issue 18): the tree then goes
three levels below the tileset's terrain, its stored surface cut finer. It is compared with the
same flight over the tileset alone.

Reported: frames that fall back more than one level, frames whose CPU work (selection, stalls,
uploads) exceeds the frame's 33.3 ms, and peak resident bytes, after the first second.

With ``--fast 600``, instead (paper 004's case, where prefetch must pay): 600 m/s with a 90°
turn, the tileset on slow storage (``--storage-ms`` per read, charged on the simulated clock),
flown with paper 004's radii (memory and cache areas all round, larger in front, pushed ahead
by the speed) beside the velocity's predictions, with the velocity's alone, and with no
prefetch: fallbacks over one level, frames over budget, stalls and bytes read. ``--budget-mb``
sets the stages' budgets (GPU too): the areas must fit them for the radii to pay.

The simulated clock waits for the workers' jobs (their cost on the clock decides when a result
is usable), so the fallbacks and bytes read are the same on any machine; "over budget" is the
render thread's own work, in real time (its waits for the workers left out).

    python bench/bench_flight.py [--work DIR] [--seconds 40] [--fast 600 --storage-ms 40
                                  --budget-mb 64]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import lodscape
from bench_spine import write
from lodscape import Camera, SceneOptions
from lodscape.build import build
from lodscape.flight import fly
from lodscape.geo.tiles import lonlat_to_merc, merc_to_lonlat
from lodscape.imagery.layers import ImageryLayer
from lodscape.imagery.sources import HttpSource
from lodscape.store.provider import LayeredProvider, Provider
from lodscape.store.tileset import TilesetProvider
from lodscape.stream import SimClock, StreamOptions
from lodscape.terrain.source import RasterSource

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _tileserver import TileServer

FPS = 30.0
SPEED = 300.0
AGL = 300.0
BUDGET_MB = 16.0


def cameras(dem: Path, seconds: float) -> list[Camera]:
    """A west-to-east line across the DEM's middle, 300 m above its smoothed ground."""
    src = RasterSource(dem)
    b = src.bounds_merc
    y = (b.top + b.bottom) / 2
    (lon0, lon1), (lat, _) = merc_to_lonlat([b.left + 500, b.right - 500], [y, y])
    lon0, lon1, lat = float(lon0), float(lon1), float(lat)
    metres = (lon1 - lon0) * 111_320 * math.cos(math.radians(lat))
    n = int(min(seconds, metres / SPEED) * FPS)
    lons = lon0 + (lon1 - lon0) * (SPEED * np.arange(n) / FPS) / metres
    xm, ym = lonlat_to_merc(lons, np.full(n, lat))
    # the ground under and ahead of the camera, smoothed over a second of flight
    ground, _ = src.sample(xm, ym, 20.0)
    ahead = np.convolve(np.pad(ground, (0, int(FPS))), np.ones(int(FPS)) / FPS, "valid")[:n]
    alt = np.maximum(ground, ahead) + AGL
    src.close()
    return [
        Camera(float(lo), lat, float(a), heading=90.0, pitch=-15.0, width=640, height=360)
        for lo, a in zip(lons, alt, strict=True)
    ]


def run(
    tileset: Path,
    cams: list[Camera],
    stream: StreamOptions | None,
    imagery: str | None,
    ortho: Path | None = None,
) -> dict[str, float]:
    opts = SceneOptions(gpu_budget_mb=BUDGET_MB, anisotropy=1.0, stream=stream)
    clock = SimClock()
    if ortho is not None:
        opened = lodscape.open(tileset, opts, clock=clock, imagery=[ortho])
    else:
        provider: Provider = TilesetProvider(tileset)
        if imagery is not None:
            layer = ImageryLayer(HttpSource(imagery, max_connections=16), index=1)
            provider = LayeredProvider(provider, [layer])
        opened = lodscape.Scene(provider, opts, owns=True, clock=clock)
    with opened as scene:
        if stream is not None:
            rows = fly(scene, iter(cams), FPS)
        else:
            rows = []
            for i, cam in enumerate(cams):
                scene.render(cam)
                assert scene.last is not None
                cpu = scene.last.select_ms + scene.last.load_ms
                rows.append(
                    {
                        "frame": i,
                        "time_s": i / FPS,
                        "fallback_max": scene.last.selection["fallback_max"],
                        "over_budget": int(cpu > 1000 / FPS),
                        "frame_cpu_ms": cpu,
                        "gpu_bytes": scene.last.resident_mb * 2**20,
                        "memory_bytes": 0,
                        "cache_bytes": 0,
                    }
                )
    after = [r for r in rows if r["time_s"] >= 1.0]
    peak = max(r["gpu_bytes"] + r["memory_bytes"] + r["cache_bytes"] for r in after)
    return {
        "frames": len(after),
        "fallback_gt_1": sum(r["fallback_max"] > 1 for r in after),
        "over_budget": sum(r["over_budget"] for r in after),
        "cpu_ms_median": statistics.median(r["frame_cpu_ms"] for r in after),
        "cpu_ms_max": max(r["frame_cpu_ms"] for r in after),
        "peak_mib": peak / 2**20,
        "layer_fallbacks": sum(int(r.get("layer_fallbacks", 0)) for r in after),
    }


def turning_cameras(dem: Path, speed: float, seconds: float) -> list[Camera]:
    """Fast, with a turn: east along the DEM's middle from its west quarter, a 90° turn to the
    north over five seconds, then north; ``AGL`` above the ground (smoothed), looking along."""
    src = RasterSource(dem)
    b = src.bounds_merc
    x0, y0 = b.left + (b.right - b.left) * 0.15, (b.top + b.bottom) / 2 - (b.top - b.bottom) * 0.3
    dt = 1.0 / FPS
    n = int(seconds * FPS)
    turn_at, turn_s = 0.4 * seconds, 5.0
    rate = (math.pi / 2) / turn_s  # rad/s
    headings = np.empty(n)
    xs, ys = np.empty(n), np.empty(n)
    x, y, heading = x0, y0, math.pi / 2  # heading from north, clockwise: east
    # Web Mercator metres stretch by 1/cos(lat): move by ground metres
    (_, lat_mid) = merc_to_lonlat(x0, y0)
    stretch = 1.0 / math.cos(math.radians(float(lat_mid)))
    for i in range(n):
        t = i * dt
        if turn_at <= t < turn_at + turn_s:
            heading -= rate * dt  # turning left, towards the north
        xs[i], ys[i], headings[i] = x, y, heading
        x += speed * dt * math.sin(heading) * stretch
        y += speed * dt * math.cos(heading) * stretch
    ground, _ = src.sample(xs, ys, 20.0)
    src.close()
    ground = np.where(np.isfinite(ground), ground, np.nanmax(ground))
    ahead = np.convolve(np.pad(ground, (0, int(FPS))), np.ones(int(FPS)) / FPS, "valid")[:n]
    alt = np.maximum(ground, ahead) + AGL
    lons, lats = merc_to_lonlat(xs, ys)
    return [
        Camera(
            float(lo),
            float(la),
            float(a),
            heading=float(np.degrees(h)) % 360.0,
            pitch=-15.0,
            width=640,
            height=360,
        )
        for lo, la, a, h in zip(lons, lats, alt, headings, strict=True)
    ]


class SlowStorage:
    """A tileset on slow storage (a network disk, a busy server): every read is charged
    ``latency`` seconds on the simulated clock (``cost``), whatever the machine does."""

    def __init__(self, base: Provider, latency: float) -> None:
        self._base = base
        self.latency = latency

    def cost(self, key: int) -> float:
        return self.latency

    def __getattr__(self, name: str) -> object:
        return getattr(self._base, name)


def fast_flights(
    tileset: Path,
    dem: Path,
    speed: float,
    latency_ms: float,
    seconds: float,
    runs: int,
    budget_mb: float = BUDGET_MB,
) -> None:
    """Paper 004's radii where prefetch must pay: a fast flight with a turn over slow storage,
    staged with the radii, with the velocity's predictions alone, and with no prefetch; each
    ``runs`` times, medians and ranges (uploads get a wall-clock slice a frame, so a loaded
    machine moves the figures)."""
    cams = turning_cameras(dem, speed, seconds)
    turn = (0.4 * seconds, 0.4 * seconds + 5.0)
    print(
        f"-- fast: {len(cams)} frames at {FPS:.0f} fps, {speed:.0f} m/s with a 90° turn over "
        f"5 s, {AGL:.0f} m above the ground; storage {latency_ms:.0f} ms a read; budgets "
        f"{budget_mb:.0f} MiB a stage"
    )
    mb = {"cache_mb": budget_mb, "memory_mb": budget_mb}
    modes = [
        ("radii + velocity", StreamOptions(**mb)),
        ("velocity only", StreamOptions(**mb, radii=None)),
        ("no prefetch", StreamOptions(**mb, radii=None, ahead=())),
    ]
    for label, stream in modes:
        got: list[dict[str, float]] = []
        for _ in range(runs):
            opts = SceneOptions(gpu_budget_mb=budget_mb, anisotropy=1.0, stream=stream)
            provider = SlowStorage(TilesetProvider(tileset), latency_ms / 1000.0)
            with lodscape.Scene(provider, opts, clock=SimClock()) as scene:  # type: ignore[arg-type]
                rows = fly(scene, iter(cams), FPS)
                provider._base.close()
            after = [r for r in rows if r["time_s"] >= 1.0]
            turning = [r for r in rows if turn[0] <= r["time_s"] < turn[1] + 1.0]
            got.append(
                {
                    "fell": sum(r["fallback_max"] > 1 for r in after),
                    "fell_turn": sum(r["fallback_max"] > 1 for r in turning),
                    "over": sum(r["over_budget"] for r in after),
                    "mib": sum(r["fetched_bytes"] for r in rows) / 2**20,
                    "reads": sum(r["fetched"] for r in rows),
                    "area_memory": rows[-1]["area_memory"],
                }
            )

        def med(k: str, g: list[dict[str, float]] = got) -> str:
            v = sorted(x[k] for x in g)
            mid = statistics.median(v)
            return f"{mid:.0f}" if len(v) == 1 else f"{mid:.0f} ({v[0]:.0f}–{v[-1]:.0f})"

        print(
            f"{label:>25}: {len(cams) - int(FPS)} frames after the first second, medians of "
            f"{runs}: {med('fell')} fall back > 1 level ({med('fell_turn')} in the turn and the "
            f"second after), {med('over')} over {1000 / FPS:.1f} ms; read {med('mib')} MiB in "
            f"{med('reads')} reads; {med('area_memory')} chunks in the memory area at the end"
        )


def dataset(work: Path, n: int) -> tuple[Path, Path]:
    """The n² fBm DEM and its tileset in ``work``, made unless they are there already."""
    dem, tileset = work / f"fbm{n}.tif", work / f"fbm{n}.lods"
    if not dem.exists():
        write(dem, n)
    if not tileset.exists():
        t = time.perf_counter()
        build([dem], tileset)
        print(f"built {tileset} in {time.perf_counter() - t:.0f} s")
    return dem, tileset


def write_ortho(path: Path, dem: Path, factor: int = 8) -> None:
    """An RGB orthophoto ``factor``× finer than ``dem`` over it, written strip by strip."""
    import rasterio
    from rasterio.transform import Affine

    with rasterio.open(dem) as d:
        t, crs, n = d.transform, d.crs, d.width * factor
    profile = {
        "driver": "GTiff",
        "height": n,
        "width": n,
        "count": 3,
        "dtype": "uint8",
        "crs": crs,
        "transform": Affine(t.a / factor, 0.0, t.c, 0.0, t.e / factor, t.f),
        "tiled": True,
        "blockxsize": 512,
        "blockysize": 512,
        "compress": "jpeg",
        "photometric": "YCBCR",
    }
    strip = 4096
    with rasterio.open(path, "w", **profile) as out:
        for row in range(0, n, strip):
            h = min(strip, n - row)
            cells = np.random.default_rng(row).integers(40, 230, (3, (h + 1) // 2, (n + 1) // 2))
            block = np.repeat(np.repeat(cells.astype(np.uint8), 2, axis=1), 2, axis=2)
            out.write(block[:, :h, :n], window=rasterio.windows.Window(0, row, n, h))
    add_overviews(path)


def add_overviews(path: Path) -> None:
    """Overviews by averaging, as a cloud-optimised orthophoto has them."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(path, "r+") as ds:
        if not ds.overviews(1):
            ds.build_overviews([2, 4, 8, 16, 32, 64], Resampling.average)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=None, help="keep the DEM and tileset here")
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--latency-ms", type=float, default=40.0, help="the imagery server's delay")
    ap.add_argument("--ortho", action="store_true", help="fly with an orthophoto 8x finer too")
    ap.add_argument("--dem", type=int, default=4097, help="the DEM's side (4097: issue 4's)")
    ap.add_argument(
        "--fast",
        type=float,
        default=0.0,
        metavar="M_PER_S",
        help="instead: a flight this fast with a turn over slow storage, radii against the "
        "velocity alone and no prefetch (paper 004's case; 600 for issue 22's)",
    )
    ap.add_argument("--storage-ms", type=float, default=40.0, help="--fast: ms per read")
    ap.add_argument("--runs", type=int, default=3, help="--fast: runs of each mode")
    ap.add_argument(
        "--budget-mb", type=float, default=BUDGET_MB, help="--fast: MiB of each stage (GPU too)"
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        dem, tileset = dataset(work, args.dem)
        if args.fast:
            fast_flights(
                tileset,
                dem,
                args.fast,
                args.storage_ms,
                min(args.seconds, 30.0),
                args.runs,
                args.budget_mb,
            )
            return
        size = tileset.stat().st_size / 2**20
        cams = cameras(dem, args.seconds)
        print(
            f"tileset {size:.0f} MiB; budgets {BUDGET_MB:.0f} MiB a stage; {len(cams)} frames "
            f"at {FPS:.0f} fps, {SPEED:.0f} m/s, {AGL:.0f} m above the ground"
        )
        server = TileServer()
        server.default_fault = "slow"
        server.delay = args.latency_ms / 1000
        modes: list[tuple[str, StreamOptions | None]] = [
            ("staged", StreamOptions(cache_mb=BUDGET_MB, memory_mb=BUDGET_MB)),
            (
                "async, no prefetch",
                StreamOptions(cache_mb=BUDGET_MB, memory_mb=BUDGET_MB, ahead=(), radii=None),
            ),
            ("naive (load when needed)", None),
        ]
        try:
            if args.ortho:
                ortho = work / f"fbm{args.dem}-ortho.tif"
                if not ortho.exists():
                    t = time.perf_counter()
                    write_ortho(ortho, dem)
                    print(f"wrote {ortho} in {time.perf_counter() - t:.0f} s")
                add_overviews(ortho)
                print("-- a local orthophoto 8x finer than the DEM (staged)")
                for label, imagery_path in (
                    ("tileset alone", None),
                    ("with the orthophoto", ortho),
                ):
                    stream = StreamOptions(cache_mb=BUDGET_MB, memory_mb=BUDGET_MB)
                    r = run(tileset, cams, stream, None, imagery_path)
                    print(
                        f"{label:>25}: {r['frames']} frames after the first second: "
                        f"{r['fallback_gt_1']} fall back > 1 level, {r['over_budget']} over "
                        f"{1000 / FPS:.1f} ms (CPU median {r['cpu_ms_median']:.1f} ms, max "
                        f"{r['cpu_ms_max']:.1f} ms), peak resident {r['peak_mib']:.1f} MiB, "
                        f"layer fallbacks {r.get('layer_fallbacks', 0)}"
                    )
                return
            for imagery, where in [
                (None, "the local tileset"),
                (server.template, f"imagery from a server {args.latency_ms:.0f} ms away"),
            ]:
                print(f"-- {where}")
                for label, stream in modes:
                    r = run(tileset, cams, stream, imagery)
                    print(
                        f"{label:>25}: {r['frames']} frames after the first second: "
                        f"{r['fallback_gt_1']} fall back > 1 level, {r['over_budget']} over "
                        f"{1000 / FPS:.1f} ms (CPU median {r['cpu_ms_median']:.1f} ms, max "
                        f"{r['cpu_ms_max']:.1f} ms), peak resident {r['peak_mib']:.1f} MiB"
                    )
        finally:
            server.close()


if __name__ == "__main__":
    main()
