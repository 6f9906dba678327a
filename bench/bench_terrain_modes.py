"""The two terrain modes along one flight (paper 001's GPU terrain against the spine's meshes).

    python bench/bench_terrain_modes.py [--frames 60] [--size 1280x720] [--n 2049]

Terrain: a spectral fBm DEM (n² samples at 5 m, UTM 17N, as bench_spine writes it), opened
directly (meshed on the fly). The flight: a west-to-east line across its middle, 250 m above
its highest point, looking 20° down, then the same line at 1,500 m. Each mode flies it twice in
one process with the same renderer settings: the first pass loads every tile, the second is
timed (frames of it that still load a tile are left out, and counted). Per frame, medians: CPU
time (selection, plus issuing the terrain's draws: uniforms and draw calls, no GPU wait), the
whole frame (read-back of colour and distance included), triangles drawn (the GPU mode's
counted by a primitives query) and GPU bytes of the tiles resident (meshes against height
textures with their error tables). On llvmpipe the "CPU time" of a draw includes its vertex and
tessellation shading, which Mesa runs on the calling thread: there only the frame time and the
memory mean much; on a GPU the two modes' CPU times compare what the CPU does.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

import lodscape
from bench_spine import write
from lodscape import Camera, SceneOptions
from lodscape.geo.tiles import merc_to_lonlat


def flight(scene: lodscape.Scene, frames: int, alt: float, w: int, h: int) -> list[Camera]:
    b = scene.provider.bounds_merc
    y = (b.top + b.bottom) / 2
    xs = np.linspace(b.left + 0.1 * (b.right - b.left), b.right - 0.1 * (b.right - b.left), frames)
    lon, lat = merc_to_lonlat(xs, np.full(frames, y))
    return [
        Camera(float(a), float(c), alt, heading=90.0, pitch=-20.0, width=w, height=h)
        for a, c in zip(lon, lat, strict=True)
    ]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--n", type=int, default=2049)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        dem = Path(tmp) / "fbm.tif"
        write(dem, args.n)
        for label, agl in (("low (250 m over the top)", 250.0), ("high (1,500 m)", 1500.0)):
            print(f"\n{label}, {w}×{h}, {args.frames} frames, {args.n}² DEM at 5 m:")
            for mode in ("cpu", "gpu"):
                opts = SceneOptions(terrain_mode=mode, gpu_budget_mb=2048.0)
                with lodscape.open(str(dem), opts) as scene:
                    top = scene.tree.height_range[1]
                    cams = flight(scene, args.frames, top + agl, w, h)
                    for cam in cams:  # load everything once
                        scene.render(cam)
                    cpu, frame, tris, res, calls = [], [], [], [], []
                    loading = 0
                    for cam in cams:
                        t = time.perf_counter()
                        scene.render(cam)
                        ms = (time.perf_counter() - t) * 1e3
                        last = scene.last
                        assert last is not None
                        if last.loaded:
                            # the hysteresis of the pass before chose other tiles here
                            loading += 1
                            continue
                        frame.append(ms)
                        cpu.append(last.select_ms + last.submit_ms)
                        tris.append(last.triangles)
                        res.append(last.resident_mb)
                        calls.append(last.draw_calls)
                    assert scene.terrain_mode == mode, scene.terrain_mode_note
                    print(
                        f"  {mode}: CPU {statistics.median(cpu):6.2f} ms/frame  "
                        f"frame {statistics.median(frame):7.1f} ms  "
                        f"triangles {int(statistics.median(tris)):>9,}  "
                        f"draws {int(statistics.median(calls)):>4}  "
                        f"resident {max(res):7.1f} MiB"
                        + (f"  ({loading} frames that loaded left out)" if loading else "")
                    )
    landcover_memory(max(args.frames // 3, 5), w, h)


def landcover_memory(frames: int, w: int, h: int) -> None:
    """The land-cover ground against the pre-baked tint it replaces, over the bundled Helsinki
    extract on level ground: the same tiles at the same ground resolution (256² texels a
    tile), texture bytes resident on the GPU, and frame times."""
    from lodscape.data import sample_city_path
    from lodscape.geo.keys import is_texture
    from lodscape.imagery.landcover import ground_layers, read_landcover
    from lodscape.terrain.detail import Fractal

    cover = read_landcover(sample_city_path())
    spec = "flat:24.925,60.158,24.965,60.186"
    print(f"\nland cover against the tint, {w}×{h}, {frames} frames over Helsinki at 150 m:")
    lons = np.linspace(24.932, 24.955, frames)
    cams = [
        Camera(float(x), 60.1665, 150.0, heading=10.0, pitch=-25.0, width=w, height=h) for x in lons
    ]
    for ground in ("imagery", "landcover"):
        opts = SceneOptions(gpu_budget_mb=4096.0)
        # the land cover's detail tree (no amplitude) under both, so both hold the same tiles
        scene = lodscape.open(
            spec,
            opts,
            detail=Fractal(0.7, 0.0, 0),
            landcover=cover if ground == "landcover" else None,
        )
        with scene:
            for cam in cams:
                scene.render(cam)
            times = []
            for cam in cams:
                t = time.perf_counter()
                scene.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
            assert scene.renderer is not None
            tex = [v for k, v in scene.renderer.resident().items() if is_texture(k)]
            extra = ground_layers().nbytes * 4 // 3 if ground == "landcover" else 0
            print(
                f"  {ground:9s}: {len(tex)} tile textures, {sum(tex) / 2**20:6.2f} MiB "
                f"({sum(tex) / len(tex) / 1024:5.1f} KiB a tile)"
                + (f" + {extra / 2**20:.2f} MiB of ground materials, once" if extra else "")
                + f"; frame {statistics.median(times):6.1f} ms"
            )


if __name__ == "__main__":
    main()
