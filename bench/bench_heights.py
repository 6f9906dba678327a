"""A tileset's heights at many points (``TilesetProvider.heights``, what a refined mesh below the
terrain's finest level samples, and what cities are draped with): the grid of cells against the
naive method it replaced (every point tested against every triangle of its tile), on the same
tiles of issue 4's 4097² fBm tileset; then what one refined 65² mesh (``RefinedProvider``) costs.

    python bench/bench_heights.py [--work DIR] [--dem 4097]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bench_flight import dataset
from lodscape.geo.keys import mesh_key
from lodscape.geo.tiles import Tile, merc_to_lonlat, tile, tile_id
from lodscape.store.provider import RefinedProvider
from lodscape.store.tileset import TilesetProvider, _heights_in


def naive(
    mesh: tuple[NDArray[np.float64], ...], lon: NDArray[np.float64], lat: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Every point against every triangle (the method ``_heights_in`` replaced)."""
    plon, plat, h, tri = mesh
    ax, ay = plon[tri[:, 0]], plat[tri[:, 0]]
    bx, by = plon[tri[:, 1]], plat[tri[:, 1]]
    cx, cy = plon[tri[:, 2]], plat[tri[:, 2]]
    det = (by - cy) * (ax - cx) + (cx - bx) * (ay - cy)
    px, py = lon[:, None], lat[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        wa = ((by - cy) * (px - cx) + (cx - bx) * (py - cy)) / det
        wb = ((cy - ay) * (px - cx) + (ax - cx) * (py - cy)) / det
    wc = 1.0 - wa - wb
    inside = (wa >= -1e-9) & (wb >= -1e-9) & (wc >= -1e-9) & (det != 0)
    k = np.argmax(inside, axis=1)
    r = np.arange(len(k))
    v = wa[r, k] * h[tri[k, 0]] + wb[r, k] * h[tri[k, 1]] + wc[r, k] * h[tri[k, 2]]
    out: NDArray[np.float64] = np.where(inside[r, k], v, np.nan)
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, default=None)
    ap.add_argument("--dem", type=int, default=4097)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        _, lods = dataset(work, args.dem)
        tp = TilesetProvider(lods)
        b = tp.bounds_merc
        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        z = tp.tree.zmax
        centre = tile(lon, lat, z)
        fast, slow = [], []
        for dx in range(5):
            mesh = tp._decoded(z, centre.x + dx, centre.y)
            assert mesh is not None
            plon, plat = mesh[0], mesh[1]
            # a 65² grid of points over the tile, as a refined mesh samples
            g = np.linspace(0.0, 1.0, 65)
            qx, qy = np.meshgrid(plon.min() + g * np.ptp(plon), plat.min() + g * np.ptp(plat))
            qx, qy = qx.ravel(), qy.ravel()
            t = time.perf_counter()
            a = _heights_in(mesh, qx, qy)
            fast.append(time.perf_counter() - t)
            t = time.perf_counter()
            ref = naive(mesh, qx, qy)
            slow.append(time.perf_counter() - t)
            assert np.array_equal(np.isnan(a), np.isnan(ref))
            assert np.nanmax(np.abs(a - ref)) < 1e-9
        f, s = statistics.median(fast) * 1e3, statistics.median(slow) * 1e3
        print(f"65² points on a level-{z} tile ({len(mesh[3])} triangles), median of 5 tiles:")
        print(f"  cells {f:.1f} ms, every pair {s:.1f} ms: x{s / f:.0f}, the same heights")
        refined = RefinedProvider(tp, z + 3)
        times = []
        for dx in range(6):
            key = mesh_key(tile_id(Tile(centre.x * 4 + dx, centre.y * 4, z + 2)), 0)
            t = time.perf_counter()
            refined.fetch(key)
            times.append((time.perf_counter() - t) * 1e3)
        print(
            f"a refined 65² mesh of level {z + 2}: " + ", ".join(f"{v:.1f}" for v in times) + " ms"
        )
        tp.close()


if __name__ == "__main__":
    main()
