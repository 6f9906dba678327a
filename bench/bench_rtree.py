"""The scene tree's packings on Arge et al.'s ASPECT(a) data (2004, the Priority R-tree paper):
N boxes of equal area and aspect ratio a, half lying east-west and half north-south, uniformly
spread, queried by square windows. Per packing: build time, leaves, the leaves' plan area, and
per query (median) the boxes tested on the way down and the leaves reached. The PR-tree's
guarantee is about leaves reached (its I/O bound); our culling pays for every box tested.

    python bench/bench_rtree.py [--n 50000] [--queries 50] [--window 300]

The city itself (paper 001's benchmark, frame time and boxes tested per packing) is in
``bench/bench_city.py``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from lodscape.city.rtree import pack


def aspect_boxes(n: int, a: float, rng: np.random.Generator, extent: float = 1e4) -> np.ndarray:
    """ASPECT(a): boxes of area 1e-6 × extent², sides in ratio a, half turned by 90°."""
    area = 1e-6 * extent * extent
    c = rng.uniform(0, extent, (n, 2))
    long_side = np.sqrt(area * a)
    short = area / long_side
    flip = rng.random(n) < 0.5
    wx, wy = np.where(flip, long_side, short), np.where(flip, short, long_side)
    lo = np.stack([c[:, 0] - wx / 2, c[:, 1] - wy / 2, np.zeros(n)], 1)
    hi = np.stack([c[:, 0] + wx / 2, c[:, 1] + wy / 2, np.full(n, 10.0)], 1)
    return np.concatenate([lo, hi], 1)


def window(x: float, y: float, size: float) -> np.ndarray:
    """A square window as inward planes (z unbounded)."""
    return np.array(
        [
            [1, 0, 0, -x],
            [-1, 0, 0, x + size],
            [0, 1, 0, -y],
            [0, -1, 0, y + size],
            [0, 0, 1, 1e9],
            [0, 0, -1, 1e9],
        ],
        float,
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=50_000)
    ap.add_argument("--queries", type=int, default=50)
    ap.add_argument("--window", type=float, default=300.0)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    print(f"ASPECT(a), {args.n:,} boxes, {args.queries} windows of {args.window:g} m (medians)")
    for a in (1.0, 100.0, 10_000.0):
        boxes = aspect_boxes(args.n, a, rng)
        xy = rng.uniform(0, 1e4 - args.window, (args.queries, 2))
        planes = [window(x, y, args.window) for x, y in xy]
        for packing in ("str", "hilbert", "priority"):
            t = time.perf_counter()
            tree = pack(boxes, packing=packing)
            built = (time.perf_counter() - t) * 1e3
            tested, reached, ms = [], [], []
            for p in planes:
                t = time.perf_counter()
                vis, n = tree.cull(p)
                ms.append((time.perf_counter() - t) * 1e3)
                tested.append(n)
                reached.append(int(vis.sum()))
            leaf = tree.levels[0]
            area = float(np.prod(leaf[:, 3:5] - leaf[:, :2], axis=1).sum())
            print(
                f"  a={a:<7g} {packing:8s} built {built:6.1f} ms, {tree.leaves:,} leaves "
                f"covering {area / 1e6:7.1f} km²; per query: boxes tested "
                f"{statistics.median(tested):5.0f}, leaves reached "
                f"{statistics.median(reached):4.0f}, {statistics.median(ms):.3f} ms"
            )


if __name__ == "__main__":
    main()
