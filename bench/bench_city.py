"""Paper 001's benchmark: a city of about 10,000 objects and 7 million triangles, naive against
every optimisation, on the same headless renderer along a pedestrian, a street-level and a
bird's-eye path.

    python bench/bench_city.py [--frames 8] [--size 640x360]

The city: the bundled Helsinki extract (446 buildings, 1,397 trees, lamps and benches) repeated
7 times side by side (12,901 objects), with trees drawn from a finer shared model (a crown of
1,280 triangles instead of 80) to reach the paper's triangle count; real footprints, real tags.
Naive: one draw call per object and material, full detail, no culling. Defaults: R-tree
frustum culling, per-leaf levels of detail, merged meshes by material drawn with
multi-draw-indirect and instanced street objects; the camera in a uniform buffer with the
instances in a storage buffer, and coherent hierarchical occlusion queries
(CHC++: leaves, their parents where all were hidden, query skipping) are measured as
additions (the buffers are off by default; occlusion culling is "auto": on for a software
rasteriser below 10 m). Each optimisation's share: the defaults with that one flipped;
the three R-tree packings (STR, Hilbert, Priority R-tree) compared on the same paths, and
their frustum culling alone (time and boxes tested). "frame" is the whole frame
(terrain, city, read-back of the picture); "city pass" the city's draw alone, GPU waits
included. Medians over the path's frames after one warm-up frame; draw calls, triangles,
queries and boxes tested are per frame (medians). On a software rasteriser (llvmpipe) textures
get no anisotropic filtering, which would cost more than everything else.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np
from shapely import affinity

import lodscape
from lodscape import Camera
from lodscape.city import mesh as city_mesh
from lodscape.city.model import CityOptions, build_city
from lodscape.city.osm import City, Feature, read_osm
from lodscape.data import sample_city_path


def grown_city(copies: int = 7) -> City:
    base = read_osm(sample_city_path())
    w, s, e, n = base.bounds
    dx, dy = (e - w) * 1.05, (n - s) * 1.05
    out = City(f"helsinki x{copies}", [], [])
    for k in range(copies):
        ox, oy = (k % 4) * dx, (k // 4) * dy
        for b in base.buildings:
            fp = affinity.translate(b.footprint, ox, oy)
            out.buildings.append(replace(b, osm_id=f"{b.osm_id}#{k}", footprint=fp))
        for f in base.features:
            out.features.append(Feature(f.kind, f.lon + ox, f.lat + oy, f.height))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", default="640x360")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    # the grown tree model: the same tree, a finer crown
    tree = city_mesh.MODELS["tree"]
    fine = city_mesh._sphere(2.4, 4.6, 3)
    city_mesh.MODELS["tree"] = {
        "bark": tree["bark"],
        "foliage": city_mesh._geometry(*fine),
    }
    city = grown_city()
    t = time.perf_counter()
    w, s, e, n = city.bounds
    spec = f"flat:{w - 0.01},{s - 0.005},{e + 0.01},{n + 0.005}"
    scene = lodscape.open(spec)
    model = build_city(city, scene.heights)
    print(
        f"city: {model.objects:,} objects ({model.buildings:,} buildings), "
        f"{model.triangles(0):,} triangles at full detail, {model.tree.leaves} leaves; "
        f"built in {time.perf_counter() - t:.1f} s"
    )
    others = {}
    for packing in ("str", "hilbert", "priority"):
        if packing == model.tree.packing:
            continue
        t = time.perf_counter()
        others[packing] = build_city(city, scene.heights, packing=packing)
        print(f"the same city in a {packing} R-tree: built in {time.perf_counter() - t:.1f} s")
    for tree in [model.tree, *(o.tree for o in others.values())]:
        leaf = tree.levels[0]
        vol = float(np.prod(leaf[:, 3:] - leaf[:, :3], axis=1).sum())
        area = float(np.prod(leaf[:, 3:5] - leaf[:, :2], axis=1).sum())
        print(
            f"  {tree.packing:8s} R-tree: {tree.leaves} leaves, {len(tree.levels)} levels; "
            f"leaf boxes cover {area / 1e6:.2f} km² in plan, {vol / 1e9:.3f} km³"
        )
    scene.add_city(model)
    lat0 = model.frame.lat
    span_lon, span_lat = (e - w), (n - s)

    def path(lat: float, alt: float, heading: float, pitch: float) -> list[Camera]:
        """Cameras moving east across the grown city."""
        return [
            Camera(
                w + span_lon * (0.05 + 0.9 * i / args.frames),
                lat,
                alt,
                heading=heading,
                pitch=pitch,
                width=width,
                height=height,
            )
            for i in range(args.frames + 1)
        ]

    paths = {
        "pedestrian (2 m, level, walls in the way)": path(lat0 - 0.15 * span_lat, 2.0, 80.0, 0.0),
        "street level (25 m, looking along the blocks)": path(
            lat0 - 0.15 * span_lat, 25.0, 80.0, -3.0
        ),
        "bird's-eye (400 m, 35° down)": path(lat0 - 0.35 * span_lat, 400.0, 20.0, -35.0),
    }
    full = CityOptions(timed=True)
    runs = {"naive": replace(CityOptions.naive(), timed=True), "defaults": full}
    # occlusion culling is "auto" by default (on a software rasteriser below 10 m): both ways
    runs["  occlusion culling always on"] = replace(full, occlusion=True)
    runs["  occlusion culling always off"] = replace(full, occlusion=False)
    for flag, what in (
        ("frustum", "frustum culling"),
        ("lod", "levels of detail"),
        ("hierarchical", "node queries (leaf queries only)"),
        ("indirect", "multi-draw-indirect"),
        ("instancing", "instancing"),
        ("buffers", "uniform and storage buffers"),
    ):
        on = getattr(full, flag)
        if flag == "hierarchical":
            runs["  with occlusion culling, leaf queries only"] = replace(
                full, occlusion=True, hierarchical=False
            )
            continue
        runs[f"  {'without' if on else 'with'} {what}"] = replace(full, **{flag: not on})
    defaults: dict[str, tuple[float, float, float]] = {}
    for pname, cams in paths.items():
        print(f"\n{pname}, {width}×{height}, {args.frames} frames:")
        base: tuple[float, float] | None = None
        swaps = {f"  {p} packing instead of {model.tree.packing}": o for p, o in others.items()}
        for rname, opts in [*runs.items(), *((k, full) for k in swaps)]:
            on = scene
            on.add_city(swaps.get(rname, model), opts)
            on.render(cams[0])
            times, city_ms, calls, tris, queries, tested = [], [], [], [], [], []
            gpu_mb: list[float] = []
            for cam in cams[1:]:
                t = time.perf_counter()
                on.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
                assert on.last is not None
                calls.append(on.last.city.get("city_draw_calls", 0))
                tris.append(on.last.city.get("city_triangles", 0))
                queries.append(on.last.city.get("city_queries", 0))
                city_ms.append(on.last.city.get("city_pass_us", 0) / 1e3)
                tested.append(on.last.city.get("city_boxes_tested", 0))
                gpu_mb.append(on.last.resident_mb)
            med = statistics.median(times)
            cmed = statistics.median(city_ms)
            if base is None:
                base = (med, cmed)
            if rname == "defaults":
                defaults[pname] = (med, cmed, statistics.median(gpu_mb))
            print(
                f"  {rname:42s} frame {med:7.1f} ms (x{base[0] / med:5.2f})  "
                f"city pass {cmed:7.1f} ms (x{base[1] / cmed:6.2f})  "
                f"draws {int(np.median(calls)):>6,}  tris {int(np.median(tris)):>9,}  "
                f"queries {int(np.median(queries)):>4,}  boxes {int(np.median(tested)):>4,}  "
                f"terrain GPU {statistics.median(gpu_mb):5.1f} MiB"
            )
        # the scene tree alone: frustum culling's time and boxes tested, per packing
        for m in [model, *others.values()]:
            cull_ms, tested = [], []
            for cam in cams[1:]:
                planes = m.local_planes(scene.prepare(cam))
                t = time.perf_counter()
                for _ in range(20):
                    _, n = m.tree.cull(planes)
                cull_ms.append((time.perf_counter() - t) / 20 * 1e3)
                tested.append(n)
            print(
                f"  culling, {m.tree.packing:8s} R-tree: {statistics.median(cull_ms):6.3f} ms, "
                f"boxes tested {int(np.median(tested)):>5,}"
            )
    scene.close()
    # the ground's imagery and the facade/roof atlas block-compressed, in a scene of their own
    # (opened after the first is closed: one GL context at a time)
    print("\ntextures block-compressed (BC1/BC3), the defaults on each path:")
    with lodscape.open(spec, lodscape.SceneOptions(compress_textures=True)) as packed:
        packed.add_city(model, full)
        for pname, cams in paths.items():
            packed.render(cams[0])
            times, city_ms, gpu_mb = [], [], []
            for cam in cams[1:]:
                t = time.perf_counter()
                packed.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
                assert packed.last is not None
                city_ms.append(packed.last.city.get("city_pass_us", 0) / 1e3)
                gpu_mb.append(packed.last.resident_mb)
            med, cmed = statistics.median(times), statistics.median(city_ms)
            d = defaults[pname]
            print(
                f"  {pname.split(' (')[0]:12s} frame {med:7.1f} ms (uncompressed {d[0]:.1f}, "
                f"x{d[0] / med:.2f})  city pass {cmed:6.1f} ms (x{d[1] / cmed:.2f})  terrain "
                f"GPU {statistics.median(gpu_mb):.2f} MiB (uncompressed {d[2]:.2f})"
            )


if __name__ == "__main__":
    main()
