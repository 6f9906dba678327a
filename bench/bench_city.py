"""Paper 001's benchmark: a city of about 10,000 objects and 7 million triangles, naive against
every optimisation, on the same headless renderer along a street-level and a bird's-eye path.

    python bench/bench_city.py [--frames 8] [--size 640x360]

The city: the bundled Helsinki extract (446 buildings, 1,397 trees, lamps and benches) repeated
7 times side by side (12,901 objects), with trees drawn from a finer shared model (a crown of
1,280 triangles instead of 80) to reach the paper's triangle count; real footprints, real tags.
Naive: one draw call per object and material, full detail, no culling. Optimised: R-tree
frustum culling, per-leaf levels of detail, merged meshes by material drawn with
multi-draw-indirect, instanced street objects, and leaf-level coherent occlusion queries. Each
optimisation's share: the optimised run with that one turned off. Medians over the path's
frames after one warm-up frame; draw calls and triangles are per frame (medians).
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
        "street level (25 m, looking along the blocks)": path(
            lat0 - 0.15 * span_lat, 25.0, 80.0, -3.0
        ),
        "bird's-eye (400 m, 35° down)": path(lat0 - 0.35 * span_lat, 400.0, 20.0, -35.0),
    }
    full = CityOptions()
    runs = {
        "naive": CityOptions.naive(),
        "all optimisations": full,
        "  without frustum culling": replace(full, frustum=False),
        "  without levels of detail": replace(full, lod=False),
        "  without occlusion culling": replace(full, occlusion=False),
        "  without multi-draw-indirect": replace(full, indirect=False),
        "  without instancing": replace(full, instancing=False),
    }
    for pname, cams in paths.items():
        print(f"\n{pname}, {width}×{height}, {args.frames} frames:")
        base_ms = None
        for rname, opts in runs.items():
            scene.set_city_options(opts)
            scene.render(cams[0])
            times, calls, tris = [], [], []
            for cam in cams[1:]:
                t = time.perf_counter()
                scene.render(cam)
                times.append((time.perf_counter() - t) * 1e3)
                assert scene.last is not None
                calls.append(scene.last.city.get("city_draw_calls", 0))
                tris.append(scene.last.city.get("city_triangles", 0))
            med = statistics.median(times)
            if base_ms is None:
                base_ms = med
            print(
                f"  {rname:32s} {med:9.1f} ms  (x{base_ms / med:6.2f} vs naive)  "
                f"draw calls {int(np.median(calls)):>7,}  triangles {int(np.median(tris)):>10,}"
            )
    scene.close()


if __name__ == "__main__":
    main()
