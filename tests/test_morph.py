"""Geomorphing (CDLOD-style: the CPU terrain mode's vertex shader, the GPU mode's tessellation
evaluation shader): along a slow approach,
what the camera sees of the ground moves continuously. Each frame's depth is reprojected into
the next camera: where the surface itself did not move the two agree, and the disagreement, in
pixels of the surface's displacement, is what popped. With morphing no frame pops by more than a
pixel; without it, the frames where tiles split do."""

from __future__ import annotations

import math

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, reprojected_jump, write_dem
from lodscape import Camera, SceneOptions
from lodscape.geo.frames import WGS84_A
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.terrain.mesh import build_mesh

pytestmark = pytest.mark.gl


def test_morph_offsets_lead_onto_the_coarser_grid() -> None:
    """A mesh moved by its offsets is the grid of half the segments: its even vertices stay,
    the others land on the coarse edges and diagonals (north-west to south-east)."""
    h = np.asarray(fbm_heights(33, seed=4, relief=300.0), np.float64)
    fine = build_mesh(1, 14, 8000, 6000, h)
    assert fine.morph is not None
    moved = fine.vertices[:, :3].astype(np.float64) + fine.morph
    g = moved[: 33 * 33].reshape(33, 33, 3)
    # every moved vertex lies on the coarse grid's (even vertices') triangles
    assert np.allclose(g[::2, ::2], fine.vertices[: 33 * 33, :3].reshape(33, 33, 3)[::2, ::2])
    assert np.allclose(g[1::2, ::2], (g[:-1:2, ::2] + g[2::2, ::2]) / 2, atol=1e-3)
    assert np.allclose(g[1::2, 1::2], (g[:-1:2, :-1:2] + g[2::2, 2::2]) / 2, atol=1e-3)
    # the skirts follow their ring
    assert np.abs(fine.morph).max() > 1.0
    # a terrain-adaptive mesh (its own diagonals) is not morphed
    assert build_mesh(1, 14, 8000, 6000, h, adaptive=True).morph is None


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("morph") / "dem.tif"
    return write_dem(
        str(path),
        fbm_heights(513, seed=9, relief=500.0),
        crs="EPSG:32617",
        west=500_000.0,
        north=4_000_000.0,
        res=10.0,
    )


def _approach(dem: str, morph: bool, terrain_mode: str = "cpu") -> list[float]:
    """Per pair of consecutive frames of an approach, the 99.9th percentile of the reprojected
    jump (px). Frames load every tile they draw (no streaming: the same tiles on any machine),
    and morph as a flight's do."""
    from lodscape.lod.select import SelectOptions

    # a coarse bound (8 px) makes each split's step plain to see
    opts = SceneOptions(
        select=SelectOptions(max_sse=8.0),
        morph=morph,
        anisotropy=1.0,
        terrain_mode=terrain_mode,
        meshes="grid",  # the meshes that morph (a picture's TINs do not)
    )
    jumps: list[float] = []
    with lodscape.open(dem, opts) as scene:
        scene.view.morph = morph  # as a streaming scene's view does (one-shot scenes do not)
        # from south of the DEM (0.75 of its width back, 0.55 up), straight at its middle,
        # 1 % nearer each frame
        b = scene.provider.bounds_merc
        (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
        lon0, lat0 = (w + e) / 2.0, (s + n) / 2.0
        extent = (b.right - b.left) * math.cos(math.radians(lat0))
        cam0 = Camera(
            lon0, lat0 - math.degrees(0.75 * extent / WGS84_A),
            scene.tree.height_range[1] + 0.55 * extent, pitch=-35.0, width=256, height=160,
        )  # fmt: skip
        target = cam0.position + cam0.forward * 6000.0
        prev = None
        for i in range(36):
            f = 1.0 - 0.01 * i
            p = target + (cam0.position - target) * f
            from lodscape.geo.frames import ecef_to_geodetic

            lon, lat, alt = (float(a) for a in ecef_to_geodetic(p))
            cam = cam0.moved(lon=lon, lat=lat, alt=alt)
            _, depth = scene.render(cam)
            if scene.terrain_mode_note is not None:
                pytest.skip(scene.terrain_mode_note)
            fitted = scene.prepare(cam)
            if prev is not None:
                jump = reprojected_jump(prev[0], prev[1], depth, fitted)
                # edges of the ground against the sky and what hills uncover: not the ground
                # moving; the 99.5th percentile stands above those few pixels
                jumps.append(float(np.nanpercentile(jump, 99.9)))
            prev = (depth, fitted)
    return jumps


@pytest.mark.parametrize("terrain_mode", ["cpu", "gpu"])
def test_a_slow_approach_never_pops_with_morphing(dem: str, terrain_mode: str) -> None:
    """Both terrain modes: the CPU mode's grids move by their offsets, the GPU mode's
    tessellation evaluation blends a tile's heights with its grid of half the cells."""
    with_morph = _approach(dem, True, terrain_mode)
    without = _approach(dem, False, terrain_mode)
    # without morphing, where tiles split under the camera the ground jumps by over a pixel
    assert max(without) > 1.0, without
    # with it no frame moves the ground by a pixel (the floor, ~0.2-0.4 px, is the
    # reprojection's own: sub-pixel sampling of slopes)
    assert max(with_morph) < 1.0, with_morph
    assert max(with_morph) < 0.6 * max(without), (with_morph, without)


def test_a_split_takes_on_its_parents_glide() -> None:
    """Where a tile gliding onto its grid splits, its children drawn one grid coarser (their
    grid is the parent's, their half grid the parent's coarser one) take on where the glide
    was; a child at the parent's own grid starts at its half grid (the parent's surface)."""
    from types import SimpleNamespace

    from _synthetic import AnalyticSource
    from lodscape.lod.view import TerrainView
    from lodscape.terrain.pyramid import build_tree

    view = TerrainView(build_tree(AnalyticSource()))
    view.morph_frames = 10

    def frame(z: list[int], x: list[int], y: list[int], grid: list[int]) -> np.ndarray:
        sel = SimpleNamespace(
            z=np.array(z), x=np.array(x), y=np.array(y), grid=np.array(grid), count=len(z)
        )
        return view._morphs(sel)  # type: ignore[arg-type]

    # a parent (12, 100, 200) that refined its grid 0 -> 1 two frames ago, still gliding
    assert frame([12], [100], [200], [0]).tolist() == [0.0]
    assert frame([12], [100], [200], [1]).tolist() == [0.9]
    assert np.allclose(frame([12], [100], [200], [1]), [0.8])
    # it splits: three children one grid coarser, one at its grid
    got = frame([13, 13, 13, 13], [200, 201, 200, 201], [400, 400, 401, 401], [0, 0, 1, 0])
    assert np.allclose(got, [0.7, 0.7, 0.9, 0.7])
