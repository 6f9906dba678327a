"""A corpus of hostile command lines: each ends with one line on stderr that names the input,
exit status 2, and no output file of any kind."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import Affine

from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.scene import SKY

EAST, NORTH, RES = 700000.0, 4060000.0, 30.0


def _dem(folder: Path, crs: str = "EPSG:32617") -> str:
    """A small DEM in metres of ``crs`` (a lon/lat CRS makes it a mislabelled one)."""
    h = fbm_heights(65, seed=1)
    return write_dem(str(folder / "dem.tif"), h, crs=crs, west=EAST, north=NORTH, res=RES)


def _route(name: str, text: str) -> Callable[[Path], list[str]]:
    """A flight along a route file ``name`` holding ``text``."""

    def case(folder: Path) -> list[str]:
        (folder / name).write_text(text)
        return ["fly", _dem(folder), "--path", str(folder / name), "-o", str(folder / "o.mp4")]

    return case


def _bad_depth(folder: Path) -> list[str]:
    return [
        "render",
        _dem(folder),
        "-o",
        str(folder / "out.png"),
        "--depth",
        str(folder / "out.xyz"),
    ]


def _globe_at_zero(folder: Path) -> list[str]:
    return ["globe", "--lon", "10", "--lat", "45", "--alt", "0", "-o", str(folder / "out.png")]


def _orbit(flag: str, value: str) -> Callable[[Path], list[str]]:
    """A flight round the DEM with one flag of the given value."""

    def case(folder: Path) -> list[str]:
        orbit = "-78.78,36.66,500,2000"
        return ["fly", _dem(folder), "--orbit", orbit, flag, value, "-o", str(folder / "out.mp4")]

    return case


def _empty_lods(folder: Path) -> list[str]:
    (folder / "site.lods").write_bytes(b"")
    return ["render", str(folder / "site.lods"), "-o", str(folder / "out.png")]


def _text_lods(folder: Path) -> list[str]:
    (folder / "site.lods").write_text("not a tileset\n")
    return ["info", str(folder / "site.lods")]


def _absurd(value: float) -> Callable[[Path], list[str]]:
    def case(folder: Path) -> list[str]:
        h = fbm_heights(65, seed=1)
        h[3:6, 3:6] = np.float32(value)
        dem = write_dem(
            str(folder / "dem.tif"), h, crs="EPSG:32617", west=EAST, north=NORTH, res=RES
        )
        return ["render", dem, "-o", str(folder / "out.png")]

    return case


def _bands(path: Path, data: np.ndarray, res: float) -> Path:
    """A GeoTIFF of (bands, rows, cols) ``data`` at ``res`` metres in UTM 17N."""
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=data.shape[2],
        height=data.shape[1],
        count=data.shape[0],
        dtype=data.dtype,
        crs="EPSG:32617",
        transform=Affine(res, 0.0, EAST, 0.0, -res, NORTH),
    ) as dst:
        dst.write(data)
    return path


def _three_bands(folder: Path) -> list[str]:
    h = fbm_heights(33, seed=2).astype(np.float32)
    path = _bands(folder / "dem.tif", np.stack([h, h, h]), RES)
    return ["build", str(path), "-o", str(folder / "out.lods")]


def _bad_fill(folder: Path) -> list[str]:
    return ["render", _dem(folder), "--fill", "value:high", "-o", str(folder / "out.png")]


def _bad_sea(folder: Path) -> list[str]:
    return ["render", _dem(folder), "--sea-level", "deep", "-o", str(folder / "out.png")]


def _band_on_a_procedural(folder: Path) -> list[str]:
    return ["render", "procedural:seed=1", "--band", "2", "-o", str(folder / "out.png")]


def _cache_is_a_file(folder: Path) -> list[str]:
    (folder / "cache").write_text("a file")
    return [
        "render",
        _dem(folder),
        "--imagery",
        "http://127.0.0.1:9/{z}/{x}/{y}.png",
        "--imagery-cache",
        str(folder / "cache"),
        "-o",
        str(folder / "out.png"),
    ]


def _metres_labelled_degrees(folder: Path) -> list[str]:
    return ["render", _dem(folder, "EPSG:4326"), "-o", str(folder / "out.png")]


def _millimetre_pixels(folder: Path) -> list[str]:
    h = fbm_heights(65, seed=1)
    dem = write_dem(str(folder / "dem.tif"), h, crs="EPSG:32617", west=EAST, north=NORTH, res=0.001)
    return ["build", dem, "-o", str(folder / "out.lods")]


def _truncated_imagery(folder: Path) -> list[str]:
    data = np.random.default_rng(3).integers(0, 255, (3, 200, 200), dtype=np.uint16)
    path = _bands(folder / "ortho.tif", data, 2.0)
    path.write_bytes(path.read_bytes()[:40_000])
    return ["render", _dem(folder), "--imagery", str(path), "-o", str(folder / "out.png")]


def _text_dem(folder: Path) -> list[str]:
    (folder / "dem.tif").write_text("elevation,100\n")
    return ["render", str(folder / "dem.tif"), "-o", str(folder / "out.png")]


def _camera_not_json(folder: Path) -> list[str]:
    (folder / "cam.json").write_text("{lon: 1, lat: 2")
    return [
        "render",
        _dem(folder),
        "--camera",
        str(folder / "cam.json"),
        "-o",
        str(folder / "o.png"),
    ]


def _points(name: str, text: str) -> Callable[[Path], list[str]]:
    """A build from a point file ``name`` holding ``text`` (UTM 17N)."""

    def case(folder: Path) -> list[str]:
        (folder / name).write_text(text)
        return ["build", str(folder / name), "--crs", "EPSG:32617", "-o", str(folder / "o.lods")]

    return case


_LAYERS: dict[str, bytes] = {}
_LAYER_SERVER: list[str] = []


def _layer_json(name: str, layer: dict[str, object]) -> Callable[[Path], list[str]]:
    """A render over a Cesium-style terrain server whose ``layer.json`` is ``layer`` (served
    on loopback by a server started once for the module)."""

    def case(folder: Path) -> list[str]:
        import json
        import threading
        from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

        _LAYERS[f"/{name}/layer.json"] = json.dumps(layer).encode()
        if not _LAYER_SERVER:

            class Handler(BaseHTTPRequestHandler):
                def log_message(self, *args: object) -> None:
                    pass

                def do_GET(self) -> None:
                    body = _LAYERS.get(self.path.split("?")[0])
                    if body is None:
                        self.send_error(404)
                        return
                    self.send_response(200)
                    self.send_header("Content-Length", str(len(body)))
                    self.end_headers()
                    self.wfile.write(body)

            httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
            threading.Thread(target=httpd.serve_forever, daemon=True).start()
            _LAYER_SERVER.append(f"http://127.0.0.1:{httpd.server_address[1]}")
        url = f"{_LAYER_SERVER[0]}/{name}/layer.json"
        (folder / "c").mkdir()  # the user's cache folder, there before the command
        return ["render", url, "--imagery-cache", str(folder / "c"), "-o", str(folder / "o.png")]

    return case


def _six_bands(folder: Path, bands: str) -> list[str]:
    data = np.random.default_rng(4).integers(0, 255, (6, 64, 64), dtype=np.uint8)
    path = _bands(folder / "scene.tif", data, RES)
    return [
        "render", _dem(folder), "--imagery", str(path), "--imagery-bands", bands,
        "-o", str(folder / "out.png"),
    ]  # fmt: skip


_QM = {"format": "quantized-mesh-1.0", "tiles": ["{z}/{x}/{y}.terrain"], "scheme": "tms"}


def _stats_over_route(folder: Path) -> list[str]:
    (folder / "route.csv").write_text("lon,lat,alt\n-78.78,36.66,900\n-78.77,36.66,900\n")
    route = str(folder / "route.csv")
    return ["fly", _dem(folder), "--path", route, "--stats", route, "-o", str(folder / "o.mp4")]


def _city_far_away(folder: Path) -> list[str]:
    from lodscape.data import sample_city_path

    return ["render", _dem(folder), "--city", str(sample_city_path()), "-o", str(folder / "o.png")]


CASES = {
    "a city far from the DEM": (_city_far_away, "lies outside the terrain"),
    "statistics over the route": (_stats_over_route, "--stats would overwrite --path"),
    "a picture over its DEM": (
        lambda f: ["render", _dem(f), "-o", str(f / "dem.tif")],
        "-o would overwrite SOURCE",
    ),
    "a layer.json of maxzoom 99": (_layer_json("deep", {**_QM, "maxzoom": 99}), "maxzoom 99"),
    "a layer.json with inverted bounds": (
        _layer_json("inverted", {**_QM, "bounds": [10, 50, 5, 45]}),
        "inverted/layer.json",
    ),
    "a pitch of 91": (
        lambda f: ["render", _dem(f), "--pitch", "91", "-o", str(f / "o.png")],
        "--pitch",
    ),
    "a roll of 1000": (
        lambda f: [
            "render",
            _dem(f),
            "--lon",
            "-78.7",
            "--lat",
            "36.6",
            "--alt",
            "900",
            "--roll",
            "1000",
            "-o",
            str(f / "o.png"),
        ],
        "--roll",
    ),
    "a pitch without a position": (
        lambda f: ["render", _dem(f), "--pitch", "-45", "-o", str(f / "o.png")],
        "--pitch",
    ),
    "a budget of 0 MiB": (_orbit("--budget-mb", "0"), "--budget-mb"),
    "imagery bands that do not exist": (lambda f: _six_bands(f, "7,3,2"), "--imagery-bands"),
    "imagery bands that are not numbers": (lambda f: _six_bands(f, "red"), "--imagery-bands"),
    "a LAS file that is not one": (_points("survey.las", "garbage\n"), "survey.las"),
    "points with an infinite height": (
        _points("survey.csv", "x,y,z\n1,2,inf\n3,4,5\n6,7,8\n"),
        "row 2",
    ),
    "XYZ points of two columns": (_points("survey.xyz", "1 2\n3 4\n5 6\n"), "survey.xyz"),
    "a CSV separated by semicolons": (
        _points("survey.csv", "x;y;z\n700000;4060000;100\n700100;4060000;110\n"),
        "survey.csv",
    ),
    "a camera file that is not JSON": (_camera_not_json, "cam.json"),
    "a route that is a GeoJSON point": (
        _route("route.geojson", '{"type": "Point", "coordinates": [-78.7, 36.6, 900]}'),
        "route.geojson",
    ),
    "a route with a word for a number": (
        _route("route.csv", "lon,lat,alt\n-78.7,36.6,900\n-78.7,north,900\n"),
        "route.csv",
    ),
    "truncated 16-bit orthophoto": (_truncated_imagery, "ortho.tif: cannot be read"),
    "a DEM that is a text file": (_text_dem, "dem.tif: not a raster"),
    "pixels of 1 mm": (_millimetre_pixels, "ask for level 27"),
    "imagery cache that is a file": (_cache_is_a_file, "cache"),
    "UTM metres labelled EPSG:4326": (_metres_labelled_degrees, "CRS is probably wrong"),
    "route with a header only": (_route("route.csv", "lon,lat,alt\n"), "route.csv"),
    "depth of an unknown type": (_bad_depth, "out.xyz"),
    "globe camera at height 0": (_globe_at_zero, "under the ground"),
    "negative flight duration": (_orbit("--duration", "-1"), "--duration"),
    "zero flight speed": (_orbit("--speed", "0"), "--speed"),
    "empty .lods": (_empty_lods, "site.lods"),
    "text .lods": (_text_lods, "site.lods"),
    "undeclared nodata -3.4e38": (_absurd(-3.4e38), "--nodata"),
    "undeclared nodata 1e30": (_absurd(1e30), "--nodata"),
    "heights of 1e7 m": (_absurd(1e7), "--nodata"),
    "three bands and no --band": (_three_bands, "--band"),
    "a fill that is not one": (_bad_fill, "--fill"),
    "a sea level that is not one": (_bad_sea, "--sea-level"),
    "--band on a procedural source": (_band_on_a_procedural, "--band"),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_hostile_command_lines(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    make, named = CASES[name]
    argv = make(tmp_path)
    before = set(tmp_path.iterdir())
    code, _, err = run_cli(argv, capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (name, err)
    assert len(lines) == 1, (name, err)
    assert named in lines[0], (name, lines[0])
    assert set(tmp_path.iterdir()) == before, name  # nothing written, not even a temporary


@pytest.mark.gl
@pytest.mark.parametrize(
    ("west", "north", "res", "shape"),
    [(-180.0, -60.0, 25.0 / 128, (129, 129)), (-180.0, 85.0, 360.0 / 256, (121, 256))],
    ids=["south cap", "whole world"],
)
def test_polar_and_global_dems_get_an_overview(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    west: float,
    north: float,
    res: float,
    shape: tuple[int, int],
) -> None:
    """No camera given: a view of the whole data, even round a pole or the whole Earth (it
    asked for a camera latitude of -96° and, from orbit, clipped the Earth at a horizon
    computed for low altitudes)."""
    h = np.ascontiguousarray(fbm_heights(257, seed=4)[: shape[0], : shape[1]])
    dem = write_dem(str(tmp_path / "dem.tif"), h, crs="EPSG:4326", west=west, north=north, res=res)
    out = tmp_path / "view.png"
    code, _, err = run_cli(
        ["render", dem, "-o", str(out), "--size", "160x100", "-q", "--no-ellipsoid"], capsys
    )
    assert code == 0, err
    from PIL import Image

    rgb = np.asarray(Image.open(out).convert("RGB")).astype(int)
    sky = np.all(np.abs(rgb - np.array(SKY) * 255) <= 2, axis=2)
    assert (~sky).mean() > 0.02  # the terrain is in the picture


def test_gdal_messages_stay_out_of_the_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    """rasterio hands GDAL's messages to Python's logging, whose last-resort handler printed
    them ("ERROR 4: …") above lodscape's own one-line error; the command line silences them."""
    import logging

    from lodscape.cli import _quiet_gdal

    _quiet_gdal()
    logging.getLogger("rasterio._env").error("ERROR 4: `x.tif' not recognized")
    logging.getLogger("rasterio._err").warning("TIFFReadDirectory: unknown field")
    assert capsys.readouterr().err == ""
