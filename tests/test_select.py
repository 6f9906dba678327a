"""Selection, frame by frame, with no IO and no GPU (cesium-native's selection tests)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from _synthetic import AnalyticSource
from lodscape.geo.keys import tile_id_of_array
from lodscape.geo.tiles import tile_from_id_array, tile_id_array
from lodscape.lod._reference import select_reference
from lodscape.lod.camera import Camera
from lodscape.lod.select import (
    SLOPE_ROOM,
    Selection,
    SelectOptions,
    parts_vertical,
    select,
    tile_boxes,
    tile_far,
)
from lodscape.lod.view import TerrainView, follows
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
    # a small viewport: far siblings of split tiles fall under the band
    "small": Camera(-84.22, 36.72, 8000.0, heading=180, pitch=-23, width=320, height=240),
    "horizon": Camera(
        -84.35, 36.47, 1500.0, heading=45, pitch=0, fov_y=75, width=1920, height=1080
    ),
}


def _clip(cam: Camera) -> Camera:
    return cam.with_clip(max(cam.alt * 0.05, 1.0), 3e5)


def _tiles(sel: Selection) -> list[tuple[int, int, int, int, int]]:
    cols = (sel.z, sel.x, sel.y, sel.grid, sel.texture_up)
    return sorted(zip(*(c.tolist() for c in cols), strict=True))


@pytest.mark.parametrize("ladder", [False, True])
@pytest.mark.parametrize("hold", [False, True])
@pytest.mark.parametrize("name", CAMERAS)
def test_vectorised_equals_naive_reference(
    tree: TileTree, name: str, hold: bool, ladder: bool
) -> None:
    """On the tree's grids and on the TINs' ladder over it, whose rungs below its split rung
    cost as much as it where a tile can split (a tile that meets no rung splits, or is drawn
    at the split rung and held from it), all its rungs on the finest level."""
    from lodscape.terrain.tin_tiles import SPLIT_RUNG, ErrorLadder

    over = ErrorLadder(tree) if ladder else tree
    opts = SelectOptions(hold_parent_grid=hold)
    cam = _clip(CAMERAS[name])
    sel = select(opts, cam, over)
    assert sel.count > 0
    assert _tiles(sel) == sorted(select_reference(opts, cam, over))
    if ladder:
        assert np.all(sel.grid[sel.z < tree.zmax] <= SPLIT_RUNG)
    moved = cam.moved(alt=cam.alt * 0.8)
    again = select(opts, moved, over, previous=sel)
    assert _tiles(again) == sorted(select_reference(opts, moved, over, previous=sel))


def test_the_hysteresis_carries_between_the_frames_of_a_motion_not_across_a_cut(
    tree: TileTree,
) -> None:
    """A frame that follows the last (the eye moved a little, the view turned a little) is
    selected against it; a cut (a jump, a turn past half the field of view, another viewport
    or bound) as if it were the first: an unrelated picture is the same whatever was rendered
    before it."""
    opts = SelectOptions()
    carried = 0
    for cam in map(_clip, CAMERAS.values()):
        view = TerrainView(tree, opts)
        view.morph = False
        first = view.update(cam, np.zeros(0, np.uint64), blocking=True).selection
        nearest = float(first.dist_near.min())
        # backwards by a quarter of the distance to the nearest tile: the next frame
        step = cam.moved(alt=cam.alt + 0.25 * nearest)
        assert follows(cam, step, nearest)
        got = view.update(step, np.zeros(0, np.uint64), blocking=True).selection
        want = select(opts, step, tree, first)
        assert _tiles(got) == _tiles(want)
        carried += _tiles(want) != _tiles(select(opts, step, tree))
        # away by more than the nearest tile's distance, turned, or resized: a cut
        away = cam.moved(alt=cam.alt + 1.5 * nearest)
        turned = cam.moved(pitch=min(cam.pitch + 0.75 * cam.fov_y, 90.0))
        resized = replace(cam, width=cam.width // 2)
        for other in (away, turned, resized):
            assert not follows(step, other, float(got.dist_near.min()))
            view.update(step, np.zeros(0, np.uint64), blocking=True)
            cut = view.update(other, np.zeros(0, np.uint64), blocking=True).selection
            assert _tiles(cut) == _tiles(select(opts, other, tree))
    # the hysteresis did something on some camera (else this proves nothing)
    assert carried > 0


def test_a_split_holds_its_parents_grid_where_frames_geomorph(tree: TileTree) -> None:
    # a still picture has nothing to glide: its tiles take the coarsest grid their error
    # allows; frames that geomorph keep a split from coarsening the ground (no jump)
    held, free = [], []
    for morph in (True, False):
        view = TerrainView(tree)
        view.morph = morph
        for cam in map(_clip, CAMERAS.values()):
            got = view.update(cam, np.zeros(0, np.uint64), blocking=True).selection
            # unrelated cameras, each a cut: no hysteresis from the one before
            want = select(SelectOptions(hold_parent_grid=morph), cam, tree)
            assert _tiles(got) == _tiles(want)
            (held if morph else free).append(got.triangles)
    assert all(f <= h for f, h in zip(free, held, strict=True))
    assert sum(free) < sum(held), (free, held)
    # said outright, it holds whatever the frames do
    view = TerrainView(tree, SelectOptions(hold_parent_grid=True))
    view.morph = False
    cam = _clip(CAMERAS["oblique-low"])
    got = view.update(cam, np.zeros(0, np.uint64), blocking=True).selection
    assert _tiles(got) == _tiles(select(SelectOptions(hold_parent_grid=True), cam, tree))


@pytest.mark.parametrize("name", CAMERAS)
def test_pixel_rule_and_error_bound(tree: TileTree, name: str) -> None:
    cam = _clip(CAMERAS[name])
    sel = select(OPTS, cam, tree)
    ratio = sel.px_per_texel
    assert cam.near is not None
    # above the band only where the data has no finer level or the near plane cuts the tile
    exempt = (sel.z - sel.texture_up == tree.texture_zmax) | (sel.dist_near < cam.near)
    assert np.all(ratio[~exempt] <= OPTS.split)
    # below it only where the texture is already a root's: the data is small on screen
    low = ratio < OPTS.merge
    assert np.all(sel.z[low] - sel.texture_up[low] == tree.zmin), ratio[low]
    assert sel.magnified == int((~(ratio <= OPTS.split)).sum())
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
        # a tile on the frustum's edge may come into view or leave it (culling has no
        # hysteresis): compare what both cameras see
        a, b = _seen_by_both(first, cam, nudged, tree), _seen_by_both(second, cam, nudged, tree)
        assert np.array_equal(np.sort(first.keys[a]), np.sort(second.keys[b]))
        assert np.array_equal(np.sort(first.texture_keys[a]), np.sort(second.texture_keys[b]))


def _seen_by_both(sel: Selection, one: Camera, two: Camera, tree: TileTree) -> np.ndarray:
    seen = np.zeros(sel.count, bool)
    for z in np.unique(sel.z).tolist():
        m = sel.z == z
        st = tree.level(z).stats(sel.x[m], sel.y[m])
        seen[m] = tile_boxes(one, z, sel.x[m], sel.y[m], st.min_h, st.max_h).inside & (
            tile_boxes(two, z, sel.x[m], sel.y[m], st.min_h, st.max_h).inside
        )
    return seen


def test_tile_far_is_the_boxes_farthest_distance(tree: TileTree) -> None:
    """``tile_far`` (what fitting a far plane asks, with no clip distances) is ``tile_boxes``'
    ``dist_far``, and no corner of a box's lattice lies beyond it."""
    for cam in CAMERAS.values():
        for z in range(tree.zmin, tree.zmin + 3):
            n = 1 << (z - tree.zmin)
            x0, y0 = tree.roots()
            dx, dy = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(n)))
            x = (x0[:, None] * n + dx).ravel()
            y = (y0[:, None] * n + dy).ravel()
            st = tree.level(z).stats(x, y)
            x, y = x[st.exists], y[st.exists]
            st = tree.level(z).stats(x, y)
            far = tile_far(cam, z, x, y, st.min_h, st.max_h)
            boxes = tile_boxes(_clip(cam), z, x, y, st.min_h, st.max_h)
            assert np.array_equal(far, boxes.dist_far)
            assert np.all(far >= boxes.dist_near)


