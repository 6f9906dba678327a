"""Patch visibility (paper 003): skip patches whose every triangle faces away from the camera.

One normal per patch would drop patches that are partly visible; each patch carries instead a
normal cone (the axis a and half-angle α that hold every one of its surface triangles' normals),
a bounding sphere (c, r) of its points and the lowest a·p over them. A patch faces away when
n·(e - p) < 0 for every normal n in the cone and point p of the patch, e the eye. Writing
n = a·cos φ + u·sin φ (u ⊥ a, φ <= α): n·(e - p) <= A·cos φ + B·sin φ with A = a·e - min a·p and
B = |(e - c)⊥a| + r; for A < 0 that grows with φ, so the patch faces away when A < 0 and
A·cos α + B·sin α < 0. The test is conservative (a patch passing it has no front-facing
triangle), so culling never removes a pixel; a tile's skirts go with its last patch.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from lodscape.geo.cones import CONE_SIZE, normal_cone, patch_cones

__all__ = ["CONE_SIZE", "backfacing", "normal_cone", "patch_cones"]

F64 = NDArray[np.float64]


def backfacing(cones: F64, centres: F64, eye: F64) -> NDArray[np.bool_]:
    """Which patches face away from ``eye`` (ECEF metres): ``cones`` (N, 10) as ``normal_cone``
    gives them (rows of NaN: no cone, never culled), ``centres`` (N, 3) their meshes' centres."""
    c = np.asarray(cones, dtype=np.float64)
    if c.size == 0:
        return np.zeros(0, dtype=bool)
    axis, cos_a, sin_a = c[:, :3], c[:, 3], c[:, 4]
    e = np.asarray(eye, np.float64) - np.asarray(centres, np.float64)
    big_a = np.einsum("ij,ij->i", axis, e) - c[:, 9]
    w = e - c[:, 5:8]
    perp = w - axis * np.einsum("ij,ij->i", axis, w)[:, None]
    big_b = np.linalg.norm(perp, axis=1) + c[:, 8]
    d = np.linalg.norm(w, axis=1)
    worst = big_a * cos_a + big_b * sin_a
    # a margin for the float32 vertices the GPU draws: a millionth of the distance, a millimetre
    margin = 1e-6 * d + 1e-3
    out: NDArray[np.bool_] = np.isfinite(worst) & (big_a < -margin) & (worst < -margin)
    return out
