"""What a frame's read-back costs: the picture drawn top row first and read straight into the
arrays returned (now), against the GL's bottom-up rows read into new bytes and flipped into
new arrays (before: two reads and two copies of a frame's size), in one process, alternating.

The scene is the sample (or ``--dem``) at the bench_peers cameras; per round and camera the
median of ``--repeat`` whole frames (``Scene.render``, colour and distance), and of the frame's
end alone (the GPU's wait, the reads, the copies: ``FrameTarget.end``) and of the GPU's wait in
it (a ``glFinish`` before the reads: the rest is the reads and copies). Both ways draw the same
frame; the pictures are compared (the rasteriser's fill rule turns with the picture: pixels on
a triangle's edge may go to its neighbour).

    python bench/bench_readback.py [--resolution 1920x1080] [--rounds 3] [--repeat 20]
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))


def _old_end(self: Any, camera: Any, labelled: bool = False) -> tuple[Any, Any]:
    """The read-back as it was: bottom-up rows into new bytes, flipped into new arrays."""
    self._use()
    fbo = self.fbo(labelled)
    self.ctx.wireframe = False
    h, w = camera.height, camera.width
    rgb = np.frombuffer(fbo.read(components=3, attachment=0, alignment=1), np.uint8)
    rgb = np.ascontiguousarray(rgb.reshape(h, w, 3)[::-1])
    dist = np.frombuffer(fbo.read(components=1, attachment=1, alignment=1, dtype="f4"), np.float32)
    return rgb, np.ascontiguousarray(dist.reshape(h, w)[::-1])


def main() -> None:
    import bench_peers
    import lodscape
    from lodscape.render import target as target_mod

    args, dem, cams = bench_peers.lodscape_views(rounds=3)
    w, h = next(iter(cams.values())).width, next(iter(cams.values())).height
    scene = lodscape.open(dem, lodscape.SceneOptions(anisotropy=1.0))
    cls = target_mod.FrameTarget
    new_end, new_begin = cls.end, cls.begin

    def old_begin(self: Any, camera: Any, **kw: Any) -> Any:
        fbo = new_begin(self, camera, **kw)
        self.flipped = False  # the GL's own orientation: the flip is the read-back's
        self.ctx.front_face = "ccw"
        return fbo

    ends: list[float] = []
    waits: list[float] = []

    def timed(end: Any) -> Any:
        def run(self: Any, camera: Any, labelled: bool = False) -> Any:
            t = time.perf_counter()
            self.ctx.finish()  # the GPU's wait counted in the end, either way, and apart
            waits.append(time.perf_counter() - t)
            got = end(self, camera, labelled)
            ends.append(time.perf_counter() - t)
            return got

        return run

    ways = {
        "top-down": (new_begin, timed(new_end)),
        "flipped": (old_begin, timed(_old_end)),
    }
    print(f"{dem.name}, {w}x{h}, {args.rounds} rounds of {args.repeat} frames a camera")
    pictures: dict[str, dict[str, Any]] = {}
    rows = []
    for r in range(args.rounds):
        order = list(ways) if r % 2 == 0 else list(ways)[::-1]
        for way in order:
            cls.begin, cls.end = ways[way]  # type: ignore[method-assign]
            for name, cam in cams.items():
                for _ in range(3):
                    scene.render(cam)
                ends.clear()
                waits.clear()
                times = []
                for _ in range(args.repeat):
                    t = time.perf_counter()
                    rgb, dist = scene.render(cam)
                    times.append(time.perf_counter() - t)
                pictures.setdefault(way, {})[name] = (rgb, dist)
                frame, end = statistics.median(times) * 1e3, statistics.median(ends) * 1e3
                rows.append((r + 1, way, name, frame, end, statistics.median(waits) * 1e3))
    cls.begin, cls.end = new_begin, new_end  # type: ignore[method-assign]
    renderer = scene.renderer
    gl = renderer.ctx.info["GL_RENDERER"] if renderer is not None else "?"
    scene.close()
    print(f"GL: {gl}")
    print(
        "round | camera | frame ms: top-down / flipped (×) | end ms: top-down / flipped"
        " | of it the GPU's wait: top-down / flipped"
    )
    ratios = []
    for r in range(1, args.rounds + 1):
        for name in cams:
            got = {way: (f, e, g) for rr, way, n, f, e, g in rows if rr == r and n == name}
            (ft, et, gt), (ff, ef, gf) = got["top-down"], got["flipped"]
            ratios.append(ff / ft)
            frames = f"{ft:6.2f} / {ff:6.2f} (×{ff / ft:.2f})"
            print(f"  {r} | {name:8s} | {frames} | {et:5.2f} / {ef:5.2f} | {gt:5.2f} / {gf:5.2f}")
    print(f"frame ratio flipped / top-down: median ×{statistics.median(ratios):.2f} "
          f"(range ×{min(ratios):.2f}–×{max(ratios):.2f})")  # fmt: skip
    for name in cams:
        (a, da), (b, db) = pictures["top-down"][name], pictures["flipped"][name]
        same = float(np.all(a == b, axis=2).mean())
        fin = np.isfinite(da) & np.isfinite(db)
        near = float((np.abs(da[fin] - db[fin]) <= 1e-4 * da[fin]).mean()) if fin.any() else 1.0
        print(f"  {name}: same colour {same:.4f} of pixels, distance within 1e-4 {near:.4f}")


if __name__ == "__main__":
    main()
