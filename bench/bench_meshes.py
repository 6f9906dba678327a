"""What a picture's TIN tiles cost against regular grids (``SceneOptions.meshes``), in one
process, alternating: two scenes over the same DEM, one meshing tiles as RTINs cut at the
error the frame allows (``terrain.tin_tiles``), one as the regular grids, each round starting
with the other. Per round, scene, ellipsoid on and off, and camera: the median of
``--repeat`` whole frames (``Scene.render``: colour and distance read back), the median of the
GL's own clock over the same frames (a ``GL_TIME_ELAPSED`` query around each: on a GPU the
time from its first command to the read-back's end, the gaps where it waited for the CPU's
commands included; on llvmpipe a rough figure), the triangles drawn and the draw calls.

The cameras are bench_peers' (the sample's overview, oblique, low and down views). Where a
GPU is lent, this is the bench to run beside ``bench_peers.py`` at 1920x1080: its frames are
read back in the same way, and it says whether the TINs' fewer triangles pay there.

    python bench/bench_meshes.py [--dem DEM.tif] [--resolution 1920x1080] [--rounds 4]
        [--repeat 20]
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).parent))

MESHES = ("tin", "grid")


def _frame(scene: Any, cam: Any) -> tuple[float, float]:
    """One frame on the scene's GL thread: wall ms and the GL clock's ms around it."""
    query = scene.renderer.ctx.query(time=True)
    t = time.perf_counter()
    with query:
        scene.render(cam)
    return (time.perf_counter() - t) * 1e3, query.elapsed / 1e6


def main() -> None:
    import bench_peers
    import lodscape

    args, dem, cams = bench_peers.lodscape_views(rounds=4)
    w, h = next(iter(cams.values())).width, next(iter(cams.values())).height
    scenes = {
        m: lodscape.open(dem, lodscape.SceneOptions(anisotropy=1.0, meshes=m)) for m in MESHES
    }
    for scene in scenes.values():  # every camera's tiles meshed before anything is timed
        for cam in cams.values():
            scene.render(cam)
    renderer = scenes["tin"].renderer
    gl = renderer.ctx.info["GL_RENDERER"] if renderer is not None else "?"
    print(f"{dem.name}, {w}x{h}, GL: {gl}, {args.rounds} rounds of {args.repeat} frames a camera")
    print("round | meshes | ellipsoid | per camera: frame ms / GL clock ms (triangles, draws)")
    rows: dict[tuple[int, str, bool, str], tuple[float, float]] = {}
    for r in range(args.rounds):
        for m in MESHES if r % 2 == 0 else MESHES[::-1]:
            scene = scenes[m]
            for ellipsoid in (True, False):
                scene.renderer.ellipsoid = ellipsoid
                line = []
                for name, cam in cams.items():
                    for _ in range(3):
                        scene.on_gl(_frame, scene, cam)
                    got = [scene.on_gl(_frame, scene, cam) for _ in range(args.repeat)]
                    wall = statistics.median(g[0] for g in got)
                    clock = statistics.median(g[1] for g in got)
                    rows[(r, m, ellipsoid, name)] = (wall, clock)
                    st = scene.frame_stats()
                    line.append(
                        f"{name} {wall:.2f}/{clock:.2f} "
                        f"({int(st['triangles']):,d}, {int(st['draw_calls'])})"
                    )
                print(f"  {r + 1} | {m:4s} | {'on ' if ellipsoid else 'off'} | " + " | ".join(line))
            scene.renderer.ellipsoid = True
    for ellipsoid in (True, False):
        walls = [
            rows[(r, "grid", ellipsoid, n)][0] / rows[(r, "tin", ellipsoid, n)][0]
            for r in range(args.rounds)
            for n in cams
        ]
        clocks = [
            rows[(r, "grid", ellipsoid, n)][1] / rows[(r, "tin", ellipsoid, n)][1]
            for r in range(args.rounds)
            for n in cams
        ]
        print(
            f"ellipsoid {'on ' if ellipsoid else 'off'}: grid / TIN frame ×"
            f"{statistics.median(walls):.2f} (×{min(walls):.2f}–×{max(walls):.2f}), GL clock ×"
            f"{statistics.median(clocks):.2f} (×{min(clocks):.2f}–×{max(clocks):.2f}); "
            "above 1: the TINs faster"
        )
    for scene in scenes.values():
        scene.close()


if __name__ == "__main__":
    main()
