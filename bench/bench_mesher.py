"""Mesher benchmark: lodscape's RTIN against pymartini and pydelatin, in the same run.

Terrain: the embedded real DEM (Jacksboro, 257² crop of its 90 m grid) and realistic spectral
fBm surfaces (Hurst 0.8, 1,200 m of relief) of 257², 513² and 1025². Error bounds 1 m and 5 m.

Each mesh is drawn back onto its grid (``lodscape.terrain.rtin.mesh_error``) to measure its real
error. pymartini does not keep to the error it is asked for, so it is also run at the largest
requested error whose mesh does keep to the bound ("martini=", found by bisection): that is the
fair comparison of triangle counts. pydelatin keeps to its bound but inserts points greedily.

Times are medians of ``--repeat`` runs of the whole job: the error pyramid plus one mesh.

    python bench/bench_mesher.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np
import rasterio
from pydelatin import Delatin
from pymartini import Martini

from bench_spine import spectral_fbm
from lodscape.data import sample_dem_path
from lodscape.terrain.rtin import Rtin, mesh_error

Mesh = tuple[np.ndarray, np.ndarray]


def terrains() -> dict[str, np.ndarray]:
    with rasterio.open(sample_dem_path()) as ds:
        real = ds.read(1).astype(np.float64)[:257, :257]
    out = {"jacksboro-257": real}
    for n in (257, 513, 1025):
        out[f"fbm-{n}"] = spectral_fbm(n, seed=n).astype(np.float64)
    return out


def timed(fn: Callable[[], Mesh], repeat: int) -> tuple[float, Mesh]:
    times, result = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t)
    assert result is not None
    return statistics.median(times), result


def ours(h: np.ndarray, e: float) -> Mesh:
    return Rtin(h).mesh(e)


def martini(m: Martini, h32: np.ndarray, e: float) -> Mesh:
    v, t = m.create_tile(h32).get_mesh(e)
    return v.reshape(-1, 2), t.reshape(-1, 3)


def delatin(h32: np.ndarray, e: float) -> Mesh:
    n = h32.shape[0]
    d = Delatin(h32, width=n, height=n, max_error=e)
    return d.vertices[:, :2], d.triangles


def martini_within(m: Martini, h: np.ndarray, h32: np.ndarray, e: float) -> float:
    """The largest request (to 1 %) whose pymartini mesh keeps within ``e``."""
    lo, hi = 0.0, e
    for _ in range(12):
        mid = (lo + hi) / 2
        if mesh_error(h, *martini(m, h32, mid)) <= e:
            lo = mid
        else:
            hi = mid
        if hi - lo < 0.01 * e:
            break
    return lo


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    ours(np.zeros((5, 5)), 0.0)  # compile (or load) the numba kernels outside the timings
    tri_ratio, time_ratio = [], []
    header = (
        f"{'terrain':>14} {'max err':>7} | {'ours':>18} | {'martini (asked)':>26} | "
        f"{'martini= (keeps)':>26} | {'delatin':>18}"
    )
    print(header)
    for name, h in terrains().items():
        h32 = h.astype(np.float32)
        m = Martini(h.shape[0])
        for e in (1.0, 5.0):
            t_o, (v, t) = timed(lambda h=h, e=e: ours(h, e), args.repeat)
            err_o = mesh_error(h, v, t)
            t_m, mm = timed(lambda m=m, h32=h32, e=e: martini(m, h32, e), args.repeat)
            err_m = mesh_error(h, *mm)
            fair = martini_within(m, h, h32, e)
            t_f, mf = timed(lambda m=m, h32=h32, f=fair: martini(m, h32, f), args.repeat)
            t_d, md = timed(lambda h32=h32, e=e: delatin(h32, e), max(1, args.repeat // 3))
            tri_ratio.append(len(t) / len(mf[1]))
            time_ratio.append(t_o / t_f)
            print(
                f"{name:>14} {e:>5.0f} m | {len(t):>8,d} {1e3 * t_o:>6.1f} ms | "
                f"{len(mm[1]):>8,d} {1e3 * t_m:>6.1f} ms err {err_m:5.2f} | "
                f"{len(mf[1]):>8,d} {1e3 * t_f:>6.1f} ms @{fair:5.2f} | "
                f"{len(md[1]):>8,d} {1e3 * t_d:>6.1f} ms"
            )
            assert err_o <= e + 1e-9, (name, e, err_o)
    med = statistics.median
    print(
        f"median triangles ours / pymartini at equal measured error: {med(tri_ratio):.2f} "
        f"(max {max(tri_ratio):.2f}; goal <= 1)"
    )
    print(
        f"median time ours / pymartini at equal measured error: {med(time_ratio):.2f} "
        f"(max {max(time_ratio):.2f}; goal <= 2)"
    )


if __name__ == "__main__":
    main()
