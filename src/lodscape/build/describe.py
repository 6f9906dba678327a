"""What a terrain is, as ``lodscape info`` prints it: footprint, heights, levels, and for a
tileset its build record and each level's errors against the budget it was built to."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import Any

import numpy as np

from lodscape.build.tiles import level_budget
from lodscape.geo.tiles import ORIGIN, merc_to_lonlat
from lodscape.store.provider import RefinedProvider
from lodscape.store.tileset import TIN_GRID

__all__ = ["describe"]


def describe(provider: Any) -> Iterator[tuple[str, str]]:
    """(label, text) lines describing ``provider`` (an empty label: the line goes on the one
    before): a raster's resolution and nodata, or a
    tileset's size, build options, fill, voids and inputs; then each stored level's tiles and
    errors (a tileset's against its build's budget)."""
    imagery_zmax = provider.texture_levels[0]
    if isinstance(provider, RefinedProvider):
        # a tileset whose baked imagery is finer than its terrain: report the terrain's own
        provider = provider.base
    tree = provider.tree
    b = provider.bounds_merc
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    yield ("source", f"{provider.name}")
    yield ("bounds", f"{w:.6f} {s:.6f} {e:.6f} {n:.6f} (lon/lat)")
    yield ("bounds 3857", f"{b.left:.1f} {b.bottom:.1f} {b.right:.1f} {b.top:.1f}")
    lo, hi = tree.height_range
    yield ("heights", f"{lo:.1f} .. {hi:.1f} m")
    yield (
        "levels",
        f"{tree.zmin} .. {tree.zmax}, textures to {tree.texture_zmax}"
        + (f" (coarsened by {tree.coarsened})" if tree.coarsened else ""),
    )
    if imagery_zmax != tree.texture_zmax:
        yield ("imagery", f"levels {tree.zmin} .. {imagery_zmax} (baked at its own)")
    manifest = getattr(provider, "manifest", None)  # a tileset's build record
    if manifest is None:
        res = provider.resolution_merc
        if res is not None:
            yield ("resolution", f"{res:.3f} m (Web Mercator)")
        raster = getattr(provider, "source", None)
        share = getattr(raster, "valid_share", None)
        if isinstance(share, float) and share < 1.0:
            yield (
                "nodata",
                f"{100.0 * (1.0 - share):.1f} % of the raster (drawn as "
                "holes; --fill to stand something in)",
            )
            voids = getattr(raster, "void_share", None)
            if isinstance(voids, float) and voids > 0.0:
                yield (
                    "voids",
                    f"{100.0 * voids:.2f} % of the raster inside the data "
                    "(--fill interpolate, a build's default, fills them from their rims)",
                )
    else:
        size = os.path.getsize(provider.path)
        yield ("tileset", f"{size / 2**20:.2f} MiB, schema {manifest['schema']}")
        yield ("terrain", "quantized-mesh-1.0, octvertexnormals; imagery: MBTiles PNG")
        opts = manifest["options"]
        yield ("build", f"error {opts['error_texels']} texel(s) per level")
        fill = opts.get("fill", "nearest")  # builds before the option filled with nearest
        yield ("fill", f"{fill} where the data has none")
        voids = manifest.get("void_share")
        if voids:
            what = "filled from their rims" if fill == "interpolate" else f"given {fill}"
            yield ("voids", f"{100.0 * voids:.2f} % of the raster inside the data, {what}")
        for p in manifest["provenance"]:
            held = "remote" if p.get("bytes") is None else f"{p['bytes']:,d} bytes"
            yield ("input", f"{p['path']} ({held})")
    stored = [lv for lv in tree.levels if hasattr(lv, "exists")]
    if len(stored) < len(tree.levels):
        # a procedural planet's, or a large DEM's made as views reach it: nothing read here
        yield ("tiles", "statistics made as views reach them")
    for lv in stored:
        label = f"z{lv.z}"
        text = (
            f"{int(lv.exists.sum())} tiles, max error {float(lv.error[-1][lv.exists].max()):.2f} m"
        )
        if manifest is None:
            yield (label, text + " (finest grid)")
            continue
        ys, _ = np.nonzero(lv.exists)
        budget = level_budget(opts["error_texels"], tree.tile_size, lv.z, ys + lv.y0)
        err = lv.error[-1][lv.exists]
        over = int((err > budget * (1.0 + 1e-9)).sum())
        worst = int(np.argmax(err / np.maximum(budget, 1e-12)))
        if lv.z < tree.zmax:
            # a coarse tile over its level's budget is what the build refines: its children
            # are drawn where it would show more than the budget
            refined = f"{over} refined by finer tiles" if over else "none needs finer tiles"
            yield (label, f"{text}; {refined} (budget {float(budget.min()):.2f} m)")
            continue
        if not over:
            yield (label, f"{text}; every tile within its budget ({float(budget.min()):.2f} m)")
            continue
        res = float(manifest.get("resolution_merc", 0.0))
        grid = 2.0 * ORIGIN / (1 << lv.z) / TIN_GRID
        yield (
            label,
            text + f"; {over} over their budget (worst {err[worst]:.2f} m against "
            f"{budget[worst]:.2f} m)",
        )
        if grid <= res / 2.0:
            yield (
                "",
                "as expected: the finest grid is twice as fine as the data, and "
                "what is left is the data's own relief between its samples",
            )
