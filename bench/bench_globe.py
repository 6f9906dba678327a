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

With ``--flight``: a descent from orbit to the street over the embedded sample DEM in one scene
(the globe, the sample's own terrain tiles laid in where it has data), at a steady screen-space
speed (the altitude falls by the same share each frame, so the ground crosses the screen at
about the same pace): per frame the globe's facets, the pixels its terrain tiles drew, the
selection and the whole frame; the worst frame and the medians.
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
    ap.add_argument(
        "--flight", type=int, default=0, metavar="N", help="also an N-frame descent over the sample"
    )
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
    if args.flight:
        _descent(args.flight, w, h)


def _descent(n: int, w: int, h: int) -> None:
    """Orbit to street over the sample DEM: ``n`` frames, the altitude a geometric series from
    2,000 km to 1.5 km above its highest ground, looking at the DEM's middle from the south,
    straight down at first, 40° down at the end."""
    import lodscape
    from lodscape.data import sample_dem_path
    from lodscape.globe import Globe, GlobeOptions

    scene = lodscape.open(sample_dem_path())
    g = Globe(scene, GlobeOptions())
    try:
        lon, lat = -84.25, 36.59
        top = scene.tree.height_range[1]
        alts = np.geomspace(2.0e6, top + 1500.0, n)
        rows = []
        g.render(Camera(lon, lat, 2.0e6, pitch=-90.0, width=w, height=h))  # context, images
        for i, alt in enumerate(alts):
            f = i / max(n - 1, 1)
            down = np.radians(90.0 - 50.0 * f)  # the view's angle below the horizon
            back = float(alt) / np.tan(down) / 111_000.0 if f > 0 else 0.0
            target = (lon, lat, top * 0.5)
            cam = (
                Camera(lon, lat, float(alt), pitch=-90.0, width=w, height=h)
                if f == 0
                else Camera.looking_at(lon, lat - back, float(alt), target, width=w, height=h)
            )
            t = time.perf_counter()
            g.render(cam)
            rows.append(
                (
                    float(alt),
                    (time.perf_counter() - t) * 1e3,
                    g.last["select_ms"],
                    g.last["triangles"],
                    g.last["terrain_pixels"],
                )
            )
    finally:
        g.close()
    whole = [r[1] for r in rows]
    worst = max(rows, key=lambda r: r[1])
    print(
        f"\ndescent over the sample, {n} frames from 2,000 km to {alts[-1]:,.0f} m, {w}×{h}: "
        f"frame median {statistics.median(whole):.0f} ms, worst {worst[1]:.0f} ms (at "
        f"{worst[0] / 1e3:,.1f} km); selection median {statistics.median(r[2] for r in rows):.1f}"
        f" ms; globe facets up to {max(r[3] for r in rows):,}; the sample's own tiles drew "
        f"pixels in {sum(r[4] > 0 for r in rows)} frames, "
        f"{rows[-1][4] / (w * h):.0%} of the last"
    )
    for alt, ms, sel, facets, px in [*rows[:: max(1, n // 8)], rows[-1]]:
        print(
            f"    {alt / 1e3:>9,.1f} km: {ms:6.0f} ms, selection {sel:5.1f} ms, {facets:>5,} "
            f"facets, terrain pixels {px / (w * h):4.0%}"
        )


if __name__ == "__main__":
    main()
