"""Scale benchmark: what a build costs its coordinator and each worker, against the number of
tiles, on a VRT mosaic of GeoTIFFs (issue 38).

The mosaic: a spectral fBm surface (``--size``² samples at 30 m, UTM 32N) cut into ``--tile``²
GeoTIFFs (tiled, deflate) under one hand-written VRT, the quarter of it below a height masked as
nodata (a sea with a coastline, which the plan skips). Each run is a fresh process:

- **threads** (×2, in process): pixels read per tile by level (every ``RasterSource`` read
  counted against the tile being made), the largest block's time, the time to the first
  finished tile and the planning time;
- **dask ×1, ×2**: a scheduler and workers started as their own processes (``dask scheduler``,
  ``dask worker``, one thread each) before the clock starts, so the coordinator's CPU is the
  build's own: its CPU per tile, its peak RSS and each worker's, the wall time and the speed-up
  from one worker to two;
- with ``--before REV``, the same Dask runs of that commit's build (its own worktree), where
  the mosaic is small enough for it (``--before-max`` samples a side), and what each
  tileset's recorded errors cost a renderer: the triangles and tiles the spine's four views
  draw at 1280×720, each tileset drawn by its own commit.

Every build must give the same rows as the threads build (checked). Medians over ``--rounds``
where more than one.

    python bench/bench_scale.py [--size 4097] [--tile 1025] [--sizes 2049,4097] [--before REV]
        [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))


def write_mosaic(folder: Path, size: int, tile: int) -> Path:
    """``size``² samples as (size/tile)² GeoTIFFs and one VRT over them; returns the VRT."""
    import rasterio
    from affine import Affine

    from bench_spine import spectral_fbm

    vrt = folder / f"mosaic-{size}.vrt"
    if vrt.exists():
        return vrt
    heights = spectral_fbm(size).astype(np.float32)
    sea = np.quantile(heights, 0.25)
    heights[heights < sea] = -9999.0
    res, west, north = 30.0, 300000.0, 5500000.0
    n = -(-size // tile)
    sources = []
    for i in range(n):
        for j in range(n):
            block = heights[i * tile : (i + 1) * tile, j * tile : (j + 1) * tile]
            path = folder / f"m{size}-{i}-{j}.tif"
            profile = {
                "driver": "GTiff",
                "height": block.shape[0],
                "width": block.shape[1],
                "count": 1,
                "dtype": "float32",
                "nodata": -9999.0,
                "crs": "EPSG:32632",
                "transform": Affine(
                    res, 0.0, west + j * tile * res, 0.0, -res, north - i * tile * res
                ),
                "tiled": True,
                "blockxsize": 256,
                "blockysize": 256,
                "compress": "deflate",
            }
            with rasterio.open(path, "w", **profile) as dst:
                dst.write(block, 1)
            sources.append(
                f"""  <ComplexSource>
   <SourceFilename relativeToVRT="1">{path.name}</SourceFilename><SourceBand>1</SourceBand>
   <SrcRect xOff="0" yOff="0" xSize="{block.shape[1]}" ySize="{block.shape[0]}"/>
   <DstRect xOff="{j * tile}" yOff="{i * tile}" xSize="{block.shape[1]}" ySize="{block.shape[0]}"/>
   <NODATA>-9999</NODATA>
  </ComplexSource>"""
            )
    from pyproj import CRS

    wkt = CRS.from_epsg(32632).to_wkt()
    vrt.write_text(
        f"""<VRTDataset rasterXSize="{size}" rasterYSize="{size}">
 <SRS>{wkt}</SRS>
 <GeoTransform>{west}, {res}, 0, {north}, 0, {-res}</GeoTransform>
 <VRTRasterBand dataType="Float32" band="1">
  <NoDataValue>-9999</NoDataValue>
{chr(10).join(sources)}
 </VRTRasterBand>
