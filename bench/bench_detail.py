"""Fractal detail (paper 003): tile generation throughput, the detail's share of frame time, and
how many triangles patch culling skips.

    python bench/bench_detail.py

Throughput: 65×65 tiles (64 segments) of fractal detail on the sample DEM and of the procedural
planet, made one after another (what one worker does), against the same tiles of the plain DEM
(the baseline, in the same process). Frame share: the same low views over the sample DEM rendered
with and without --detail fractal (every tile loaded, medians of 3 renders after a warm-up).
Patch culling: triangles drawn with and without it at a low oblique view and a view straight
down, on the sample DEM with detail and on the procedural planet; the pictures are compared.
Visible region: the tiles whose bounds the selection asks for, and its time, with and without
the region pre-cull (medians of 7, same process).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace

import numpy as np

import lodscape
from lodscape import Camera, SceneOptions
from lodscape.data import sample_dem_path
from lodscape.geo.keys import mesh_key
from lodscape.geo.tiles import merc_to_lonlat, tiles_array
from lodscape.lod.select import select
from lodscape.terrain.detail import Fractal


def _throughput(provider: object, z: int, x0: int, y0: int, n: int = 6) -> float:
    heights = getattr(provider, "heights", None)
    t = time.perf_counter()
    for i in range(n):
        for j in range(n):
            if heights is not None:
                heights.tile(z, x0 + i, y0 + j, 64)
            else:
                provider.fetch(mesh_key(_id(z, x0 + i, y0 + j), 2))  # type: ignore[attr-defined]
    return n * n / (time.perf_counter() - t)


def _id(z: int, x: int, y: int) -> int:
    from lodscape.geo.tiles import Tile, tile_id

    return int(tile_id(Tile(x, y, z)))


def main() -> None:
    dem = str(sample_dem_path())
    plain = lodscape.open(dem)
    det = lodscape.open(dem, detail=Fractal(0.7, None, 1))
    proc = lodscape.open("procedural:seed=3")
    b = plain.provider.bounds_merc
    cx, cy = (b.left + b.right) / 2, (b.top + b.bottom) / 2
    tree = det.tree
    print("fractal tile generation, 65×65 heights per tile, one thread (tiles/s):")
    for name, scene, z in (
        ("DEM (no detail), finest level", plain, tree.base.zmax),
        ("DEM + detail, 2 levels below", det, tree.base.zmax + 2),
        ("DEM + detail, deepest level", det, tree.zmax),
        ("procedural planet, z 12", proc, 12),
        ("procedural planet, z 18", proc, 18),
    ):
        x, y = tiles_array(cx, cy, z)
        rates = [_throughput(scene.provider, z, int(x), int(y)) for _ in range(3)]
        print(f"  {name:34s} {statistics.median(rates):8.1f}")

    lon, lat = (float(v) for v in merc_to_lonlat(cx, cy))
    g = plain.ground_height(lon, lat) or 0.0
    views = {
        "low oblique (150 m)": Camera(
            lon, lat, g + 150, heading=40, pitch=-15, width=640, height=360
        ),
        "straight down (600 m)": Camera(lon, lat, g + 600, pitch=-90, width=640, height=360),
    }
    print("\nframe time with and without detail (sample DEM, 640×360, all tiles loaded; ms):")
    for vname, cam in views.items():
        row = []
        for scene in (plain, det):
            scene.render(cam)
            times, sel = [], []
            for _ in range(3):
                t = time.perf_counter()
                scene.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
                assert scene.last is not None
                sel.append(scene.last.select_ms)
            row.append((statistics.median(times), statistics.median(sel), scene.last.triangles))
        (tp, sp, np_), (td, sd, nd) = row
        print(
            f"  {vname:22s} plain {tp:7.1f} (select {sp:5.1f}, {np_:,} tris)  detail {td:7.1f} "
            f"(select {sd:5.1f}, {nd:,} tris)  detail share {100 * (td - tp) / td:5.1f} %"
        )
    # the cost of making the tiles a low flight needs: every load of the detailed view
    cam = views["low oblique (150 m)"]
    with lodscape.open(dem, detail=Fractal(0.7, None, 1)) as fresh:
        t = time.perf_counter()
        fresh.render(cam)
        first = (time.perf_counter() - t) * 1e3
        assert fresh.last is not None
        print(
            f"  first detailed frame (every tile made): {first:.0f} ms, of which loading "
            f"{fresh.last.load_ms:.0f} ms for {fresh.last.loaded} meshes and textures"
        )

    print("\npatch culling (normal cones, 8×8-cell patches), triangles drawn:")
    gp = proc.ground_height(7.0, 46.0) or 0.0
    cases = {
        "DEM + detail": (dem, Fractal(0.7, None, 1), lon, lat, g),
        "procedural": ("procedural:seed=3", None, 7.0, 46.0, gp),
    }
    for cname, (src, fr, lo, la, ground) in cases.items():
        cams = {
            "low oblique": Camera(
                lo, la, ground + 80, heading=60, pitch=-10, width=640, height=360
            ),
            "straight down": Camera(lo, la, ground + 1500, pitch=-90, width=640, height=360),
        }
        for vname, cam in cams.items():
            out = []
            for cull in (True, False):
                with lodscape.open(src, SceneOptions(cull_backfacing=cull), detail=fr) as s:
                    rgb, _ = s.render(cam)
                    assert s.last is not None
                    out.append((rgb, s.last.triangles, s.last.backfacing))
            (ra, ta, pa), (rb, tb, _) = out
            same = bool(np.array_equal(ra, rb))
            print(
                f"  {cname:14s} {vname:14s} {tb:>10,} -> {ta:>10,} "
                f"({100 * (tb - ta) / tb:5.2f} % fewer, {pa} patches), same picture: {same}"
            )

    print("\nvisible region (frustum ∩ the slab of the parents' heights), selection only:")
    for cname, (src, fr, lo, la, ground) in cases.items():
        with lodscape.open(src, detail=fr) as s:
            cams = {
                "low oblique": Camera(
                    lo, la, ground + 80, heading=60, pitch=-10, width=640, height=360
                ),
                "oblique 3 km": Camera(
                    lo, la, ground + 3000, heading=60, pitch=-25, width=640, height=360
                ),
                "straight down": Camera(lo, la, ground + 1500, pitch=-90, width=640, height=360),
            }
            for vname, cam in cams.items():
                cam = s.prepare(cam)
                res = []
                for on in (True, False):
                    opts = replace(s.options.select, region=on)
                    select(opts, cam, s.tree)
                    times = []
                    for _ in range(7):
                        t = time.perf_counter()
                        sel = select(opts, cam, s.tree)
                        times.append((time.perf_counter() - t) * 1e3)
                    res.append((statistics.median(times), sel))
                # cold: a fresh tree, nothing cached (the procedural planet's bounds computed)
                cold = []
                for on in (False, True):
                    with lodscape.open(src, detail=fr) as fresh:
                        opts = replace(fresh.options.select, region=on)
                        t = time.perf_counter()
                        select(opts, cam, fresh.tree)
                        cold.append((time.perf_counter() - t) * 1e3)
                (ta, a), (tb, b) = res
                print(
                    f"  {cname:14s} {vname:14s} bounds asked {b.visited:>6,} -> {a.visited:>6,} "
                    f"({a.outside:,} dropped unseen); select warm {tb:6.1f} -> {ta:6.1f} ms "
                    f"(x{tb / ta:4.2f}), cold {cold[0]:7.1f} -> {cold[1]:7.1f} ms "
                    f"(x{cold[0] / cold[1]:4.2f}); same tiles: {np.array_equal(a.keys, b.keys)}"
                )
    for s in (plain, det, proc):
        s.close()


if __name__ == "__main__":
    main()
