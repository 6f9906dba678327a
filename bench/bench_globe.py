"""The globe (paper 002): the paper's experiment, the screen-space mode at equal on-screen
error, and the refinement's update time per viewpoint move, vectorised against a naive
recursive version of the same rule.

    python bench/bench_globe.py [--moves 40] [--size 1280x720] [--frames]

Experiment: base level 7 (32,768 facets) with the block nearest the viewpoint (QTM level 4,
the paper's T = 2·4^(6-2) = 512 blocks) refined three levels: 32,704 level-7 and 4,096 level-10
facets, the paper's 36,800, against the whole of level 9 (524,288 facets, the paper's figure);
then one and four blocks at +2. Then, from a camera looking at that place, the
screen-space mode with its error bound set to the thinning selection's own largest error.

Updates: a descent from 20,000 km to 5 km (and on along the ground), one selection per move,
medians; both versions give the same facets (checked on every move).

With ``--frames``: whole frames along the same descent (selection, mesh without cracks, draw
and read-back, headless on EGL), median milliseconds and frames per second.

With ``--flight N``: a descent from orbit to the street over the embedded sample DEM in one
scene, flown as a flight is (``lodscape.flight.fly``: the one frame loop, the sample's tiles and
any ``--imagery`` layer streaming on a simulated clock at ``--fps``), at a steady screen-space
speed (the altitude falls by the same share each frame, so the ground crosses the screen at
about the same pace): frames, fallbacks over one level, frames over budget, the worst frame,
selection time, facets and triangles. ``--imagery bluemarble:Z`` cuts the Blue Marble into
Web Mercator tiles down to level Z (offline) for a layer over the whole globe.
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
    ap.add_argument("--fps", type=float, default=30.0, help="the descent's frame rate")
    ap.add_argument(
        "--imagery",
        default=None,
        help="an imagery layer for the descent (a template, .mbtiles, folder or raster), or "
        "bluemarble:Z for NASA's Blue Marble cut into Web Mercator tiles down to level Z",
    )
    args = ap.parse_args()
    if args.imagery and args.imagery.startswith("bluemarble:"):
        args.imagery = _blue_marble_tiles(int(args.imagery.split(":")[1]))
    w, h = (int(v) for v in args.size.split("x"))
    lat, lon = 45.0, 10.0
    full = facet_count(9)
    print(f"whole level 9: {full:,} facets (the paper: 524,288)")
    # the paper's figure: the nearest block (QTM level 4, 64 level-7 facets) refined three
    # levels, 32,704 facets of level 7 and 4,096 of level 10
    paper = thinning(lat, lon, base=7, block_level=4, extra=3, blocks=1)
    print(
        f"the paper's setting, base 7 + the nearest block at +3: {paper.count:,} facets "
        f"(level 7: {len(paper.levels[7]):,}, level 10: {len(paper.levels[10]):,}; "
        f"{paper.count / full:.1%} of level 9; the paper: 36,800)"
    )
    for blocks, extra in ((1, 3), (1, 2), (4, 2)):
        sel = thinning(lat, lon, base=7, block_level=4, extra=extra, blocks=blocks)
        print(
            f"base 7 + thinning area of {blocks} block(s) at +{extra}: {sel.count:,} facets "
            f"({sel.count / full:.1%} of level 9)"
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
        _descent(args.flight, w, h, args.imagery, args.fps)


def _blue_marble_tiles(zmax: int) -> str:
    """A folder of z/x/y.png Web Mercator tiles cut from the Blue Marble (``lodscape[earth]``),
    levels 0..zmax (nearest-pixel resampling): a real imagery layer for the globe, offline."""
    import os
    import tempfile

    from PIL import Image

    from lodscape.geo.tiles import bounds_array, merc_to_lonlat
    from lodscape.imagery.globe import earth_image

    image, notice = earth_image()
    if notice is not None:
        raise SystemExit(f"bluemarble: {notice}")
    rows, cols = image.shape[:2]
    out = tempfile.mkdtemp(prefix="bluemarble-")
    f = (np.arange(256) + 0.5) / 256.0
    for z in range(zmax + 1):
        for x in range(1 << z):
            for y in range(1 << z):
                left, bottom, right, top = bounds_array(z, x, y)
                lon, lat = merc_to_lonlat(
                    (left + (right - left) * f)[None, :], (top - (top - bottom) * f)[:, None]
                )
                c = np.clip(((lon + 180.0) / 360.0 * cols).astype(int), 0, cols - 1)
                r = np.clip(((90.0 - lat) / 180.0 * rows).astype(int), 0, rows - 1)
                os.makedirs(f"{out}/{z}/{x}", exist_ok=True)
                Image.fromarray(image[r, c]).save(f"{out}/{z}/{x}/{y}.png")
    return out


def _descent(n: int, w: int, h: int, imagery: str | None, fps: float) -> None:
    """Orbit to street over the sample DEM as a flight (``lodscape.flight.fly``, the one frame
    loop, streaming on a simulated clock at ``fps``): ``n`` frames, the altitude a geometric
    series from 2,000 km to 1.5 km above its highest ground, looking at the DEM's middle from
    the south, straight down at first, 40° down at the end; ``imagery`` a layer streamed over
    the whole globe and on the DEM's tiles."""
    import tempfile
    from pathlib import Path

    import lodscape
    from lodscape.data import sample_dem_path
    from lodscape.flight import fly
    from lodscape.globe import Globe, GlobeOptions
    from lodscape.stream import SimClock, StreamOptions

    options = lodscape.SceneOptions(
        stream=StreamOptions(cache_mb=256.0, memory_mb=256.0), gpu_budget_mb=256.0
    )
    cache = tempfile.mkdtemp(prefix="bench-globe-")
    scene = lodscape.open(
        sample_dem_path(), options, clock=SimClock(), imagery=imagery, imagery_cache=cache
    )
    g = Globe(scene, GlobeOptions())
    lon, lat = -84.25, 36.59
    top = scene.tree.height_range[1]
    alts = np.geomspace(2.0e6, top + 1500.0, n)
    cams = []
    for i, alt in enumerate(alts):
        f = i / max(n - 1, 1)
        down = np.radians(90.0 - 50.0 * f)  # the view's angle below the horizon
        back = float(alt) / np.tan(down) / 111_000.0 if f > 0 else 0.0
        target = (lon, lat, top * 0.5)
        cams.append(
            Camera(lon, lat, float(alt), pitch=-90.0, width=w, height=h)
            if f == 0
            else Camera.looking_at(lon, lat - back, float(alt), target, width=w, height=h)
        )
    wall: list[float] = []
    t = [time.perf_counter()]

    def tick(_: int) -> None:
        now = time.perf_counter()
        wall.append((now - t[0]) * 1e3)
        t[0] = now

    try:
        rows = list(fly(g, iter(cams), fps, stats=Path(cache) / "rows.csv", on_frame=tick))
    finally:
        g.close()
    worst = int(np.argmax(wall))
    fell = [r["fallback_max"] > 1 or r["imagery_fallbacks"] > 0 for r in rows]
    print(
        f"\ndescent over the sample as a flight at {fps:g} fps, {n} frames from 2,000 km to "
        f"{alts[-1]:,.0f} m, {w}×{h}{', imagery ' + imagery if imagery else ''}:"
    )
    print(
        f"    frame (wall) median {statistics.median(wall):.0f} ms, worst {wall[worst]:.0f} ms "
        f"(frame {worst}, {alts[worst] / 1e3:,.1f} km); frame CPU (selections, loading) median "
        f"{statistics.median(r['frame_cpu_ms'] for r in rows):.1f} ms, over the "
        f"{1000 / fps:.0f} ms budget in {sum(r['over_budget'] for r in rows)} frames"
    )
    print(
        f"    globe selection median {statistics.median(r['select_ms'] for r in rows):.1f} ms; "
        f"facets up to {max(r['facets'] for r in rows):,}; terrain triangles up to "
        f"{max(r['triangles'] for r in rows):,}; the sample's own tiles drew pixels in "
        f"{sum(r['terrain_pixels'] > 0 for r in rows)} frames, "
        f"{rows[-1]['terrain_pixels'] / (w * h):.0%} of the last"
    )
    print(
        f"    fell back more than one level (terrain tiles, or imagery from an ancestor two or "
        f"more up) in {sum(fell)} frames, {sum(fell[int(fps) :])} after the first second; "
        f"imagery tiles missing (none resident yet) in "
        f"{sum(r['imagery_missing'] > 0 for r in rows)} frames"
    )
    for i in [*range(0, n, max(1, n // 8)), n - 1]:
        r = rows[i]
        print(
            f"    {alts[i] / 1e3:>9,.1f} km: {wall[i]:6.0f} ms, selection {r['select_ms']:5.1f} "
            f"ms, {r['facets']:>5,} facets, {r['triangles']:>7,} terrain triangles, "
            f"terrain pixels {r['terrain_pixels'] / (w * h):4.0%}, imagery tiles "
            f"{r['imagery_tiles']} ({r['imagery_fallbacks']} from 2+ up)"
        )


if __name__ == "__main__":
    main()
