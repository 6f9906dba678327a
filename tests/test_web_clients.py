"""What MapLibre, Cesium and other web clients are given over a DEM with a nodata collar and a
void (issue 39): imagery transparent exactly where the DEM has no data, every imagery tile of
the advertised range there (none a 404), Terrarium from level 0 with no -32768 m, TileJSON
documents valid against TileJSON 3.0.0 with absolute URLs, and the MapLibre page."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import jsonschema
import numpy as np
import pytest
from PIL import Image

from _synthetic import fbm_heights, run_cli, write_dem
from _tileserver import serve_tileset
from lodscape.build import build
from lodscape.geo.tiles import Tile, merc_to_lonlat, tiles_array, xy_bounds
from lodscape.store.tileset import TilesetProvider

EAST, NORTH, RES, NODATA = 640000.0, 5200000.0, 30.0, -9999.0

#: TileJSON 3.0.0 as its specification (github.com/mapbox/tilejson-spec, 3.0.0/README.md)
#: states it, field by field: types, zoom ranges, the required members.
TILEJSON_3 = {
    "type": "object",
    "required": ["tilejson", "tiles", "vector_layers"],
    "properties": {
        "tilejson": {"type": "string", "pattern": r"^3\.0\.0$"},
        "tiles": {"type": "array", "minItems": 1, "items": {"type": "string"}},
        "vector_layers": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["id", "fields"],
                "properties": {
                    "id": {"type": "string"},
                    "fields": {"type": "object", "additionalProperties": {"type": "string"}},
                    "description": {"type": "string"},
                    "minzoom": {"type": "integer", "minimum": 0, "maximum": 30},
                    "maxzoom": {"type": "integer", "minimum": 0, "maximum": 30},
                },
            },
        },
        "attribution": {"type": "string"},
        "bounds": {"type": "array", "items": {"type": "number"}, "minItems": 4, "maxItems": 4},
        "center": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
        "data": {"type": "array", "items": {"type": "string"}},
        "description": {"type": "string"},
        "fillzoom": {"type": "integer", "minimum": 0, "maximum": 30},
        "grids": {"type": "array", "items": {"type": "string"}},
        "legend": {"type": "string"},
        "maxzoom": {"type": "integer", "minimum": 0, "maximum": 30},
        "minzoom": {"type": "integer", "minimum": 0, "maximum": 30},
        "name": {"type": "string"},
        "scheme": {"enum": ["xyz", "tms"]},
        "template": {"type": "string"},
        "version": {"type": "string", "pattern": r"^\d+\.\d+\.\d+\w?[\w\d]*$"},
    },
}


def _valid_tilejson(doc: dict[str, object]) -> None:
    """Valid TileJSON 3.0.0 whose tile URLs are absolute and whose zooms and bounds agree."""
    jsonschema.validate(doc, TILEJSON_3)
    for url in doc["tiles"]:  # type: ignore[attr-defined]
        parts = urlsplit(url)
        assert parts.scheme in ("http", "https"), url
        assert parts.netloc, url
        assert all(k in url for k in ("{z}", "{x}", "{y}")), url
    assert 0 <= doc["minzoom"] <= doc["maxzoom"] <= 30  # type: ignore[operator]
    w, s, e, n = doc["bounds"]  # type: ignore[misc]
    assert -180 <= w < e <= 180
    assert -90 <= s < n <= 90


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, np.ndarray]:
    h = fbm_heights(513, seed=21) + 200.0
    h[:260, :] = NODATA  # a collar along the north edge, wider than a tile
    h[:, -44:] = NODATA  # and the east
    h[380:420, 60:160] = NODATA  # a void
    path = tmp_path_factory.mktemp("web") / "collar.tif"
    write_dem(str(path), h, crs="EPSG:32633", west=EAST, north=NORTH, res=RES, nodata=NODATA)
    return str(path), h


@pytest.fixture(scope="module")
def tileset(dem: tuple[str, np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("web-tileset") / "collar.lods"
    build([dem[0]], out)  # the default fill: interpolate
    return out


@pytest.fixture(scope="module")
def served(tileset: Path) -> Iterator[str]:
    with serve_tileset(tileset) as url:
        yield url


def _has_data(h: np.ndarray, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
    """Whether the DEM has a height at points (its own pixels, nearest)."""
    from pyproj import Transformer

    x, y = Transformer.from_crs("EPSG:4326", "EPSG:32633", always_xy=True).transform(lon, lat)
    col = np.floor((np.asarray(x) - EAST) / RES).astype(np.int64)
    row = np.floor((NORTH - np.asarray(y)) / RES).astype(np.int64)
    inside = (col >= 0) & (col < h.shape[1]) & (row >= 0) & (row < h.shape[0])
    out = np.zeros(col.shape, bool)
    out[inside] = h[row[inside], col[inside]] != NODATA
    return out


def test_imagery_is_transparent_exactly_where_the_dem_has_no_data(
    tileset: Path, dem: tuple[str, np.ndarray]
) -> None:
    """At the finest imagery level every texel clear of the data's edges (all points within
    two DEM pixels agree) is opaque where the DEM has data and transparent where it has none
    (the collar, the void, the world around): a client's base map shows there."""
    import sqlite3

    h = dem[1]
    provider = TilesetProvider(tileset)
    zmax = int(provider.manifest["levels"]["texture_zmax"])
    agree = {True: 0, False: 0}
    with sqlite3.connect(tileset) as db:
        rows = db.execute(
            "SELECT tile_column, tile_row, tile_data FROM tiles WHERE zoom_level = ?", (zmax,)
        ).fetchall()
    assert rows
    for x, row, data in rows:
        y = (1 << zmax) - 1 - row
        alpha = np.asarray(Image.open(io.BytesIO(data)).convert("RGBA"))[..., 3]
        n = alpha.shape[0]
        b = xy_bounds(Tile(x, y, zmax))
        f = (np.arange(n) + 0.5) / n
        xm, ym = np.meshgrid(b.left + f * (b.right - b.left), b.top - f * (b.top - b.bottom))
        lon, lat = merc_to_lonlat(xm, ym)
        here = _has_data(h, lon, lat)
        d = 2.0 * RES / 111_000.0  # two DEM pixels, in degrees of latitude (and more of lon)
        clear = np.ones_like(here)
        for dx, dy in ((-2 * d, 0), (2 * d, 0), (0, -d), (0, d), (2 * d, d), (-2 * d, -d),
                       (2 * d, -d), (-2 * d, d)):  # fmt: skip
            clear &= _has_data(h, lon + dx, lat + dy) == here
        assert (alpha[clear & here] == 255).all(), (x, y)
        assert (alpha[clear & ~here] == 0).all(), (x, y)
        agree[True] += int((clear & here).sum())
        agree[False] += int((clear & ~here).sum())
        # lodscape's own renderer still draws the fill there: every texel it gets is opaque
        from lodscape.geo.keys import texture_key
        from lodscape.geo.tiles import tile_id

        assert provider.texture(texture_key(tile_id(Tile(x, y, zmax))))[..., 3].min() == 255
    provider.close()
    assert agree[True] > 10_000, agree
    assert agree[False] > 10_000, agree