</VRTDataset>
"""
    )
    return vrt


# --- one run (a fresh process) ---------------------------------------------------------------


def _instrument() -> dict[str, Any]:
    """Counters of pixels read per tile level and block times (threads in this process)."""
    from lodscape.build import blocks, tiles
    from lodscape.terrain import source

    local = threading.local()
    pixels: dict[int, list[int]] = defaultdict(list)
    block_s: list[float] = []
    plan_s = [0.0]
    read = source.RasterSource._read_raw

    def counted(self: Any, overview: Any, r0: int, r1: int, c0: int, c1: int) -> Any:
        if getattr(local, "count", None) is not None:
            local.count += max(r1 - r0, 0) * max(c1 - c0, 0)
        return read(self, overview, r0, r1, c0, c1)

    source.RasterSource._read_raw = counted  # type: ignore[method-assign]

    def per_tile(fn: Any) -> Any:
        def wrapped(job: Any, z: int, x: int, y: int, *a: Any) -> Any:
            outer = getattr(local, "count", None)
            local.count = 0
            try:
                return fn(job, z, x, y, *a)
            finally:
                pixels[z].append(local.count)
                local.count = outer

        return wrapped

    for name in ("made_from_data", "made_from_children", "made_without_data"):
        setattr(blocks, name, per_tile(getattr(tiles, name)))

    make = blocks.make_block

    def timed_block(*a: Any) -> Any:
        t = time.perf_counter()
        try:
            return make(*a)
        finally:
            block_s.append(time.perf_counter() - t)

    import lodscape.build as build_module

    build_module.make_block = timed_block  # type: ignore[assignment]
    plan = build_module.plan_blocks

    def timed_plan(*a: Any, **k: Any) -> Any:
        it = plan(*a, **k)
        while True:
            t = time.perf_counter()
            try:
                row = next(it)
            except StopIteration:
                plan_s[0] += time.perf_counter() - t
                return
            plan_s[0] += time.perf_counter() - t
            yield row

    build_module.plan_blocks = timed_plan  # type: ignore[assignment]
    return {"pixels": pixels, "block_s": block_s, "plan_s": plan_s}


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss, not inherited from the
    process that started it)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return float(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def views(path: str) -> None:
    """The spine's four views of a tileset at 1280×720: triangles and tiles drawn (how the
    recorded errors drive the selection); prints JSON."""
    import lodscape

    sys.path.insert(0, str(ROOT / "tests"))
    from _synthetic import spine_views

    out = {}
    with lodscape.open(path) as scene:
        for name, cam in spine_views(scene, 1280, 720).items():
            scene.render(cam)
            st = scene.frame_stats()
            out[name] = [int(st.get("triangles", 0)), int(st.get("tiles", 0))]
    print(json.dumps(out))


def opening(path: str) -> None:
    """Seconds to open an input with an empty overview cache (the sidecar overviews made from
    every pixel) and again with it made, and the pixels per second of the first; prints JSON."""
    import rasterio

    with tempfile.TemporaryDirectory() as cache:
        os.environ["LODSCAPE_CACHE"] = cache
        from lodscape.terrain.source import open_rasters

        times = []
        for _ in range(2):
            t = time.perf_counter()
            open_rasters([path]).close()
            times.append(time.perf_counter() - t)
    with rasterio.open(path) as ds:
        pixels = ds.width * ds.height
    print(
        json.dumps({"cold_s": times[0], "warm_s": times[1], "mpx_per_s": pixels / times[0] / 1e6})
    )


def one(args: argparse.Namespace) -> None:
    """A single build in this process; prints its figures as JSON."""
    import lodscape.build as build_module
    from lodscape.build.executors import DaskExecutor, PoolExecutor

    counters = _instrument() if args.mode == "threads" else None
    if args.mode == "threads":
        executor: Any = PoolExecutor(2, processes=False)
    else:
        executor = DaskExecutor(args.scheduler)
    first: list[float] = []
    t0 = time.perf_counter()
    cpu0 = time.process_time()

    def progress(done: int, total: int) -> None:
        if done > 0 and not first:
            first.append(time.perf_counter() - t0)

    try:
        report = build_module.build([args.dem], args.out, executor=executor, progress=progress)
    finally:
        wall = time.perf_counter() - t0
        cpu = time.process_time() - cpu0
        worker_rss: list[float] = []
        if args.mode != "threads":
            got = executor.client.run(peak_rss_mb)
            worker_rss = sorted(float(v) for v in got.values())
        executor.close()
    out: dict[str, Any] = {
        "tiles": report.planned,
        "wall_s": wall,
        "client_cpu_s": cpu,
        "client_cpu_ms_per_tile": 1000.0 * cpu / max(report.planned, 1),
        "client_rss_mb": peak_rss_mb(),
        "worker_rss_mb": worker_rss,
        "first_tile_s": first[0] if first else None,
    }
    if counters is not None:
        px = counters["pixels"]
        out["pixels_per_tile"] = {
            str(z): {"max": max(v), "mean": float(np.mean(v)), "tiles": len(v)}
            for z, v in sorted(px.items())
        }
        out["largest_block_s"] = max(counters["block_s"], default=0.0)
        out["plan_s"] = counters["plan_s"][0]
    print(json.dumps(out))


def _rows(path: Path) -> list[tuple[Any, ...]]:
    with closing(sqlite3.connect(path)) as db:
        return db.execute("SELECT z, x, y, error, data FROM terrain ORDER BY z, x, y").fetchall()


class Cluster:
    """A Dask scheduler and ``workers`` single-threaded workers, each its own process."""

    def __init__(self, folder: Path, workers: int) -> None:
        self.file = folder / f"scheduler-{os.getpid()}-{workers}.json"
        self.file.unlink(missing_ok=True)
        log = open(folder / "dask.log", "ab")  # noqa: SIM115
        quiet = {**os.environ, "DASK_DISTRIBUTED__LOGGING__DISTRIBUTED": "error"}
        self.procs = [
            subprocess.Popen(
                [
                    "dask",
                    "scheduler",
                    "--scheduler-file",
                    str(self.file),
                    "--port",
                    "0",
                    "--dashboard-address",
                    "127.0.0.1:0",
                    "--host",
                    "127.0.0.1",
                ],
                stdout=log,
                stderr=log,
                env=quiet,
                start_new_session=True,
            )
        ]
        while not self.file.exists():
            time.sleep(0.2)
        time.sleep(0.5)
        self.address = json.loads(self.file.read_text())["address"]
        self.procs.append(
            subprocess.Popen(
                [
                    "dask",
                    "worker",
                    self.address,
                    "--nworkers",
                    str(workers),
                    "--nthreads",
                    "1",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                ],
                stdout=log,
                stderr=log,
                env=quiet,
                start_new_session=True,
            )
        )
        from distributed import Client

        with Client(self.address) as c:
            c.wait_for_workers(workers, timeout=120)

    def close(self) -> None:
        for p in reversed(self.procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            p.wait(timeout=30)


def run(
    python_path: Path, mode: str, dem: Path, out: Path, scheduler: str | None = None
) -> dict[str, Any]:
    out.unlink(missing_ok=True)
    cmd = [sys.executable, __file__, "--one", mode, "--dem", str(dem), "--out", str(out)]
    if scheduler:
        cmd += ["--scheduler", scheduler]
    env = {**os.environ, "PYTHONPATH": str(python_path)}
    got = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=7200)
    if got.returncode != 0:
        raise SystemExit(f"{mode} on {dem.name} failed:\n{got.stderr[-3000:]}")
    figures: dict[str, Any] = json.loads(got.stdout.strip().splitlines()[-1])
    if got.stderr.strip():
        figures["stderr"] = got.stderr.strip()[-500:]
    return figures


def run_views(python_path: Path, tileset: Path) -> dict[str, Any]:
    cmd = [sys.executable, __file__, "--one", "views", "--dem", str(tileset)]
    env = {**os.environ, "PYTHONPATH": str(python_path)}
    got = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=1800)
    if got.returncode != 0:
        raise SystemExit(f"views of {tileset.name} failed:\n{got.stderr[-3000:]}")
    out: dict[str, Any] = json.loads(got.stdout.strip().splitlines()[-1])
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="2049,4097")
    ap.add_argument("--tile", type=int, default=1025)
    ap.add_argument("--before", default=None)
    ap.add_argument("--before-max", type=int, default=2049)
    ap.add_argument("--work", default=None)
    ap.add_argument("--one", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--dem", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--scheduler", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one == "views":
        views(args.dem)
        return
    if args.one == "open":
        opening(args.dem)
        return
    if args.one:
        args.mode = args.one
        one(args)
        return
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    here = ROOT / "src"
    before = None
    if args.before:
        before = work / f"before-{args.before}"
        if not before.exists():
            subprocess.run(
                ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(before), args.before],
                check=True,
                capture_output=True,
            )
        before = before / "src"
    results: dict[str, Any] = {}
    for size in (int(s) for s in args.sizes.split(",")):
        dem = write_mosaic(work, size, args.tile)
        key = f"{size}²"
        print(f"== {key} mosaic ({dem})", flush=True)
        res: dict[str, Any] = {"threads": run(here, "threads", dem, work / "threads.lods")}
        want = _rows(work / "threads.lods")
        print(f"threads ×2: {json.dumps(res['threads'])}", flush=True)
        for workers in (1, 2):
            cluster = Cluster(work, workers)
            try:
                name = f"dask ×{workers}"
                res[name] = run(here, "dask", dem, work / "dask.lods", cluster.address)
                same = _rows(work / "dask.lods") == want
                res[name]["same_rows"] = same
                print(f"{name}: {json.dumps(res[name])}", flush=True)
                if before is not None and size <= args.before_max:
                    bname = f"before {name}"
                    res[bname] = run(before, "dask", dem, work / "before.lods", cluster.address)
                    print(f"{bname}: {json.dumps(res[bname])}", flush=True)
                    if workers == 1:
                        # what each tileset's recorded errors cost a renderer
                        for who, path, code in (
                            ("now", work / "threads.lods", here),
                            ("before", work / "before.lods", before),
                        ):
                            res[f"views {who}"] = run_views(code, path)
                            print(f"views {who}: {json.dumps(res[f'views {who}'])}", flush=True)
            finally:
                cluster.close()
        d1, d2 = res["dask ×1"], res["dask ×2"]
        res["speedup_1_to_2"] = d1["wall_s"] / d2["wall_s"]
        print(f"speed-up ×1 → ×2: {res['speedup_1_to_2']:.2f}", flush=True)
        if "before dask ×2" in res:
            b = res["before dask ×2"]
            print(
                f"before/now on 2 workers: wall ×{b['wall_s'] / d2['wall_s']:.2f}, client CPU "
                f"per tile ×{b['client_cpu_ms_per_tile'] / d2['client_cpu_ms_per_tile']:.1f}",
                flush=True,
            )
        results[key] = res
    (work / "scale.json").write_text(json.dumps(results, indent=1))
    print(f"figures: {work / 'scale.json'}")


if __name__ == "__main__":
    main()
