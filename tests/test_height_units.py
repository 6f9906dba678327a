"""Heights in feet come out in metres: a DEM in a projected CRS measured in US survey feet, a
compound CRS whose vertical axis is in feet, and a band whose unit says ``ft``; ``--z-units``
overrides what the file says (real GeoTIFFs through rasterio, the real command)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.errors import SourceError
from lodscape.geo.tiles import merc_to_lonlat
from lodscape.terrain.source import RasterSource, parse_z_units

US_FT = 1200.0 / 3937.0


def _metres(n: int = 129) -> np.ndarray:
    """Relief of 200..400 m."""
    h = fbm_heights(n, seed=11).astype(np.float64)
    return 200.0 + 200.0 * (h - h.min()) / (h.max() - h.min())


# (CRS, west, north, pixel) in the CRS's own units; the heights are written in `factor` units
CASES = {
    "projected-us-ft": ("EPSG:2277", 2_300_000.0, 10_100_000.0, 100.0, US_FT, None),
    "compound-us-ft": ("EPSG:2277+6360", 2_300_000.0, 10_100_000.0, 100.0, US_FT, None),
    "band-unit-ft": ("EPSG:32614", 620_000.0, 3_350_000.0, 30.0, 0.3048, "ft"),
}


@pytest.fixture(params=sorted(CASES))
def feet_dem(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[str, float]:
    crs, west, north, res, factor, unit = CASES[request.param]
    heights = (_metres() / factor).astype(np.float32)
    path = write_dem(
        str(tmp_path / f"{request.param}.tif"), heights, crs=crs, west=west, north=north,
        res=res, unit=unit,
    )  # fmt: skip
    return path, factor


def test_heights_in_feet_are_read_as_metres(feet_dem: tuple[str, float]) -> None:
    path, factor = feet_dem
    with RasterSource(path) as src:
        assert src.z_factor == pytest.approx(factor)
        lo, hi = src.data_range
        assert lo == pytest.approx(200.0, abs=0.01)
        assert hi == pytest.approx(400.0, abs=0.01)
        assert "--z-units" in str(src.z_note)
    with RasterSource(path, z_units="m") as src:  # the user knows better
        assert src.data_range[1] == pytest.approx(400.0 / factor, abs=0.05)
        assert src.z_note is None


def test_info_and_a_render_report_metres(
    feet_dem: tuple[str, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, factor = feet_dem
    code, out, err = run_cli(["info", path], capsys)
    assert code == 0, err
    line = next(x for x in out.splitlines() if x.strip().startswith("heights"))
    lo, hi = (float(v) for v in line.split(":")[1].replace("m", "").split(".."))
    assert 195.0 <= lo <= 205.0, line
    assert 395.0 <= hi <= 405.0, line
    assert err.count("converted to metres") == 1, err
    code, out, _ = run_cli(["info", path, "--z-units", "m"], capsys)
    line = next(x for x in out.splitlines() if x.strip().startswith("heights"))
    assert float(line.split("..")[1].replace("m", "")) > 395.0 / factor
    # the picture: the ground at the data's centre is in metres
    with lodscape.open(path) as scene:
        b = scene.provider.bounds_merc
        lon, lat = merc_to_lonlat((b.left + b.right) / 2, (b.bottom + b.top) / 2)
        ground = scene.provider.ground_height(float(lon), float(lat))
        assert 195.0 <= float(ground or 0.0) <= 405.0
    depth = tmp_path / "d.npy"
    code, _, err = run_cli(
        ["render", path, "--size", "160x90", "-o", str(tmp_path / "v.png"), "--depth", str(depth)],
        capsys,
    )
    assert code == 0, err


def test_a_build_converts_and_remembers_the_unit(
    feet_dem: tuple[str, float], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, _ = feet_dem
    out = tmp_path / "site.lods"
    code, _, err = run_cli(["build", path, "-o", str(out), "-q"], capsys)
    assert code == 0, err
    code, text, err = run_cli(["info", str(out)], capsys)
    line = next(x for x in text.splitlines() if x.strip().startswith("heights"))
    lo, hi = (float(v) for v in line.split(":")[1].replace("m", "").split(".."))
    assert 190.0 <= lo <= 210.0, line
    assert 390.0 <= hi <= 410.0, line


@pytest.mark.parametrize(
    ("text", "factor"),
    [("m", 1.0), ("ft", 0.3048), ("us-ft", US_FT), ("US survey foot", US_FT), ("0.5", 0.5)],
)
def test_z_units_are_parsed(text: str, factor: float) -> None:
    assert parse_z_units(text) == pytest.approx(factor)


@pytest.mark.parametrize("text", ["yards", "0", "-1", "nan", ""])
def test_bad_z_units_are_refused(text: str) -> None:
    with pytest.raises(SourceError, match="--z-units"):
        parse_z_units(text)
