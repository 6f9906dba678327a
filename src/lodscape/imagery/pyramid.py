"""Coarser imagery from finer: what a build makes its coarse levels' textures from, and what an
export makes the overviews above the stored levels from."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["halve_rgba"]


def halve_rgba(big: NDArray[np.floating]) -> NDArray[np.uint8]:
    """A (2n, 2n, 4) RGBA mosaic (0..255) halved to (n, n, 4): each texel the alpha-weighted
    mean colour of the four beneath it and their mean alpha; where all four are transparent
    their plain mean colour (the colour under alpha 0, a fill's tint, is kept)."""
    a = big[..., 3:4] / 255.0

    def quad(v: NDArray[np.floating]) -> NDArray[np.float64]:
        out: NDArray[np.float64] = v[0::2, 0::2] + v[1::2, 0::2] + v[0::2, 1::2] + v[1::2, 1::2]
        return out

    asum = quad(a)
    rgb = np.where(
        asum > 0.0, quad(big[..., :3] * a) / np.maximum(asum, 1e-12), quad(big[..., :3]) / 4.0
    )
    out = np.dstack([rgb, asum / 4.0 * 255.0])
    halved: NDArray[np.uint8] = np.floor(np.clip(out, 0.0, 255.0) + 0.5).astype(np.uint8)
    return halved