def test_a_box_large_on_screen_is_charged_in_parts_what_its_points_ask() -> None:
    """A tile filling the view is charged in parts (``parts_vertical``), per metre of height
    error, the most that a metre up moves the image of any of its points on screen (a bound),
    and not much more; the whole box's charge takes its nearest depth and its image's most
    stretched place from opposite ends of the view (about twice its points' here)."""
    from lodscape.geo.frames import ecef_to_geodetic, enu_basis, geodetic_to_ecef
    from lodscape.geo.tiles import bounds_array, merc_to_lonlat

    rng = np.random.default_rng(7)
    z, tx, ty = 13, 2177, 3197  # about 3.9 km a side at 36.7 N
    lo_h, hi_h = 300.0, 420.0
    left, bottom, right, top = (
        float(v[0]) for v in bounds_array(z, np.array([tx]), np.array([ty]))
    )
    parts_ratio, whole_ratio = [], []
    for _ in range(12):
        fx, fy = rng.uniform(0.3, 0.7, 2)
        lon, lat = (
            float(v)
            for v in merc_to_lonlat(left + fx * (right - left), bottom + fy * (top - bottom))
        )
        cam = Camera(
            lon, lat, hi_h + float(rng.uniform(300.0, 1500.0)), heading=float(rng.uniform(0, 360)),
            pitch=float(rng.uniform(-90.0, -35.0)), width=480, height=320,
        ).with_clip(10.0, 1e5)  # fmt: skip
        one = (np.array([tx]), np.array([ty]), np.array([lo_h]), np.array([hi_h]))
        whole = tile_boxes(cam, z, *one).vertical[0]
        ks, parts = parts_vertical(cam, z, *one)
        assert ks[0] > 1
        # points of the tile at any height in its range, those on screen
        n = 200_000
        mx = left + rng.uniform(0, 1, n) * (right - left)
        my = bottom + rng.uniform(0, 1, n) * (top - bottom)
        plon, plat = merc_to_lonlat(mx, my)
        p = geodetic_to_ecef(plon, plat, rng.uniform(lo_h, hi_h, n)) - cam.position
        q = p @ cam.rotation.T
        t = np.tan(np.radians(cam.fov_y) / 2)
        seen = (-q[:, 2] > cam.near) & (np.abs(q[:, 1] / -q[:, 2]) <= t)
        seen &= np.abs(q[:, 0] / -q[:, 2]) <= t * cam.aspect
        assert seen.sum() > 2000
        up = enu_basis(*ecef_to_geodetic(p[seen] + cam.position)[:2])[:, 2]

        def image(v: np.ndarray, cam: Camera = cam) -> np.ndarray:
            w = v @ cam.rotation.T
            out: np.ndarray = cam.scale * w[:, :2] / -w[:, 2:3]
            return out

        step = 1e-3
        moved = np.linalg.norm(image(p[seen] + step * up) - image(p[seen]), axis=1) / step
        assert moved.max() <= parts[0] * (1 + 1e-6)
        parts_ratio.append(moved.max() / parts[0])
        whole_ratio.append(moved.max() / whole)
    # the figures BENCHMARKS.md quotes (``pytest -s`` shows them)
    print(
        f"the largest a metre up moves a point: {min(parts_ratio):.2f}-{max(parts_ratio):.2f} "
        f"of the parts' charge, {min(whole_ratio):.2f}-{max(whole_ratio):.2f} of the whole box's"
    )
    assert np.median(parts_ratio) > 0.7, parts_ratio
    assert np.median(whole_ratio) < 0.6, whole_ratio


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
    resident = np.sort(np.concatenate([roots.keys, roots.texture_keys]))
    sel = select(OPTS, cam, tree, resident=resident)
    # everything wanted and absent is requested, coarse levels first
    want = set(wanted.keys.tolist()) | set(wanted.texture_keys.tolist())
    assert set(sel.loads.tolist()) == want - set(resident.tolist())
    lz = tile_id_of_array(sel.loads) >> np.uint64(52)
    assert np.all(np.diff(lz.astype(np.int64)) >= 0)
    # no hole: each wanted tile is drawn or covered by a drawn ancestor
    drawn = set(tile_id_array(sel.z, sel.x, sel.y).tolist())
    for z, x, y in zip(wanted.z, wanted.x, wanted.y, strict=True):
        chain = {int(tile_id_array(z - s, x >> s, y >> s)) for s in range(0, z - tree.zmin + 1)}
        assert chain & drawn
    assert sel.fallback.max() > 0
    assert np.all(np.isin(sel.keys, resident))
    assert np.all(np.isin(sel.texture_keys, resident))


