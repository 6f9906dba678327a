"""Ground from a land-cover mask (paper 001): OSM land use, natural areas and roads rasterised
per tile, coloured from ground materials in the shader; less memory than pre-baked imagery."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import shapely

import lodscape
from _synthetic import changed_share, run_cli
from lodscape import Camera, SceneOptions
from lodscape.errors import SourceError
from lodscape.geo.keys import is_texture
from lodscape.geo.tiles import tile, xy_bounds
from lodscape.imagery.landcover import CLASSES, Landcover, classify, read_landcover


def _sample() -> Path:
    from lodscape.data import sample_city_path

    return sample_city_path()


def test_tags_classify() -> None:
    assert classify({"landuse": "forest"}) == "forest"
    assert classify({"natural": "wood"}) == "forest"
    assert classify({"leisure": "park"}) == "grass"
    assert classify({"natural": "water", "water": "lake"}) == "water"
    assert classify({"water": "pond"}) == "water"
    assert classify({"amenity": "parking"}) == "paved"
    assert classify({"building": "yes"}) is None
    assert classify({}) is None


def test_the_helsinki_extract_is_rasterised_where_it_lies() -> None:
    lc = read_landcover(_sample())
    assert lc.counts["road"] > 500
    assert lc.counts["grass"] > 50
    assert lc.counts["water"] > 0
    # painting order: classes rise, and a shape's texels carry its class
    values = [v for _, v in lc.shapes]
    assert values == sorted(values)
    t = tile(24.944, 60.170, 16)
    mask = lc.mask(t.z, t.x, t.y, 256)
    assert mask.shape == (256, 256)
    assert mask.dtype == np.uint8
    found = {CLASSES[v] for v in np.unique(mask)}
    assert {"road", "paved", "ground"} <= found
    # every road texel's centre lies in some road shape (a texel of slack at the edges)
    b = xy_bounds(t)
    res = (b.right - b.left) / 256
    roads = shapely.union_all([g for g, v in lc.shapes if v == CLASSES.index("road")])
    rows, cols = np.nonzero(mask == CLASSES.index("road"))
    pick = np.random.default_rng(0).choice(len(rows), 200, replace=False)
    pts = shapely.points(b.left + (cols[pick] + 0.5) * res, b.top - (rows[pick] + 0.5) * res)
    assert np.all(shapely.distance(roads, pts) <= 1.5 * res)
    # and a point in a mapped park, away from anything painted over it, is grass
    grass = CLASSES.index("grass")
    park = next(g for g, v in lc.shapes if v == grass and g.area > 5e3)
    over = shapely.union_all([g for g, v in lc.shapes if v > grass]).buffer(3.0)
    p = park.difference(over).buffer(-2.0).representative_point()
    assert not p.is_empty
    tp = tile(*_lonlat(p.x, p.y), 17)
    m = lc.mask(tp.z, tp.x, tp.y, 256)
    bb = xy_bounds(tp)
    col = int((p.x - bb.left) / (bb.right - bb.left) * 256)
    row = int((bb.top - p.y) / (bb.top - bb.bottom) * 256)
    assert CLASSES[m[row, col]] == "grass"


def _lonlat(xm: float, ym: float) -> tuple[float, float]:
    from lodscape.geo.tiles import merc_to_lonlat

    lon, lat = merc_to_lonlat(xm, ym)
    return float(lon), float(lat)


def test_bad_files_are_one_line_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.osm.pbf"
    bad.write_bytes(b"not a pbf at all")
    with pytest.raises(SourceError, match=r"bad\.osm\.pbf"):
        read_landcover(bad)
    with pytest.raises(SourceError, match="no such file"):
        read_landcover(tmp_path / "missing.osm")
    empty = tmp_path / "trees.osm"
    empty.write_text(
        "<?xml version='1.0'?><osm version='0.6'>"
        "<node id='1' lat='60.1' lon='24.9'><tag k='natural' v='tree'/></node></osm>"
    )
    with pytest.raises(SourceError, match="no land use"):
        read_landcover(empty)


@pytest.fixture(scope="module")
def cover():  # type: ignore[no-untyped-def]
    return read_landcover(_sample())


def test_masks_from_many_threads_equal_masks_from_one(cover) -> None:  # type: ignore[no-untyped-def]
    # the scene's workers rasterise tiles at once; GEOS prepares shapes lazily, and shared
    # prepared shapes once corrupted the heap (an abort in CI). Fresh shapes each round, every
    # tile asked by four threads together.
    from concurrent.futures import ThreadPoolExecutor

    import mercantile

    tiles = list(mercantile.tiles(24.93, 60.163, 24.95, 60.172, [16]))
    assert len(tiles) >= 12
    for _ in range(5):
        lc = Landcover(cover.name, [(shapely.from_wkb(g.wkb), v) for g, v in cover.shapes])
        asked = [t for t in tiles for _ in range(4)]
        with ThreadPoolExecutor(4) as pool:
            masks = list(pool.map(lc.mask, *zip(*[(t.z, t.x, t.y) for t in asked], strict=True)))
        for k, t in enumerate(tiles):
            want = cover.mask(t.z, t.x, t.y)
            for m in masks[4 * k : 4 * k + 4]:
                assert np.array_equal(m, want)
        assert any(m.any() for m in masks)


def _flat() -> str:
    return "flat:24.925,60.158,24.965,60.186"


CAM = Camera(24.9405, 60.1690, 150.0, heading=100.0, pitch=-25.0, width=320, height=200)


@pytest.mark.gl
@pytest.mark.parametrize("mode", ["cpu", "gpu"])
def test_landcover_ground_renders_and_holds_less_than_imagery(cover, mode: str) -> None:  # type: ignore[no-untyped-def]
    from lodscape.terrain.detail import Fractal

    pictures, texture_bytes = {}, {}
    for ground in ("imagery", "landcover"):
        opts = SceneOptions(terrain_mode=mode, anisotropy=1.0)
        # the land cover's detail tree (no amplitude) under both, so both hold the same tiles
        scene = lodscape.open(
            _flat(),
            opts,
            detail=Fractal(0.7, 0.0, 0),
            landcover=cover if ground == "landcover" else None,
        )
        with scene:
            assert scene.ground == ground
            rgb, depth = scene.render(CAM)
            assert scene.last is not None
            assert np.isfinite(depth).mean() > 0.5
            renderer = scene.renderer
            assert renderer is not None
            textures = {k: v for k, v in renderer.resident().items() if is_texture(k)}
            texture_bytes[ground] = sum(textures.values()) / len(textures)
            pictures[ground] = rgb
    # roads: dark grey, unlike anything in the tint
    rgb = pictures["landcover"].astype(np.int16)
    grey = (np.abs(rgb[..., 0] - rgb[..., 2]) < 12) & (rgb.sum(axis=2) < 300)
    assert grey.mean() > 0.02
    assert np.abs(pictures["landcover"].astype(int) - pictures["imagery"].astype(int)).mean() > 10
    # one byte a texel, no mipmaps, against RGBA with its mip chain: over 5× less per tile
    assert texture_bytes["imagery"] / texture_bytes["landcover"] > 5.0


@pytest.mark.gl
def test_cli_ground_landcover(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "g.png"
    osm = str(_sample())
    view = ["--lon", "24.9405", "--lat", "60.169", "--alt", "150", "--pitch", "-25"]
    view += ["--size", "200x120", "--anisotropy", "1", "-o", str(out), "-q"]
    code, _, err = run_cli(
        ["render", "flat", "--city", osm, "--ground", "landcover", *view], capsys
    )
    assert code == 0, err
    tinted = tmp_path / "t.png"
    tint_view = [*view[:-3], "-o", str(tinted), "-q"]
    code, _, err = run_cli(
        ["render", "flat", "--city", osm, "--ground", "tint", *tint_view], capsys
    )
    assert code == 0, err
    # the ground wears the map's materials: much of the picture differs from the tint
    assert changed_share(out, tinted) > 0.2
    code, _, err = run_cli(["render", _flat(), "--ground", "landcover", *view], capsys)
    assert code == 2
    assert "--landcover FILE or --city FILE" in err
    code, _, err = run_cli(["render", _flat(), "--ground", "sand", *view], capsys)
    assert code == 2
    assert "--ground is tint or landcover" in err
    code, _, err = run_cli(
        ["render", _flat(), "--ground", "landcover", "--landcover", osm, "--imagery", "x", *view],
        capsys,
    )
    assert code == 2
    assert "pick one" in err