def test_an_export_has_every_advertised_imagery_tile_and_valid_tilejson(
    tileset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "web"
    argv = ["export", str(tileset), "--cesium", str(folder), "--base-url", "https://tiles.example"]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    tj = json.loads((folder / "imagery.json").read_text())
    _valid_tilejson(tj)
    assert tj["tiles"][0] == "https://tiles.example/imagery/{z}/{x}/{y}.png"
    w, s, e, n = tj["bounds"]
    missing = empty = 0
    stored = {p.relative_to(folder / "imagery") for p in (folder / "imagery").rglob("*.png")}
    for z in range(tj["minzoom"], tj["maxzoom"] + 1):
        (x0, x1), (y0, y1) = (
            tuple(v.tolist())
            for v in tiles_array(*_merc([w, e], [n, s]), z)  # type: ignore[arg-type]
        )
        for xx in range(x0, x1 + 1):
            for yy in range(y0, y1 + 1):
                f = folder / "imagery" / str(z) / str(xx) / f"{yy}.png"
                if not f.exists():
                    missing += 1
                    continue
                alpha = np.asarray(Image.open(f).convert("RGBA"))[..., 3]
                empty += int(alpha.max() == 0)
    assert missing == 0
    assert len(stored) > 0
    assert empty > 0  # the collar's tiles, which the tileset does not store: there, transparent


def _merc(lon: list[float], lat: list[float]) -> tuple[np.ndarray, np.ndarray]:
    from lodscape.geo.tiles import lonlat_to_merc

    return lonlat_to_merc(lon, lat)


def test_serve_gives_terrarium_from_level_0_and_valid_tilejson(served: str, tileset: Path) -> None:
    with httpx.Client(base_url=served, headers={"X-Forwarded-Proto": "https"}) as c:
        imagery = c.get("/imagery.json").json()
        terrarium = c.get("/terrarium.json").json()
        for doc in (imagery, terrarium):
            _valid_tilejson(doc)
            assert doc["tiles"][0].startswith("https://127.0.0.1:")
        assert terrarium["encoding"] == "terrarium"
        assert terrarium["fill"] == "interpolate"
        assert terrarium["minzoom"] == 0
        provider = TilesetProvider(tileset)
        levels = provider.manifest["levels"]
        provider.close()
        # capped at the data's own level, not the terrain's finer ones
        assert terrarium["maxzoom"] == levels["texture_zmax"] < levels["zmax"]
        index = c.get("/index.json").json()
        assert index["terrarium_tilejson"] == "terrarium.json"
        w, s, e, n = terrarium["bounds"]
        lon, lat = (w + e) / 2, (s + n) / 2
        seen = 0
        for z in range(terrarium["maxzoom"] + 1):
            tx, ty = tiles_array(*_merc([lon], [lat]), z)
            r = c.get(f"/terrarium/{z}/{int(tx[0])}/{int(ty[0])}.png")
            assert r.status_code == 200, z
            rgba = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGBA"), np.float64)
            hm = rgba[..., 0] * 256 + rgba[..., 1] + rgba[..., 2] / 256 - 32768
            assert hm.min() > -1000.0, z  # never -32768 m (MapLibre ignores alpha)
            seen += int((rgba[..., 3] == 255).any())
        assert seen >= terrarium["maxzoom"] - 3  # the data shows from a few levels down
        deeper = terrarium["maxzoom"] + 1
        tx, ty = tiles_array(*_merc([lon], [lat]), deeper)
        assert c.get(f"/terrarium/{deeper}/{int(tx[0])}/{int(ty[0])}.png").status_code == 404
        assert c.get("/terrarium/3/0/0.png").status_code == 404  # far from the data
        # the imagery: a tile of the range the tileset does not store is there, transparent
        z = imagery["maxzoom"]
        (x0, x1), (y0, y1) = (
            tuple(v.tolist())
            for v in tiles_array(*_merc([w, e], [n, s]), z)  # type: ignore[arg-type]
        )
        codes = []
        for xx in range(x0, x1 + 1):
            for yy in range(y0, y1 + 1):
                codes.append(c.get(f"/imagery/{z}/{xx}/{yy}.png").status_code)
        assert set(codes) == {200}
        assert c.get(f"/imagery/{z}/{x1 + 3}/{y0}.png").status_code == 404


def test_the_maplibre_page_names_what_is_served(served: str, tmp_path: Path) -> None:
    """``/maplibre``: MapLibre GL JS (an ES module) from the default CDN build, over the
    imagery's and the Terrarium terrain's TileJSON that /index.json names."""
    from lodscape.serve import MAPLIBRE_JS, maplibre_source

    with httpx.Client(base_url=served) as c:
        r = c.get("/maplibre")
        assert r.status_code == 200
        assert r.headers["content-type"].startswith("text/html")
        page = r.text
        assert json.dumps(MAPLIBRE_JS + "maplibre-gl.mjs") in page
        assert f'href="{MAPLIBRE_JS}maplibre-gl.css"' in page
        for key in ("index.terrarium_tilejson", "index.imagery_tilejson", '"raster-dem"'):
            assert key in page
        index = c.get("/index.json").json()
        for key in ("terrarium_tilejson", "imagery_tilejson"):
            assert c.get("/" + index[key]).status_code == 200
    dist = tmp_path / "dist"
    dist.mkdir()
    (dist / "maplibre-gl.mjs").write_text("export const Map = null;")
    (dist / "maplibre-gl.css").write_text("body {}")
    assert maplibre_source(str(dist)) == ("maplibre-js/", dist.resolve())
    with pytest.raises(Exception, match="--maplibre-js"):
        maplibre_source(str(tmp_path))
