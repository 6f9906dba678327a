"""Selection, frame by frame, with no IO and no GPU (cesium-native's selection tests)."""

from __future__ import annotations

import numpy as np
import pytest

from _synthetic import AnalyticSource
from lodscape.geo.tiles import tile_id_array
from lodscape.lod._reference import select_reference
from lodscape.lod.camera import Camera
from lodscape.lod.select import Selection, SelectOptions, select
from lodscape.terrain.pyramid import TileTree, build_tree

OPTS = SelectOptions()


@pytest.fixture(scope="module")
def tree() -> TileTree:
    return build_tree(AnalyticSource())


CAMERAS = {
    "oblique-high": Camera(-84.25, 36.50, 4000.0, heading=10, pitch=-25),
    "oblique-low": Camera(-84.30, 36.55, 900.0, heading=60, pitch=-10),
    "down": Camera(-84.25, 36.6, 3000.0, pitch=-90),
    "far": Camera(-84.25, 36.0, 30000.0, heading=0, pitch=-30),
    "horizon": Camera(
        -84.35, 36.47, 1500.0, heading=45, pitch=0, fov_y=75, width=1920, height=1080
    ),
}


def _clip(cam: Camera) -> Camera:
    return cam.with_clip(max(cam.alt * 0.05, 1.0), 3e5)


def _tiles(sel: Selection) -> list[tuple[int, int, int, int]]:
    return sorted(
        zip(sel.z.tolist(), sel.x.tolist(), sel.y.tolist(), sel.grid.tolist(), strict=True)
    )


@pytest.mark.parametrize("name", CAMERAS)
def test_vectorised_equals_naive_reference(tree: TileTree, name: str) -> None:
    cam = _clip(CAMERAS[name])
    sel = select(OPTS, cam, tree)
    assert sel.count > 0
    assert _tiles(sel) == sorted(select_reference(OPTS, cam, tree))
    moved = cam.moved(alt=cam.alt * 0.8)
    again = select(OPTS, moved, tree, previous=sel)
    assert _tiles(again) == sorted(select_reference(OPTS, moved, tree, previous=sel))


@pytest.mark.parametrize("name", CAMERAS)
def test_pixel_rule_and_error_bound(tree: TileTree, name: str) -> None:
    cam = _clip(CAMERAS[name])
    sel = select(OPTS, cam, tree)
    ratio = sel.screen_px / sel.texture_size
    exempt = (sel.z == tree.zmax) | (sel.dist_near < cam.near)  # type: ignore[operator]
    assert np.all(ratio[~exempt] <= OPTS.split)
    # below the band only where the tree has no coarser level to merge into
    low = (ratio < OPTS.merge) & ~exempt
    assert np.all(sel.z[low] == tree.zmin), ratio[low]
    assert sel.max_sse <= OPTS.max_sse
    assert sel.stats()["max_sse_px"] <= OPTS.max_sse


def test_detail_grows_towards_the_camera(tree: TileTree) -> None:
    sel = select(OPTS, _clip(CAMERAS["oblique-low"]), tree)
    near = sel.dist_near < np.median(sel.dist_near)
    assert sel.z[near].mean() > sel.z[~near].mean()


def test_drawn_tiles_do_not_overlap(tree: TileTree) -> None:
    sel = select(OPTS, _clip(CAMERAS["oblique-high"]), tree)
    ids = set(tile_id_array(sel.z, sel.x, sel.y).tolist())
    for step in range(1, 8):
        anc = tile_id_array(sel.z - step, sel.x >> step, sel.y >> step)
        assert not (set(anc[sel.z - step >= tree.zmin].tolist()) & ids)


def test_a_tiny_move_keeps_the_selection(tree: TileTree) -> None:
    for cam in map(_clip, CAMERAS.values()):
        first = select(OPTS, cam, tree)
        nudged = cam.moved(lon=cam.lon + 1e-6, alt=cam.alt + 0.05, heading=cam.heading + 0.01)
        second = select(OPTS, nudged, tree, previous=first)
        assert np.array_equal(np.sort(first.keys), np.sort(second.keys))


def test_hysteresis_stops_flicker(tree: TileTree) -> None:
    """Between two cameras on either side of a split threshold the selection settles."""
    cam = _clip(CAMERAS["down"])
    # walk down until the selection changes: there a split threshold was crossed
    prev = select(OPTS, cam, tree)
    alt = cam.alt
    while True:
        alt *= 0.99
        nxt = select(OPTS, cam.moved(alt=alt), tree, previous=prev)
        if not np.array_equal(np.sort(nxt.keys), np.sort(prev.keys)):
            break
        prev = nxt
    above, below = cam.moved(alt=alt / 0.99), cam.moved(alt=alt)
    sel = nxt
    history = []
    for c in [above, below] * 4:
        sel = select(OPTS, c, tree, previous=sel)
        history.append(tuple(np.sort(sel.keys).tolist()))
    # having split, going back up by 1 % does not merge again: no flicker
    assert len(set(history)) == 1
    # without a previous frame the two cameras really differ (the test is not vacuous)
    assert not np.array_equal(np.sort(select(OPTS, above, tree).keys), np.sort(sel.keys))


def test_same_inputs_same_selection(tree: TileTree) -> None:
    cam = _clip(CAMERAS["horizon"])
    a, b = select(OPTS, cam, tree), select(OPTS, cam, tree)
    for f in ("z", "x", "y", "grid", "keys", "screen_px", "sse", "skirt"):
        assert np.array_equal(getattr(a, f), getattr(b, f))


def test_looking_at_the_sky_draws_nothing(tree: TileTree) -> None:
    sel = select(OPTS, _clip(Camera(-84.25, 36.6, 3000.0, pitch=80)), tree)
    assert sel.count == 0
    assert sel.culled > 0


def test_missing_tiles_fall_back_to_resident_ancestors(tree: TileTree) -> None:
    cam = _clip(CAMERAS["oblique-low"])
    wanted = select(OPTS, cam, tree)
    roots = select(SelectOptions(max_level=tree.zmin), cam, tree)
    resident = np.sort(roots.keys)
    sel = select(OPTS, cam, tree, resident=resident)
    # everything wanted and absent is requested, coarse levels first
    assert set(sel.loads.tolist()) == set(wanted.keys.tolist()) - set(resident.tolist())
    lz = (sel.loads >> np.uint64(3)) >> np.uint64(52)
    assert np.all(np.diff(lz.astype(np.int64)) >= 0)
    # no hole: each wanted tile is drawn or covered by a drawn ancestor
    drawn = set(tile_id_array(sel.z, sel.x, sel.y).tolist())
    for z, x, y in zip(wanted.z, wanted.x, wanted.y, strict=True):
        chain = {int(tile_id_array(z - s, x >> s, y >> s)) for s in range(0, z - tree.zmin + 1)}
        assert chain & drawn
    assert sel.fallback.max() > 0
    assert np.all(np.isin(sel.keys, resident))


def test_select_needs_clip_distances(tree: TileTree) -> None:
    with pytest.raises(ValueError, match="near/far"):
        select(OPTS, CAMERAS["down"], tree)


@pytest.mark.parametrize(
    ("kw", "msg"), [({"merge": 2.0}, "merge < split"), ({"max_sse": 0.0}, "max_sse")]
)
def test_bad_options(kw: dict[str, float], msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        SelectOptions(**kw)
