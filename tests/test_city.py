"""The city from OSM attributes (paper 001): tags, geometry, the scene tree, and culling that
never changes the picture."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Polygon

import lodscape
from _synthetic import changed_share, run_cli, write_dem
from lodscape import Camera, SceneOptions
from lodscape.city.mesh import building_mesh
from lodscape.city.model import CityOptions, build_city
from lodscape.city.osm import Building, parse_length, parse_levels, read_osm
from lodscape.city.rtree import box_planes, pack
from lodscape.data import sample_city_path
from lodscape.errors import CityError


@pytest.mark.parametrize(
    ("text", "metres"),
    [
        ("12", 12.0),
        ("12.5 m", 12.5),
        ("12,5", 12.5),
        ("40 ft", 12.192),
        ("40'", 12.192),
        ("6'6\"", 1.9812),
        ("tall", None),
        ("-3", None),
        (None, None),
        ("1e9", None),
    ],
)
def test_lengths(text: str | None, metres: float | None) -> None:
    got = parse_length(text)
    assert (got is None) == (metres is None)
    if metres is not None:
        assert got == pytest.approx(metres, abs=1e-3)


def test_levels() -> None:
    assert parse_levels("3") == 3.0
    assert parse_levels("2;4") == 4.0
    assert parse_levels("3.5") == 3.5
    assert parse_levels("many") is None


def test_the_helsinki_extract() -> None:
    city = read_osm(sample_city_path())
    r = city.report()
    assert len(city.buildings) > 400
    assert city.multipolygons > 20
    assert city.holes > 20
    assert set(r["heights"]) == {"height", "levels", "default"}  # type: ignore[arg-type]
    kinds = Counter(f.kind for f in city.features)
    assert kinds["tree"] > 500
    assert kinds["street_lamp"] > 500
    assert kinds["bench"] > 100
    # relations whose rings do not close in the extract are counted, not raised
    assert sum(city.skipped.values()) >= 1
    for b in city.buildings:
        assert b.footprint.is_valid
        assert b.footprint.area > 0
        assert b.height > b.min_height >= 0.0
        assert 0.0 <= b.roof_height < b.height - b.min_height
    levels = [b for b in city.buildings if b.height_from == "levels"]
    assert levels
    assert all(b.height >= 3.0 for b in levels)


_OSM = """<?xml version='1.0' encoding='UTF-8'?>
<osm version="0.6" generator="test">
  <node id="1" lat="60.0000" lon="24.0000"/><node id="2" lat="60.0000" lon="24.0010"/>
  <node id="3" lat="60.0005" lon="24.0010"/><node id="4" lat="60.0005" lon="24.0000"/>
  <node id="5" lat="60.0010" lon="24.0000"/><node id="6" lat="60.0010" lon="24.0010"/>
  <node id="7" lat="60.0015" lon="24.0000"/><node id="8" lat="60.0015" lon="24.0010"/>
  <node id="9" lat="60.0020" lon="24.0000"/><node id="10" lat="60.0020" lon="24.0004"/>
  <node id="11" lat="60.0030" lon="24.0000"/><node id="12" lat="60.0030" lon="24.0020"/>
  <node id="13" lat="60.0040" lon="24.0020"/><node id="14" lat="60.0040" lon="24.0000"/>
  <node id="15" lat="60.0033" lon="24.0005"/><node id="16" lat="60.0033" lon="24.0015"/>
  <node id="17" lat="60.0037" lon="24.0015"/><node id="18" lat="60.0037" lon="24.0005"/>
  <node id="20" lat="60.001" lon="24.003"><tag k="natural" v="tree"/></node>
  <way id="100"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>
    <tag k="building" v="house"/><tag k="roof:shape" v="gabled"/>
    <tag k="building:levels" v="2"/></way>
  <way id="101"><nd ref="5"/><nd ref="8"/><nd ref="6"/><nd ref="7"/><nd ref="5"/>
    <tag k="building" v="yes"/><tag k="height" v="9 m"/></way>
  <way id="102"><nd ref="9"/><nd ref="10"/><nd ref="9"/><tag k="building" v="yes"/></way>
  <way id="103"><nd ref="11"/><nd ref="12"/><nd ref="13"/><nd ref="14"/><nd ref="11"/></way>
  <way id="104"><nd ref="15"/><nd ref="16"/><nd ref="17"/><nd ref="18"/><nd ref="15"/></way>
  <way id="105"><nd ref="1"/><nd ref="999"/><nd ref="3"/><nd ref="1"/>
    <tag k="building" v="yes"/></way>
  <relation id="200"><member type="way" ref="103" role="outer"/>
    <member type="way" ref="104" role="inner"/>
    <tag k="type" v="multipolygon"/><tag k="building" v="apartments"/>
    <tag k="roof:shape" v="onion"/></relation>
