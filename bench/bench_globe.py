"""The globe (paper 002): the paper's experiment, the screen-space mode at equal on-screen
error, and the refinement's update time per viewpoint move, vectorised against a naive
recursive version of the same rule.

    python bench/bench_globe.py [--moves 40] [--size 1280x720] [--frames]

Experiment: base level 7 (32,768 facets), thinning area +2 levels (level 9) over the blocks
nearest the viewpoint (QTM level 4, the paper's T = 2·4^(6-2) = 512 blocks), against the whole
of level 9 (524,288 facets, the paper's figure). Then, from a camera looking at that place, the
screen-space mode with its error bound set to the thinning selection's own largest error.

Updates: a descent from 20,000 km to 5 km (and on along the ground), one selection per move,
medians; both versions give the same facets (checked on every move).

With ``--frames``: whole frames along the same descent (selection, mesh without cracks, draw
and read-back, headless on EGL), median milliseconds and frames per second.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from lodscape import Camera
from lodscape.geo.qtm import facet_count
from lodscape.lod.globe import by_error, naive_by_error, screen_error, thinning


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--moves", type=int, default=40)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--frames", action="store_true", help="also time whole rendered frames")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    lat, lon = 45.0, 10.0
    full = facet_count(9)
    print(f"whole level 9: {full:,} facets (the paper: 524,288)")
    for blocks in (1, 4):
        sel = thinning(lat, lon, base=7, block_level=4, extra=2, blocks=blocks)
        print(
            f"base 7 + thinning area of {blocks} block(s) at +2: {sel.count:,} facets "
            f"({sel.count / full:.1%} of level 9; the paper: 36,800)"
        )
        for alt in (2.0e5, 2.0e4):
            cam = Camera(lon, lat - 0.5, alt, heading=0.0, pitch=-30.0, width=w, height=h)
            cam = cam.with_clip(alt * 0.05, 2.0e7)
            err = screen_error(sel, cam)
            same = by_error(cam, max_sse=err)
            print(
                f"    at {alt / 1e3:.0f} km: its largest on-screen error {err:.2f} px; the "
                f"screen-space mode at that bound: {same.count:,} facets "
                f"(levels {min(same.levels)}–{max(same.levels)})"
            )
    # updates along a descent
    alts = np.geomspace(2.0e7, 5.0e3, args.moves)
    cams = [
        Camera(
            lon + 0.02 * i,
            lat,
            float(a),
            heading=90.0,
            pitch=-60.0 + 50.0 * i / args.moves,
            width=w,
            height=h,
        ).with_clip(float(a) * 0.05, 2.0e7)
        for i, a in enumerate(alts)
    ]
    fast, slow, counts = [], [], []
    for cam in cams:
        t = time.perf_counter()
        a = by_error(cam, max_sse=2.0)
        t1 = time.perf_counter()
        b = naive_by_error(cam, max_sse=2.0)
        t2 = time.perf_counter()
        assert a.levels.keys() == b.levels.keys()
        assert all(np.array_equal(a.levels[k], b.levels[k]) for k in a.levels)
        fast.append((t1 - t) * 1e3)
        slow.append((t2 - t1) * 1e3)
        counts.append(a.count)
    f, s = statistics.median(fast), statistics.median(slow)
    print(
        f"\nupdates along a descent from 20,000 km to 5 km ({args.moves} moves, {w}×{h}, "
        f"2 px): vectorised {f:.2f} ms, naive recursive {s:.2f} ms per move (×{s / f:.1f}); "
        f"facets per view: median {int(statistics.median(counts)):,}, max {max(counts):,}"
    )
    if args.frames:
        from lodscape.globe import Globe, GlobeOptions

        g = Globe(None, GlobeOptions())
        try:
            g.render(cams[0])  # the context and the global image, once
            whole, select, draw = [], [], []
            for cam in cams:
                t = time.perf_counter()
                g.render(cam.moved())
                whole.append((time.perf_counter() - t) * 1e3)
                select.append(g.last["select_ms"])
                draw.append(g.last["draw_ms"])
            renderer = g.renderer.ctx.info["GL_RENDERER"]
        finally:
            g.close()
        m = statistics.median(whole)
        print(
            f"whole frames along it ({renderer}): median {m:.1f} ms ({1000 / m:.0f} fps): "
            f"selection and mesh {statistics.median(select):.1f} ms, draw and read-back "
            f"{statistics.median(draw):.1f} ms"
        )


if __name__ == "__main__":
    main()
