"""The command line as a user meets it: outputs, one-line errors, exit codes, no half-files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from _synthetic import fbm_heights, run_cli, write_dem


@pytest.fixture(scope="module")
def dem(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("cli") / "dem.tif"
    return write_dem(
        str(path), fbm_heights(257, seed=3), crs="EPSG:4326", west=7.0, north=46.5, res=0.0003
    )


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    return run_cli(argv, capsys)


@pytest.mark.gl
def test_render_writes_a_picture(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "view.png"
    depth = tmp_path / "depth.npy"
    code, stdout, err = _run(
        [
            "render",
            dem,
            "--lon",
            "7.04",
            "--lat",
            "46.44",
            "--alt",
            "3000",
            "--heading",
            "20",
            "--pitch",
            "-35",
            "--fov",
            "60",
            "--size",
            "320x200",
            "-o",
            str(out),
            "--depth",
            str(depth),
        ],
        capsys,
    )
    assert code == 0, err
    from PIL import Image

    img = np.asarray(Image.open(out))
    assert img.shape == (200, 320, 3)
    assert img.std() > 5  # a picture, not a flat fill
    d = np.load(depth)
    assert d.shape == (200, 320)
    assert np.isfinite(d).any()
    assert "max_sse_px" in stdout
    assert "tiles" in stdout
    assert list(tmp_path.iterdir()) == sorted([out, depth]) or set(tmp_path.iterdir()) == {
        out,
        depth,
    }


@pytest.mark.gl
def test_render_without_a_camera_shows_the_whole_data(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "all.png"
    argv = ["render", dem, "--size", "160x100", "-o", str(out), "-q", "--no-ellipsoid"]
    code, _, err = _run(argv, capsys)
    assert code == 0, err
    from PIL import Image

    from lodscape.scene import SKY

    with Image.open(out) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    assert rgb.shape == (100, 160, 3)
    ground = ~np.all(np.abs(rgb - np.array(SKY) * 255) <= 2, axis=2)
    # the overview frames the data: a good part of the picture, centred, its far edge below
    # the top of the picture
    assert 0.2 < ground.mean() < 0.9, ground.mean()
    cols = np.nonzero(ground)[1]
    assert 0.4 < cols.mean() / 160 < 0.6
    assert not ground[0].any()


def _bad_rasters(tmp: Path) -> dict[str, tuple[str, str]]:
    text = tmp / "notes.tif"
    text.write_text("this is not a raster\n")
    tiny = write_dem(
        str(tmp / "tiny.tif"),
        np.ones((1, 1), np.float32),
        crs="EPSG:4326",
        west=7,
        north=46,
        res=0.001,
    )
    empty = write_dem(
        str(tmp / "empty.tif"),
        np.full((20, 20), -9999, np.float32),
        crs="EPSG:4326",
        west=7,
        north=46,
        res=0.001,
        nodata=-9999,
    )
    nocrs = write_dem(
        str(tmp / "nocrs.tif"), fbm_heights(32), crs=None, west=7, north=46, res=0.001
    )
    return {
        "missing": (str(tmp / "nope.tif"), "no such file"),
        "not a raster": (str(text), "not a raster"),
        "1x1": (tiny, "1×1"),
        "all nodata": (empty, "nodata"),
        "no crs": (nocrs, "no CRS"),
    }


@pytest.mark.parametrize("case", ["missing", "not a raster", "1x1", "all nodata", "no crs"])
def test_bad_rasters_fail_in_one_line(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, message = _bad_rasters(tmp_path)[case]
    out = tmp_path / "out.png"
    code, _, err = _run(["render", path, "-o", str(out)], capsys)
    assert code == 2
    assert err.count("\n") == 1
    assert "Traceback" not in err
    assert message in err
    assert Path(path).name in err
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--lon", "7.05", "--lat", "46.45", "--alt", "10"], "under the ground"),
        (["--lon", "7.05", "--lat", "nan", "--alt", "3000"], "finite"),
        (["--lon", "7.05", "--lat", "46.45"], "--alt"),
        (["--size", "12x"], "WIDTHxHEIGHT"),
        (["--lon", "7.05", "--lat", "46.45", "--alt", "3000", "--fov", "190"], "fov"),
        (["--max-sse", "0"], "max_sse"),
        (["--anisotropy", "0.5"], "anisotropy"),
    ],
)
def test_bad_cameras_fail_in_one_line(
    dem: str, tmp_path: Path, args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out.png"
    code, _, err = _run(["render", dem, "-o", str(out), *args], capsys)
    assert code == 2, err
    assert err.count("\n") == 1
    assert "Traceback" not in err
    assert message in err
    assert not out.exists()


def test_unwritable_output_leaves_nothing(
    dem: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "no" / "such" / "dir" / "view.png"
    code, _, err = _run(["render", dem, "--size", "64x48", "-o", str(out)], capsys)
    assert code == 2
    assert "does not exist" in err
    assert err.count("\n") == 1
    out2 = tmp_path / "view.xyz"
    code, _, err = _run(["render", dem, "--size", "64x48", "-o", str(out2)], capsys)
    assert code == 2
    assert "unknown image type" in err
    assert list(tmp_path.iterdir()) == []


def test_console_script_exit_status(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "lodscape.cli", "render", str(tmp_path / "x.tif")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0
    assert "no such file" in proc.stderr
