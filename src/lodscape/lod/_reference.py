"""A naive recursive selection, one tile per Python call: the baseline for tests and benchmarks.

It applies the rules of ``lodscape.lod.select`` tile by tile, depth first, with no residency; the
vectorised selection must return the same tiles and grids.
"""

from __future__ import annotations

import numpy as np

from lodscape.geo.keys import grid_of, tile_id_of
from lodscape.geo.tiles import Tile, tile_id
from lodscape.lod.camera import Camera
from lodscape.lod.select import Selection, SelectOptions, TreeLike, tile_boxes

__all__ = ["select_reference"]


def select_reference(
    options: SelectOptions, camera: Camera, tree: TreeLike, previous: Selection | None = None
) -> list[tuple[int, int, int, int, int]]:
    """Drawn tiles as (z, x, y, grid index, levels up to the texture), in depth-first order."""
    assert camera.near is not None
    near = camera.near
    d = camera.scale
    t = tree.tile_size
    zmax = tree.zmax if options.max_level is None else min(tree.zmax, options.max_level)
    ztex = tree.zmax if tree.texture_zmax is None else tree.texture_zmax
    was = set(previous.refined.tolist()) if previous is not None else set()
    grid_before = (
        {tile_id_of(int(k)): grid_of(int(k)) for k in previous.keys.tolist()}
        if previous is not None
        else {}
    )
    tex_before = (
        {
            int(tile_id(Tile(x, y, z))): int(u)
            for z, x, y, u in zip(
                previous.z, previous.x, previous.y, previous.texture_up, strict=True
            )
        }
        if previous is not None
        else {}
    )
    out: list[tuple[int, int, int, int, int]] = []

    def metrics(z: int, x: int, y: int) -> tuple[bool, bool, float, np.ndarray, float] | None:
        st = tree.level(z).stats(np.array([x]), np.array([y]))
        if not st.exists[0]:
            return None
        box = tile_boxes(camera, z, np.array([x]), np.array([y]), st.min_h, st.max_h)
        eff = max(float(box.dist_near[0]), near)
        ground = float(box.ground[0])
        return bool(box.inside[0]), True, ground * d / eff, st.error[:, 0], ground

    def visit(z: int, x: int, y: int) -> None:
        m = metrics(z, x, y)
        if m is None or not m[0]:
            return
        _, _, px, err, ground = m
        scale = px / ground
        k = next((i for i, e in enumerate(err) if e * scale <= options.max_sse), None)
        big = px > options.split * t and z < ztex
        refine = z < zmax and (big or k is None)
        if z < zmax and not refine and tile_id(Tile(x, y, z)) in was:
            # kept split while still rough, or while every visible child stays in the band
            refine = err[-1] * scale > options.sse_merge * options.max_sse
            hold = z < ztex
            for cx, cy in (
                (2 * x, 2 * y),
                (2 * x + 1, 2 * y),
                (2 * x, 2 * y + 1),
                (2 * x + 1, 2 * y + 1),
            ):
                c = metrics(z + 1, cx, cy)
                if c is not None and c[0] and c[2] < options.merge * t:
                    hold = False
            refine = refine or hold
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
            up = max(0, z - ztex)
            while up < z - tree.zmin and px * 2**up < options.merge * t:
                up += 1
            before = tex_before.get(tile_id(Tile(x, y, z)))
            if before is not None and options.merge * t <= px * 2**before <= options.split * t:
                up = before
            out.append((z, x, y, k, up))

    xs, ys = tree.roots()
    for x, y in zip(xs.tolist(), ys.tolist(), strict=True):
        visit(tree.zmin, x, y)
    return out