</osm>
"""


def test_what_a_city_file_lost_is_said_once(capsys: pytest.CaptureFixture[str]) -> None:
    """Objects an OSM file cannot make (a relation whose rings do not close in the extract, a
    missing node) are counted and said once on stderr, naming the file, when a scene opens it."""
    skipped = sum(read_osm(sample_city_path()).skipped.values())
    assert skipped >= 1
    capsys.readouterr()
    with lodscape.open("flat", city=str(sample_city_path())):
        pass
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert str(sample_city_path().name) in lines[0]
    assert f": {skipped} OSM objects skipped (" in lines[0]


def test_broken_footprints_are_repaired_or_skipped(tmp_path: Path) -> None:
    p = tmp_path / "small.osm"
    p.write_text(_OSM)
    city = read_osm(p)
    ids = {b.osm_id.split(".")[0] for b in city.buildings}
    # the bow-tie (101) is repaired into two triangles, the multipolygon keeps its hole
    assert city.repaired == 1
    assert {"w100", "w101", "r200"} <= ids
    mp = [b for b in city.buildings if b.osm_id == "r200"]
    assert len(mp) == 1
    assert len(mp[0].footprint.interiors) == 1
    assert mp[0].kind == "apartments"
    assert mp[0].roof_shape == "flat"
    assert city.other_roofs["onion"] == 1
    house = next(b for b in city.buildings if b.osm_id == "w100")
    assert house.roof_shape == "gabled"
    assert house.height_from == "levels"
    assert house.height == pytest.approx(6.0 + house.roof_height)
    # the two-node way and the way with a missing node are not buildings
    assert "w102" not in ids
    assert "w105" not in ids
    assert [f.kind for f in city.features] == ["tree"]


@pytest.mark.parametrize("content", [b"", b"garbage" * 10, b"<osm><node"])
def test_unreadable_files_fail_in_one_line(tmp_path: Path, content: bytes) -> None:
    p = tmp_path / "bad.osm.pbf"
    p.write_bytes(content)
    with pytest.raises(CityError, match=r"bad\.osm\.pbf"):
        read_osm(p)
    with pytest.raises(CityError, match="no such file"):
        read_osm(tmp_path / "missing.osm.pbf")


@pytest.mark.parametrize("shape", ["flat", "gabled", "hipped", "pyramidal"])
def test_buildings_are_closed_and_as_tall_as_tagged(shape: str) -> None:
    poly = Polygon(
        [(0, 0), (24, 0), (24, 10), (12, 16), (0, 10)], [[(4, 3), (8, 3), (8, 6), (4, 6)]]
    )
    b = Building(
        "t",
        poly,
        14.0,
        2.0,
        shape,
        0.0 if shape == "flat" else 4.0,
        "yes",
        "brick",
        "tiles",
        "height",
    )
    parts = building_mesh(b, poly, 100.0)
    pos = np.concatenate([g.positions for g in parts.values()]).astype(np.float64)
    tri = []
    off = 0
    for g in parts.values():
        tri.append(g.triangles.astype(np.int64) + off)
        off += len(g.positions)
    t = np.concatenate(tri)
    assert pos[:, 2].max() == pytest.approx(114.0, abs=1e-3)
    assert pos[:, 2].min() == pytest.approx(102.0, abs=1e-3)
    # weld vertices and count each edge's triangles: all twice but the open bottom rings
    key = np.round(pos, 4)
    _, ids = np.unique(key, axis=0, return_inverse=True)
    e = np.sort(np.concatenate([ids[t][:, [0, 1]], ids[t][:, [1, 2]], ids[t][:, [2, 0]]]), axis=1)
    edges, counts = np.unique(e, axis=0, return_counts=True)
    once = edges[counts == 1]
    z = np.round(pos[:, 2], 4)
    zs = {float(z[np.nonzero(ids == i)[0][0]]) for i in once.ravel()}
    assert zs == {102.0}, f"open edges above the bottom: {zs}"
    assert (counts <= 2).all()


def test_wall_texture_runs_round_the_ring_and_up_from_the_base() -> None:
    poly = Polygon([(0, 0), (20, 0), (20, 10), (0, 10)])
    b = Building("t", poly, 12.0, 3.0, "flat", 0.0, "yes", "brick", "roofing", "height")
    walls = building_mesh(b, poly, 50.0)["brick"]
    pos, uv = walls.positions.astype(np.float64), walls.uvs.astype(np.float64)
    # v is metres above the walls' base (so windows sit on the storeys), u metres along them
    np.testing.assert_allclose(uv[:, 1], pos[:, 2] - 53.0, atol=1e-4)
    assert uv[:, 0].min() == pytest.approx(0.0)
    assert uv[:, 0].max() == pytest.approx(60.0, abs=1e-3)  # the perimeter
    # along each wall, u grows as fast as the distance: the texture is not stretched
    tri = walls.triangles.astype(np.int64)
    for a, c in ((0, 1), (1, 2), (2, 0)):
        d3 = np.linalg.norm(pos[tri[:, a], :2] - pos[tri[:, c], :2], axis=1)
        du = np.abs(uv[tri[:, a], 0] - uv[tri[:, c], 0])
        np.testing.assert_allclose(du, d3, atol=1e-3)


def test_materials_are_distinct_tileable_layers() -> None:
    from lodscape.city.materials import MATERIALS, layers

    names = sorted(MATERIALS)
    tex = layers(names).astype(np.float64) / 255.0
    assert tex.shape == (len(names), 128, 128, 4)
    flat = tex[..., :3].reshape(len(names), -1)
    # no two materials share a texture
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            assert np.abs(flat[i] - flat[j]).mean() > 0.02, (names[i], names[j])
    # each repeats without a seam: the jump across an edge is like the jump inside
    for i, name in enumerate(names):
        t = tex[i, ..., :3]
        inner = np.abs(np.diff(t, axis=1)).mean()
        seam = np.abs(t[:, 0] - t[:, -1]).mean()
        assert seam <= 3 * inner + 0.02, name
    # facades have windows: dark, bluish glass over a fifth or so of the wall
    t = tex[names.index("plaster"), ..., :3]
    glass = (t.sum(axis=2) < 0.9) & (t[..., 2] > t[..., 0])
    assert 0.1 < glass.mean() < 0.4


@pytest.mark.parametrize("packing", ["str", "hilbert", "priority"])
def test_rtree_leaves_are_compact(packing: str) -> None:
    """Over evenly spread objects the leaves' boxes tile the ground with little overlap (a leaf
    cut across two STR slabs would span the whole city)."""
    rng = np.random.default_rng(1)
    for n in (1000, 12_901):
        c = rng.uniform(0, 1000, (n, 3))
        tree = pack(np.concatenate([c - 2, c + 2], 1), packing=packing)
        leaf = tree.levels[0]
        area = float(np.prod(leaf[:, 3:5] - leaf[:, :2], axis=1).sum())
        assert area < 1.45e6, (n, area)


@pytest.mark.parametrize("packing", ["str", "hilbert", "priority"])
def test_rtree_cull_equals_testing_every_leaf(packing: str) -> None:
    rng = np.random.default_rng(3)
    c = rng.uniform(0, 2000, (3000, 3))
    boxes = np.concatenate(
        [c - rng.uniform(1, 20, (3000, 3)), c + rng.uniform(1, 20, (3000, 3))], 1
    )
    tree = pack(boxes, packing=packing)
    assert sorted(tree.order.tolist()) == list(range(3000))
    for _ in range(20):
        cam = Camera(
            0.0, 0.0, 10.0, heading=float(rng.uniform(0, 360)), pitch=float(rng.uniform(-60, 10))
        )
        cam = cam.with_clip(1.0, float(rng.uniform(200, 3000)))
        planes = cam.frustum_planes()
        eye = rng.uniform(0, 2000, 3)
        planes = np.concatenate([planes[:, :3], (planes[:, 3] - planes[:, :3] @ eye)[:, None]], 1)
        vis, tested = tree.cull(planes)
        brute = box_planes(tree.levels[0], planes) >= 0
        assert np.array_equal(vis, brute)
        assert tested <= sum(len(level) for level in tree.levels)


@pytest.mark.parametrize("packing", ["str", "hilbert", "priority"])
def test_rtree_nodes_hold_their_children(packing: str) -> None:
    """Every node's box holds its children's (its objects' for a leaf), every object is in one
    leaf, and no node has more children than the fanout (a leaf than its size): over compact
    boxes mixed with long thin ones (roads, rails) and a cluster of equal boxes."""
    rng = np.random.default_rng(5)
    c = rng.uniform(0, 5000, (4000, 3))
    half = rng.uniform(1, 15, (4000, 3))
    half[:300, 0] = rng.uniform(500, 2500, 300)  # long east-west
    half[300:600, 1] = rng.uniform(500, 2500, 300)  # long north-south
    c[600:900] = 1234.0  # one spot, many objects
    boxes = np.concatenate([c - half, c + half], 1)
    tree = pack(boxes, leaf=16, fanout=8, packing=packing)
    assert sorted(tree.order.tolist()) == list(range(len(boxes)))
    runs = np.diff(tree.leaf_start)
    assert runs.min() >= 1
    assert runs.max() <= 16
    leaf_of = np.repeat(np.arange(tree.leaves), runs)
    obj = boxes[tree.order]
    own = tree.levels[0][leaf_of]
    assert (own[:, :3] <= obj[:, :3]).all()
    assert (own[:, 3:] >= obj[:, 3:]).all()
    assert len(tree.levels[-1]) == 1
    assert len(tree.starts) == len(tree.levels) - 1
    for k, s in enumerate(tree.starts):
        n = np.diff(s)
        assert s[0] == 0
        assert s[-1] == len(tree.levels[k])
        assert n.min() >= 1
        assert n.max() <= 8
        parent = tree.parent(np.arange(len(tree.levels[k])), k)
        up = tree.levels[k + 1][parent]
        assert (up[:, :3] <= tree.levels[k][:, :3]).all()
        assert (up[:, 3:] >= tree.levels[k][:, 3:]).all()


@pytest.fixture(scope="module")
def city_scene():  # type: ignore[no-untyped-def]
    city = read_osm(sample_city_path())
    w, s, e, n = city.bounds
    # anisotropic filtering on llvmpipe stalls for minutes on a grazing, magnified ground texture
    scene = lodscape.open(
        f"flat:{w - 0.01},{s - 0.005},{e + 0.01},{n + 0.005}", SceneOptions(anisotropy=1.0)
    )
    scene.add_city(build_city(city, scene.heights))
    yield scene
    scene.close()


VIEWS = {
    "street": dict(lon=24.9425, lat=60.1675, alt=25.0, heading=60.0, pitch=-5.0),
    "oblique": dict(lon=24.944, lat=60.160, alt=300.0, heading=10.0, pitch=-25.0),
    "down": dict(lon=24.945, lat=60.170, alt=800.0, heading=0.0, pitch=-89.0),
}


@pytest.mark.gl
@pytest.mark.parametrize("view", VIEWS)
def test_optimised_city_draws_the_naive_picture(city_scene, view: str) -> None:  # type: ignore[no-untyped-def]
    cam = Camera(**VIEWS[view], width=320, height=180)  # type: ignore[arg-type]
    # a short turn: occlusion culling learns from the frames before (coherence)
    turn = [cam.moved(heading=cam.heading + 1.5 * i) for i in range(-4, 1)]
    pictures: dict[str, list[np.ndarray]] = {}
    stats = {}
    for name, opts in {
        "naive": CityOptions.naive(),
        "defaults": CityOptions(),
        "defaults with occlusion": CityOptions(occlusion=True),
        # every leaf asked every frame, so the two query schemes see the same history
        "culled": CityOptions(lod=False, occlusion=True, revisit=1, query_min_triangles=0),
        "leaf queries": CityOptions(
            lod=False, occlusion=True, hierarchical=False, revisit=1, query_min_triangles=0
        ),
        "no-occlusion": CityOptions(lod=False, occlusion=False),
    }.items():
        city_scene.set_city_options(opts)
        pictures[name] = [city_scene.render(c)[0] for c in turn]
        stats[name] = city_scene.last.city
    # occlusion culling never changes the picture, in any frame of the turn (levels of detail
    # do: the defaults with occlusion culling are compared with the defaults)
    for name, ref in (
        ("defaults with occlusion", "defaults"),
        ("culled", "naive"),
        ("leaf queries", "naive"),
        ("no-occlusion", "naive"),
    ):
        for i, (a, b) in enumerate(zip(pictures[name], pictures[ref], strict=True)):
            diff = np.any(a != b, axis=2)
            assert diff.mean() < 0.002, (name, i, diff.sum())
    pictures = {k: v[-1] for k, v in pictures.items()}  # type: ignore[misc]
    # the city is in the picture, its walls textured: windows' dark glass shows
    assert stats["naive"]["city_triangles"] > 0
    rgb = pictures["naive"].astype(np.int16)
    glass = (rgb.sum(axis=2) < 240) & (rgb[..., 2] > rgb[..., 0] + 8)
    assert glass.mean() > 0.002, glass.mean()
    for name in ("culled", "leaf queries", "no-occlusion"):
        assert stats[name]["city_triangles"] <= stats["naive"]["city_triangles"]
        assert stats[name]["city_draw_calls"] < stats["naive"]["city_draw_calls"]
    # a parent's box holds its leaves': asking it first hides exactly what the leaves would
    assert (
        stats["culled"]["city_culled_occlusion"] == stats["leaf queries"]["city_culled_occlusion"]
    )
    if view == "street":
        # hidden parents are asked as one: fewer queries
        assert stats["culled"]["city_node_queries"] > 0
        assert stats["culled"]["city_queries"] < stats["leaf queries"]["city_queries"]
        assert stats["culled"]["city_culled_occlusion"] > 100
        assert stats["culled"]["city_triangles"] < stats["no-occlusion"]["city_triangles"]


@pytest.mark.gl
def test_cli_renders_a_city_on_flat_ground(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "city.png"
    argv = ["render", "flat", "--city", str(sample_city_path()), "-o", str(out)]
    code, _, err = run_cli([*argv, "--size", "320x180", "-q"], capsys)
    assert code == 0, err
    # over the middle of the extract, with and without the city
    view = ["--lon", "24.9405", "--lat", "60.169", "--alt", "150", "--pitch", "-25"]
    view += ["--size", "320x180", "-q"]
    ground = write_dem(
        str(tmp_path / "flat.tif"),
        np.full((64, 64), 10.0, np.float32),
        crs="EPSG:4326",
        west=24.925,
        north=60.18,
        res=0.0005,
    )
    near, bare = tmp_path / "near.png", tmp_path / "bare.png"
    city = ["--city", str(sample_city_path())]
    code, _, err = run_cli(["render", ground, *city, "-o", str(near), *view], capsys)
    assert code == 0, err
    code, _, err = run_cli(["render", ground, "-o", str(bare), *view], capsys)
    assert code == 0, err
    # roofs and walls stand where the bare ground was: a good part of the picture changes
    assert changed_share(near, bare) > 0.1
    bad = tmp_path / "bad.osm.pbf"
    bad.write_bytes(b"nope")
    code, _, err = run_cli(
        ["render", "flat", "--city", str(bad), "-o", str(tmp_path / "x.png")], capsys
    )
    assert code == 2
    assert "bad.osm.pbf" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_auto_occlusion_is_on_among_the_walls_of_a_software_rasteriser() -> None:
    auto = CityOptions()
    assert auto.occlusion == "auto"
    assert auto.resolved(software=True, height=2.0).occlusion is True
    assert auto.resolved(software=True, height=25.0).occlusion is False
    assert auto.resolved(software=False, height=2.0).occlusion is False
    assert auto.resolved(software=True, height=None).occlusion is False  # no ground known
    assert CityOptions(occlusion=True).resolved(False, 400.0).occlusion is True
    assert not CityOptions.naive().resolved(True, 2.0).occlusion


@pytest.mark.gl
def test_the_scene_trees_packing_and_the_buffers_from_the_cli_and_python(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    view = ["--lon", "24.9405", "--lat", "60.169", "--alt", "150", "--pitch", "-25"]
    view += ["--size", "320x180", "-q", "--city", str(sample_city_path())]
    pictures = {}
    for tree in ("hilbert", "priority"):
        pictures[tree] = tmp_path / f"{tree}.png"
        argv = ["render", "flat", "--city-tree", tree, "-o", str(pictures[tree]), *view]
        code, _, err = run_cli(argv, capsys)
        assert code == 0, err
    # the buffers draw the same picture from the command line too
    pictures["buffers"] = tmp_path / "buffers.png"
    argv = ["render", "flat", "--city-buffers", "-o", str(pictures["buffers"]), *view]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    assert changed_share(pictures["hilbert"], pictures["buffers"]) == 0.0
    # the packing changes which boxes are tested, not what the city looks like (the levels of
    # detail go by leaves, so a few far objects may differ)
    assert changed_share(pictures["hilbert"], pictures["priority"]) < 0.02
    out = tmp_path / "x.png"
    code, _, err = run_cli(["render", "flat", "--city-tree", "kd", "-o", str(out), *view], capsys)
    assert code == 2
    assert "--city-tree" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()
    city = read_osm(sample_city_path())
    w, s, e, n = city.bounds
    with lodscape.open(f"flat:{w},{s},{e},{n}") as scene:
        model = scene.add_city(city, CityOptions(packing="priority"))
        assert model.tree.packing == "priority"
        assert scene.city_options.packing == "priority"


@pytest.mark.gl
def test_uniform_and_storage_buffers_draw_the_same_city() -> None:
    """The camera in a uniform buffer and the instances in a storage buffer (read by the draw's
    base instance) draw exactly what plain uniforms and instanced attributes draw: buildings
    from above, and trees seen from 30 m."""
    city = read_osm(sample_city_path())
    w, s, e, n = city.bounds
    with lodscape.open(f"flat:{w - 0.01},{s - 0.005},{e + 0.01},{n + 0.005}") as scene:
        scene.add_city(city)
        pictures = {}
        for buffers in (True, False):
            scene.set_city_options(CityOptions(buffers=buffers, occlusion=True))
            for cam in (scene.city_camera(240, 160), _street_camera(scene)):
                rgb, depth = scene.render(cam)
                rgb, depth = scene.render(cam)  # the occlusion queries settled
                assert scene._city_pass is not None
                assert scene._city_pass.buffers is buffers
                pictures[(buffers, cam.alt)] = (rgb, depth, scene.last.city["city_triangles"])
        for alt in {a for _, a in pictures}:
            a, b = pictures[(True, alt)], pictures[(False, alt)]
            assert np.array_equal(a[0], b[0])
            assert np.array_equal(a[1], b[1])
            assert a[2] == b[2] > 0


def _street_camera(scene: lodscape.Scene) -> Camera:
    """Looking down on trees in the middle of the sample (instances far from the first: the
    storage buffer is read at the draw's base instance)."""
    from lodscape.geo.frames import ecef_to_geodetic

    model = scene.city
    assert model is not None
    trees = model.instances["tree"]
    x, y, z = (float(v) for v in trees[len(trees) // 2, :3])
    ecef = model.frame.origin + np.array([x, y - 30.0, z]) @ model.frame.basis
    lon, lat, _ = (float(v) for v in ecef_to_geodetic(ecef))
    return Camera(lon, lat, z + 30.0, heading=0.0, pitch=-45.0, width=240, height=160)