def test_far_siblings_take_an_ancestors_texture(tree: TileTree) -> None:
    """A tile under the band (a far sibling of one that had to split) is textured from an
    ancestor, and the texture it gets is the one its ancestor's tile would have drawn."""
    found = False
    for cam in map(_clip, CAMERAS.values()):
        sel = select(OPTS, cam, tree)
        # tiles below the finest texture level borrow textures anyway: leave them out
        up = sel.texture_up > np.maximum(sel.z - tree.texture_zmax, 0)
        if not up.any():
            continue
        found = True
        tz, tx, ty = tile_from_id_array(tile_id_of_array(sel.texture_keys[up]))
        assert np.array_equal(tz, sel.z[up] - sel.texture_up[up])
        assert np.array_equal(tx, sel.x[up] >> sel.texture_up[up])
        assert np.array_equal(ty, sel.y[up] >> sel.texture_up[up])
        # taken up only while its texels stay within the band's top, less the slopes' room
        top = OPTS.split / SLOPE_ROOM
        assert np.all(sel.screen_px[up] * 2 <= top * sel.texture_size)
        assert np.all(sel.px_per_texel[up] <= top)
        assert np.all(sel.px_per_texel[up] > top / 2)
    assert found


def test_select_needs_clip_distances(tree: TileTree) -> None:
    with pytest.raises(ValueError, match="near/far"):
        select(OPTS, CAMERAS["down"], tree)


