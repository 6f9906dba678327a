"""Frame benchmark: selections per frame and CPU time per frame, for this checkout and (with
``--before REV``) an earlier commit of the repository, in one script.

Four workloads, through the public API only (so an older lodscape runs them too):
- **views**: the spine's four test views (straight down, oblique, low and grazing, steep and
  near) of a 2049² spectral fBm DEM at 1280×720, one-shot renders (the blocking loader), each
  drawn ``--repeat`` times once everything is resident;
- **moving**: a camera moving by one-shot renders, as a script rendering a video frame by
  frame does: from the oblique view, 10 m lower and turned 1° each frame, ``MOVING_FRAMES``
  frames after the first (loaded apart); per frame the wall time and the CPU the engine
  reports (selection and loading: the tiles that come into view, and the tiles cut at
  another bound, since TINs are cut at what the frame allows);
- **flight**: the issue-4 flight (300 m/s, 300 m above the smoothed ground, 30 frames/s,
  640×360, 16 MiB per stage) over the same DEM built into a tileset, streaming on a simulated
  clock;
- **globe**: the globe with the DEM's own tiles (``Globe(lodscape.open(dem))``) from orbit, from
  100 km and from 5 km over the DEM at 960×540, one-shot frames drawn ``--repeat`` times once
  resident, then the same frames as a window draws them (the picture left on the GPU): the
  pictures read back per frame (``Framebuffer.read`` calls), textures written per frame, the
  frame's wall time and its CPU time on the frame's thread (llvmpipe rasterises on threads
  of its own).

Counted: calls to the selection on the frame's thread per frame (the prefetch's predicted
selections run on workers and are counted apart), and the frame's CPU time as the engine
reports it: selection and loading (``select_ms + load_ms``) for the views, ``frame_cpu_ms``
for the flight (since the frame loop, both include fitting the camera to the ground under it,
about 1.5 ms on this DEM, which the Scene did before its clock started); and, the same for
both, the whole frame's wall time and the CPU time of the frame's thread. Medians; with
``--rounds`` the two commits run in turn and each ratio is the median over the rounds, with
its range.

    python bench/bench_frame.py [--before REV] [--rounds 3] [--only views|moving|globe] [--work DIR]
        [--seconds 10] [--repeat 7]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import lodscape
from lodscape import SceneOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import spine_views
from bench_flight import BUDGET_MB, FPS, cameras, dataset

ROOT = Path(__file__).resolve().parents[1]
#: Frames of the moving workload.
MOVING_FRAMES = 30


class Counter:
    """Wraps the selection wherever a module holds it by name, counting calls per thread."""

    def __init__(self) -> None:
        import lodscape.lod.select as sel

        self.main = 0
        self.workers = 0
        original = sel.select

        def counted(*args: Any, **kwargs: Any) -> Any:
            if threading.current_thread() is threading.main_thread():
                self.main += 1
            else:
                self.workers += 1
            return original(*args, **kwargs)

        for mod in list(sys.modules.values()):
            name = getattr(mod, "__name__", "")
            if name.startswith("lodscape") and getattr(mod, "select", None) is original:
                mod.select = counted  # type: ignore[attr-defined]


class GLCalls:
    """Counts framebuffer read-backs and texture writes (uploads) made through moderngl."""

    def __init__(self) -> None:
        import moderngl

        self.reads = self.writes = 0
        read, write = moderngl.Framebuffer.read, moderngl.Texture.write

        def counted_read(fbo: Any, *args: Any, **kwargs: Any) -> Any:
            self.reads += 1
            return read(fbo, *args, **kwargs)

        def counted_write(tex: Any, *args: Any, **kwargs: Any) -> Any:
            self.writes += 1
            return write(tex, *args, **kwargs)

        moderngl.Framebuffer.read = counted_read  # type: ignore[method-assign]
        moderngl.Texture.write = counted_write  # type: ignore[method-assign]


def measure_globe(dem: Path, repeat: int) -> dict[str, Any]:
    """A globe-with-terrain frame from three heights: one-shot, then as a window draws it."""
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.globe import Globe, GlobeOptions

    calls = GLCalls()
    out: dict[str, Any] = {}
    g = Globe(lodscape.open(dem, SceneOptions(anisotropy=1.0)), GlobeOptions())
    try:
        b = g.terrain.provider.bounds_merc
        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.bottom + b.top) / 2)
        )
        views = {
            "orbit": lodscape.Camera(lon, lat, 2.0e6, pitch=-90.0, width=960, height=540),
            "100 km": lodscape.Camera(lon, lat - 0.9, 1.0e5, pitch=-35.0, width=960, height=540),
            "5 km": lodscape.Camera(lon, lat - 0.08, 5000.0, pitch=-25.0, width=960, height=540),
        }
        for window in (False, True):
            for name, cam in views.items():
                g.render(cam)  # loads
                if window:  # what the viewer does after the first frame
                    g.renderer.read_back = False
                wall, cpu, reads, writes = [], [], [], []
                for _ in range(repeat):
                    r0, w0 = calls.reads, calls.writes
                    t, c = time.perf_counter(), time.thread_time()
                    g.render(cam)
                    wall.append((time.perf_counter() - t) * 1e3)
                    cpu.append((time.thread_time() - c) * 1e3)
                    reads.append(calls.reads - r0)
                    writes.append(calls.writes - w0)
                out[("window " if window else "") + name] = {
                    "reads": statistics.median(reads),
                    "writes": statistics.median(writes),
                    "frame_ms": statistics.median(wall),
                    "cpu_ms": statistics.median(cpu),
                    "range_ms": [round(min(wall), 1), round(max(wall), 1)],
                }
    finally:
        g.close()
    return out


def measure_moving(dem: Path) -> dict[str, Any]:
    """One-shot renders of a moving camera (the moving workload)."""
    with lodscape.open(dem, SceneOptions(anisotropy=1.0)) as scene:
        start = spine_views(scene, 1280, 720)["oblique"]
        scene.render(start)  # the first picture, loaded apart
        total, cpu = [], []
        for i in range(1, MOVING_FRAMES + 1):
            cam = replace(start, heading=start.heading + i, alt=start.alt - 10.0 * i)
            t = time.perf_counter()
            scene.render(cam)
            total.append((time.perf_counter() - t) * 1e3)
            assert scene.last is not None
            cpu.append(scene.last.select_ms + scene.last.load_ms)
    return {
        "frame_ms": statistics.median(total),
        "cpu_ms": statistics.median(cpu),
        "range_ms": [round(min(total), 1), round(max(total), 1)],
    }


def measure(
    dem: Path, tileset: Path, seconds: float, repeat: int, only: str | None = None
) -> dict[str, Any]:
    # the modules whose ``select`` the counter replaces (lod.view is absent before the split)
    import lodscape.flight
    import lodscape.scene
    import lodscape.store.tileset
    from lodscape.stream import SimClock, StreamOptions

    if only == "globe":
        return {"lodscape": lodscape.__file__, "globe": measure_globe(dem, repeat)}
    if only == "moving":
        return {"lodscape": lodscape.__file__, "moving": measure_moving(dem)}
    views_only = only == "views"

    with contextlib.suppress(ImportError):
        import lodscape.lod.view
    counter = Counter()
    out: dict[str, Any] = {"views": {}, "lodscape": lodscape.__file__}
    with lodscape.open(dem, SceneOptions(anisotropy=1.0)) as scene:
        for name, cam in spine_views(scene, 1280, 720).items():
            scene.render(cam)  # loads
            sels, cpu, total, thread, fit = [], [], [], [], []
            for _ in range(repeat):
                t = time.perf_counter()
                scene.prepare(cam)  # the camera fitted to the ground under it
                fit.append((time.perf_counter() - t) * 1e3)
                before = counter.main
                t, c = time.perf_counter(), time.thread_time()
                scene.render(cam)
                total.append((time.perf_counter() - t) * 1e3)
                thread.append((time.thread_time() - c) * 1e3)
                assert scene.last is not None
                sels.append(counter.main - before)
                cpu.append(scene.last.select_ms + scene.last.load_ms)
            out["views"][name] = {
                "selections": statistics.median(sels),
                "cpu_ms": statistics.median(cpu),
                "frame_ms": statistics.median(total),
                "thread_ms": statistics.median(thread),
                "fit_ms": statistics.median(fit),
            }
    if views_only:
        return out
    out["moving"] = measure_moving(dem)
    cams = cameras(dem, seconds)
    opts = SceneOptions(gpu_budget_mb=BUDGET_MB, anisotropy=1.0, stream=StreamOptions())
    main0, work0 = counter.main, counter.workers
    provider = lodscape.store.tileset.TilesetProvider(tileset)
    with lodscape.Scene(provider, opts, owns=True, clock=SimClock()) as scene:
        rows = lodscape.flight.fly(scene, iter(cams), FPS)
    out["flight"] = {
        "frames": len(rows),
        "selections_per_frame": (counter.main - main0) / len(rows),
        "predictions_per_frame": (counter.workers - work0) / len(rows),
        "cpu_ms": statistics.median(r["frame_cpu_ms"] for r in rows),
        "fallback_gt_1": sum(r["fallback_max"] > 1 for r in rows if r["time_s"] >= 1.0),
    }
    out["globe"] = measure_globe(dem, repeat)
    return out


def _report(label: str, r: dict[str, Any]) -> None:
    print(f"{label} ({r['lodscape']}):")
    for name, v in r.get("views", {}).items():
        print(
            f"  view {name:<11} selections/frame {v['selections']:.0f}  "
            f"CPU {v['cpu_ms']:6.2f} ms  whole frame {v['frame_ms']:6.1f} ms  frame's thread "
            f"{v['thread_ms']:6.1f} ms  camera fit {v['fit_ms']:5.2f} ms"
        )
    m = r.get("moving")
    if m is not None:
        print(
            f"  moving ({MOVING_FRAMES} one-shot frames) frame {m['frame_ms']:6.1f} ms "
            f"{m['range_ms']}  CPU {m['cpu_ms']:6.1f} ms"
        )
    f = r.get("flight")
    if f is not None:
        print(
            f"  flight ({f['frames']} frames) selections/frame {f['selections_per_frame']:.2f}  "
            f"predictions/frame {f['predictions_per_frame']:.2f}  CPU median {f['cpu_ms']:.2f} "
            f"ms  fallbacks > 1 level: {f['fallback_gt_1']}"
        )
    for name, v in r.get("globe", {}).items():
        print(
            f"  globe {name:<13} read-backs/frame {v['reads']:.0f}  uploads/frame "
            f"{v['writes']:.0f}  frame {v['frame_ms']:6.1f} ms {v['range_ms']}  "
            f"CPU (frame's thread) {v['cpu_ms']:6.1f} ms"
        )


def _before(rev: str, tmp: Path, work: Path, args: argparse.Namespace) -> Any:
    """A function that measures commit ``rev`` in a subprocess over the same data."""
    tree = tmp / "before"
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), rev],
        check=True,
        capture_output=True,
    )

    def run() -> dict[str, Any]:
        env = {**os.environ, "PYTHONPATH": str(tree / "src")}
        cmd = [sys.executable, str(Path(__file__).resolve()), "--json"]
        cmd += ["--work", str(work), "--seconds", str(args.seconds)]
        cmd += ["--repeat", str(args.repeat)]
        cmd += ["--only", args.only] if args.only else []
        done = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
        out: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
        return out

    def remove() -> None:
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False
        )

    run.remove = remove  # type: ignore[attr-defined]
    return run


def _ratios(label: str, pairs: list[tuple[float, float]]) -> str:
    """before / now per round: the median and the range over the rounds."""
    r = [b / max(n, 1e-9) for b, n in pairs]
    return f"  {label:<20} ×{statistics.median(r):.2f} [{min(r):.2f}, {max(r):.2f}]"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--before", default=None, help="a commit to measure in the same run")
    ap.add_argument("--work", type=Path, default=None, help="keep the DEM and tileset here")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument(
        "--only", choices=["views", "moving", "globe"], default=None, help="one workload"
    )
    ap.add_argument("--rounds", type=int, default=1, help="alternate the commits this often")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        dem, tileset = dataset(work, 2049)
        if args.json:
            print(json.dumps(measure(dem, tileset, args.seconds, args.repeat, args.only)))
            return
        before = None if args.before is None else _before(args.before, Path(tmp), work, args)
        nows, befores = [], []
        try:
            for r in range(args.rounds):  # this checkout and the other, in turn
                nows.append(measure(dem, tileset, args.seconds, args.repeat, args.only))
                _report(f"this checkout, round {r + 1}", nows[-1])
                if before is not None:
                    befores.append(before())
                    _report(f"before ({args.before}), round {r + 1}", befores[-1])
        finally:
            if before is not None:
                before.remove()
        if not befores:
            return
        print(f"ratios, before / now: median [range] over {args.rounds} round(s)")

        def pairs(*path: str) -> list[tuple[float, float]]:
            def at(r: dict[str, Any]) -> float:
                for k in path:
                    r = r[k]
                return float(r)  # type: ignore[arg-type]

            return [(at(b), at(n)) for n, b in zip(nows, befores, strict=True)]

        for name in nows[0].get("views", {}):
            for key in ("cpu_ms", "frame_ms", "thread_ms"):
                print(_ratios(f"view {name} {key.split('_')[0]}", pairs("views", name, key)))
        if "moving" in nows[0]:
            for key in ("cpu_ms", "frame_ms"):
                print(_ratios(f"moving {key.split('_')[0]}", pairs("moving", key)))
        if "flight" in nows[0]:
            print(_ratios("flight CPU", pairs("flight", "cpu_ms")))
        for name in nows[0].get("globe", {}):
            for key in ("frame_ms", "cpu_ms"):
                print(_ratios(f"globe {name} {key.split('_')[0]}", pairs("globe", name, key)))


if __name__ == "__main__":
    main()
