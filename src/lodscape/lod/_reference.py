"""A naive recursive selection, one tile per Python call: the baseline for tests and benchmarks.

It applies the rules of ``lodscape.lod.select`` tile by tile, depth first, with no residency; the
vectorised selection must return the same tiles and grids.
"""

from __future__ import annotations

import numpy as np

from lodscape.geo.tiles import Tile, tile_id
from lodscape.lod.camera import Camera
from lodscape.lod.select import Selection, SelectOptions, TreeLike, tile_boxes

__all__ = ["select_reference"]


def select_reference(
    options: SelectOptions, camera: Camera, tree: TreeLike, previous: Selection | None = None
) -> list[tuple[int, int, int, int]]:
    """Drawn tiles as (z, x, y, grid index), in depth-first order."""
    assert camera.near is not None
    near = camera.near
    d = camera.scale
    t = tree.tile_size
    zmax = tree.zmax if options.max_level is None else min(tree.zmax, options.max_level)
    was = set(previous.refined.tolist()) if previous is not None else set()
    grid_before = (
        {int(k) >> 3: int(k) & 7 for k in previous.keys.tolist()} if previous is not None else {}
    )
    out: list[tuple[int, int, int, int]] = []

    def metrics(z: int, x: int, y: int) -> tuple[bool, bool, float, np.ndarray, float] | None:
        lv = tree.level(z)
        ok, idx = lv.index(np.array([x]), np.array([y]))
        if not ok[0]:
            return None
        i = int(idx[0])
        nx = lv.min_h.shape[1]
        box = tile_boxes(
            camera,
            z,
            np.array([x]),
            np.array([y]),
            lv.min_h.ravel()[i : i + 1],
            lv.max_h.ravel()[i : i + 1],
        )
        eff = max(float(box.dist_near[0]), near)
        ground = float(box.ground[0])
        return bool(box.inside[0]), True, ground * d / eff, lv.error[:, i // nx, i % nx], ground

    def visit(z: int, x: int, y: int) -> None:
        m = metrics(z, x, y)
        if m is None or not m[0]:
            return
        _, _, px, err, ground = m
        scale = max(px / ground, options.split * t / ground)
        k = next((i for i, e in enumerate(err) if e * scale <= options.max_sse), None)
        refine = z < zmax and (px > options.split * t or k is None)
        if z < zmax and not refine and tile_id(Tile(x, y, z)) in was:
            refine = True
            for cx, cy in (
                (2 * x, 2 * y),
                (2 * x + 1, 2 * y),
                (2 * x, 2 * y + 1),
                (2 * x + 1, 2 * y + 1),
            ):
                c = metrics(z + 1, cx, cy)
                if c is not None and c[0] and c[2] < options.merge * t:
                    refine = False
        if refine:
            for cx, cy in (
                (2 * x, 2 * y),
                (2 * x + 1, 2 * y),
                (2 * x, 2 * y + 1),
                (2 * x + 1, 2 * y + 1),
            ):
                visit(z + 1, cx, cy)
        else:
            k = len(err) - 1 if k is None else k
            if grid_before.get(tile_id(Tile(x, y, z))) == k + 1:
                k += 1
            out.append((z, x, y, k))

    xs, ys = tree.roots()
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        visit(tree.zmin, x, y)
    return out