@pytest.mark.parametrize(
    ("kw", "msg"), [({"merge": 2.0}, "merge < split"), ({"max_sse": 0.0}, "max_sse")]
)
def test_bad_options(kw: dict[str, float], msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        SelectOptions(**kw)


def test_box_frames_kept_between_frames_are_the_ones_made_afresh() -> None:
    """What a tile's box is in its own frame is kept between selections: what comes back for
    tiles met before, met with another height range (a tree that learnt it), or new after the
    table was emptied (its bound) is what working it out afresh gives."""
    from lodscape.lod.select import _box_frames, _BoxFrames

    frames = _BoxFrames(limit=64)
    rng = np.random.default_rng(3)
    z = 12
    for _ in range(8):
        x = rng.integers(1000, 1012, 30).astype(np.int64)
        y = rng.integers(1500, 1512, 30).astype(np.int64)
        lo = rng.choice([0.0, 100.0], 30)
        hi = lo + rng.choice([500.0, 900.0], 30)
        got = frames.get(z, x, y, lo, hi)
        want = _box_frames(z, x, y, lo, hi)
        for a, b in zip(got, want, strict=True):
            np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-6)
    assert frames.get(z, x[:0], y[:0], lo[:0], hi[:0])[0].shape == (0, 3, 3)


def test_grid_hysteresis_holds_as_many_grids_as_the_tree_says(tree: TileTree) -> None:
    """A tile keeps last frame's grid while the one it needs is at most ``steps`` coarser:
    one regular grid, two of the TIN ladder's rungs (a fourth root of two apart: the factor
    of 1.41 one rung of eight gave); never a coarser one than it needs."""
    from lodscape.geo.keys import mesh_keys_zxy
    from lodscape.lod.select import _keep_finer_grid, _previous_grids, hysteresis_steps
    from lodscape.terrain.tin_tiles import LADDER, ErrorLadder

    z = np.full(5, 12)
    x = np.arange(100, 105)
    y = np.full(5, 200)
    ids = tile_id_array(z, x, y)
    before = _previous_grids(mesh_keys_zxy(z, x, y, np.array([3, 4, 5, 6, 2])))
    need = np.full(5, 3)
    assert _keep_finer_grid(ids, need, before, 1).tolist() == [3, 4, 3, 3, 3]
    assert _keep_finer_grid(ids, need, before, 2).tolist() == [3, 4, 5, 3, 3]
    assert hysteresis_steps(tree) == 1
    assert hysteresis_steps(ErrorLadder(tree)) == 2
    # two rungs hold a factor of about 1.41 wherever the ladder is dense (2 down to 0.25)
    dense = np.array([r for r in LADDER if r >= 0.25])
    held = dense[:-2] / dense[2:]
    assert np.all((held > 1.35) & (held < 1.45)), held
