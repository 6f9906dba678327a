"""``patch_cones`` (all patches at once, the meshes' path) against ``normal_cone`` (one patch,
written plainly): the same cone and sphere for every patch, one patch or many, with
degenerate triangles and with patches whose normals span a half-space."""

from __future__ import annotations

import numpy as np
import pytest

from lodscape.geo.cones import CONE_SIZE, normal_cone, patch_cones


def _height_field(rng: np.random.Generator, n: int, rough: float) -> np.ndarray:
    v, u = np.mgrid[0:n, 0:n].astype(np.float64)
    h = rough * rng.normal(size=(n, n))
    return np.column_stack([u.ravel() * 10.0, v.ravel() * 10.0, h.ravel()])


@pytest.mark.parametrize("patches", [1, 4, 9])
@pytest.mark.parametrize("rough", [0.0, 2.0, 40.0])
def test_patch_cones_are_each_patchs_normal_cone(patches: int, rough: float) -> None:
    rng = np.random.default_rng(patches * 7 + int(rough))
    n = 13
    verts = _height_field(rng, n, rough)
    # random triangles of neighbouring points (a few degenerate: two corners the same)
    base = rng.integers(0, n - 1, size=(patches, 40, 2))
    corner = base[..., 1] * n + base[..., 0]
    tri = np.stack([corner, corner + 1, corner + n], axis=-1)
    tri[:, :3, 2] = tri[:, :3, 1]
    up = np.array([0.0, 0.0, 1.0])
    got = patch_cones(verts, tri, up)
    assert got.shape == (patches, CONE_SIZE)
    for p in range(patches):
        want = normal_cone(verts, tri[p], up)
        if want is None:
            assert np.isnan(got[p]).all()
        else:
            np.testing.assert_allclose(got[p], want, rtol=1e-9, atol=1e-9)
    if rough == 0.0:  # flat ground: every cone is the vertical, half-angle 0
        np.testing.assert_allclose(got[:, :5], [[0, 0, 1, 1, 0]] * patches, atol=1e-12)
    if rough == 40.0:  # normals spanning a half-space: no cone
        assert np.isnan(got).all()


def test_a_patch_of_degenerate_triangles_has_no_cone() -> None:
    verts = np.zeros((4, 3))
    tri = np.array([[[0, 1, 2], [1, 2, 3]], [[0, 0, 0], [3, 3, 3]]])
    assert np.isnan(patch_cones(verts, tri, np.array([0.0, 0.0, 1.0]))).all()
    assert normal_cone(verts, tri[0], np.array([0.0, 0.0, 1.0])) is None
