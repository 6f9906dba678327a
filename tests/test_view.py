"""The viewer in a real window on a virtual screen (Xvfb): it opens, draws, follows synthetic
keys and mouse drags (xdotool, through the X server as a user's would come), writes a
screenshot and a camera file, and closes cleanly on Esc."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from _synthetic import fbm_heights, write_dem
from conftest import _on_ci

pytestmark = pytest.mark.gl


@pytest.fixture(autouse=True)
def _virtual_screen_tools() -> None:
    """Skip without Xvfb and xdotool, except on CI, where a skipped viewer test fails the run."""
    if shutil.which("Xvfb") is None or shutil.which("xdotool") is None:
        reason = "needs Xvfb and xdotool (Debian: xvfb, xdotool; .ci/run installs them)"
        if _on_ci():
            pytest.fail(reason + " (on CI the viewer tests must run)")
        pytest.skip(reason)


@pytest.fixture
def display():  # type: ignore[no-untyped-def]
    for n in range(90, 120):
        if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists():
            break
    proc = subprocess.Popen(
        ["Xvfb", f":{n}", "-screen", "0", "800x600x24", "-nolisten", "tcp"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 20
    while not Path(f"/tmp/.X11-unix/X{n}").exists():
        if time.monotonic() > deadline or proc.poll() is not None:
            proc.kill()
            pytest.fail("Xvfb did not start")
        time.sleep(0.1)
    yield f":{n}"
    proc.terminate()
    proc.wait(timeout=10)


def _xdo(env: dict[str, str], *args: str) -> str:
    out = subprocess.run(
        ["xdotool", *args], env=env, capture_output=True, text=True, timeout=60, check=False
    )
    return out.stdout.strip()


def _viewer(env: dict[str, str], *args: str) -> subprocess.Popen[str]:
    """``lodscape view`` in its own process on the virtual screen."""
    return subprocess.Popen(
        [sys.executable, "-m", "lodscape.cli", "view", *args, "--exit-after", "90"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str]) -> tuple[str, str]:
    """Wait for the viewer to close; killed if it does not."""
    try:
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


SKY = np.array([135, 179, 230])


def _screenshot_until(
    env: dict[str, str], shots: Path, ok: Callable[[np.ndarray], bool]
) -> np.ndarray:
    """Press P until a screenshot passes ``ok`` (within 45 s) and return it; the screenshots
    are removed."""
    from PIL import Image

    deadline = time.monotonic() + 45.0
    while True:
        before = set(shots.glob("*.png"))
        _xdo(env, "key", "p")
        end, new = time.monotonic() + 10.0, None
        while new is None and time.monotonic() < end:
            made = {p for p in shots.glob("*.png") if ".tmp" not in p.name} - before
            new = made.pop() if made else None
            time.sleep(0.1)
        if new is not None:
            time.sleep(0.2)  # written whole (it is renamed into place)
            rgb = np.asarray(Image.open(new).convert("RGB")).astype(np.int16)
            new.unlink()
            if ok(rgb):
                return rgb
        assert time.monotonic() < deadline, "the view never showed what was awaited"
        time.sleep(0.5)


def _ground_share(rgb: np.ndarray) -> float:
    return float((np.abs(rgb - SKY).sum(axis=2) > 40).mean())


def test_viewer_flies_takes_a_screenshot_and_closes(display: str, tmp_path: Path) -> None:
    dem = write_dem(
        str(tmp_path / "dem.tif"),
        fbm_heights(257, seed=3),
        crs="EPSG:4326",
        west=7.0,
        north=46.5,
        res=0.0002,
    )
    start = {"lon": 7.0256, "lat": 46.4744, "alt": 2200.0, "heading": 0.0, "pitch": -30.0}
    (tmp_path / "start.json").write_text(json.dumps(start))
    env = {**os.environ, "DISPLAY": display}
    shots = tmp_path / "shots"
    proc = _viewer(
        env,
        dem,
        "--camera",
        str(tmp_path / "start.json"),
        "--camera-file",
        str(tmp_path / "end.json"),
        "--screenshots",
        str(shots),
        "--size",
        "320x200",
    )
    try:
        window = _xdo(env, "search", "--sync", "--name", "lodscape").splitlines()
        assert window, "no window"
        # the first frames stream in: screenshots until one shows the ground (a loaded
        # machine may take a while), so the keys below act on a running view
        _screenshot_until(env, shots, lambda rgb: _ground_share(rgb) > 0.3)
        _xdo(env, "keydown", "w")
        time.sleep(1.0)
        _xdo(env, "keyup", "w")
        w = window[-1]
        _xdo(env, "mousemove", "--window", w, "100", "100")
        _xdo(env, "mousedown", "1")
        _xdo(env, "mousemove", "--window", w, "180", "100")
        time.sleep(0.3)
        _xdo(env, "mouseup", "1")
        time.sleep(0.5)
        # wireframe (T: its lines over the surface) and level colours (L) each change the
        # picture, and pressed again give it back; culling (C) and fractal detail (G) toggle
        # twice: every key's path runs
        # once the view has settled (two screenshots alike: the tiles have streamed in)
        last: list[np.ndarray] = []

        def settled(rgb: np.ndarray) -> bool:
            same = bool(last) and float((np.abs(rgb - last[-1]).sum(axis=2) > 60).mean()) < 0.01
            last.append(rgb)
            return same

        base = _screenshot_until(env, shots, settled)

        def changed(rgb: np.ndarray) -> float:
            return float((np.abs(rgb - base).sum(axis=2) > 60).mean())

        seen: list[float] = []

        def record(rgb: np.ndarray) -> float:
            seen.append(changed(rgb))
            return seen[-1]

        for key in ("t", "l"):
            try:
                _xdo(env, "key", key)
                _screenshot_until(env, shots, lambda rgb: record(rgb) > 0.02)
                _xdo(env, "key", key)
                _screenshot_until(env, shots, lambda rgb: record(rgb) < 0.005)
            except AssertionError:
                raise AssertionError(f"key {key}: changed shares {seen}") from None
        for key in ("c", "c", "g", "g"):
            _xdo(env, "key", key)
            time.sleep(0.4)
        for key in ("p", "k", "Escape"):
            _xdo(env, "key", key)
            time.sleep(0.5)
    finally:
        out, err = _finish(proc)
    assert proc.returncode == 0, err
    frames = int(out.split(" frames")[0].split()[-1])
    assert frames > 10, out
    # the screenshot holds terrain: varied colours below a sky
    from PIL import Image

    shot = sorted(shots.glob("*.png"))
    assert len(shot) == 1
    rgb = np.asarray(Image.open(shot[0]).convert("RGB")).astype(np.int16)
    assert rgb.shape == (200, 320, 3)
    ground = np.abs(rgb - SKY).sum(axis=2) > 40
    assert ground.mean() > 0.3
    assert rgb[ground].std() > 5.0
    # W flew north, the drag turned right by a quarter of a degree per pixel
    end = json.loads((tmp_path / "end.json").read_text())
    assert end["lat"] > start["lat"] + 1e-5
    assert 10.0 < end["heading"] < 30.0
    assert abs(end["lon"] - start["lon"]) < 0.01


def test_viewer_shows_the_globe(display: str, tmp_path: Path) -> None:
    env = {**os.environ, "DISPLAY": display}
    shots = tmp_path / "shots"
    proc = _viewer(env, "none", "--globe", "--size", "240x180", "--screenshots", str(shots))
    try:
        assert _xdo(env, "search", "--sync", "--name", "lodscape")
        _screenshot_until(env, shots, lambda rgb: (rgb.sum(axis=2) > 30).mean() > 0.1)
        _xdo(env, "key", "p")
        time.sleep(0.5)
        _xdo(env, "key", "Escape")
    finally:
        _, err = _finish(proc)
    assert proc.returncode == 0, err
    from PIL import Image

    (shot,) = sorted(shots.glob("*.png"))
    rgb = np.asarray(Image.open(shot).convert("RGB")).astype(np.int16)
    # the Earth's disc on black space: a fair share of coloured pixels, black round it
    lit = rgb.sum(axis=2) > 30
    assert 0.1 < lit.mean() < 0.9
    assert not lit[0, 0]


def test_viewer_lays_the_terrains_tiles_into_the_globe(display: str, tmp_path: Path) -> None:
    """``view DEM --globe``: the window shows what ``render DEM --globe`` does from the same
    camera, the DEM's own tiles laid into the globe (not the globe's facets draped)."""
    env = {**os.environ, "DISPLAY": display}
    dem = tmp_path / "dem.tif"
    write_dem(
        str(dem),
        fbm_heights(129, seed=5, relief=600.0),
        crs="EPSG:4326",
        west=10.0,
        north=46.1,
        res=1e-3,
    )
    camera = tmp_path / "cam.json"
    view = ["--lon", "10.064", "--lat", "45.93", "--alt", "9000", "--pitch", "-45"]
    still = tmp_path / "still.png"
    from lodscape.cli import main

    main(["render", str(dem), "--globe", *view, "--size", "240x180", "-o", str(still), "-q"])
    camera.write_text(
        json.dumps({"lon": 10.064, "lat": 45.93, "alt": 9000.0, "heading": 0.0, "pitch": -45.0})
    )
    shots = tmp_path / "shots"
    proc = _viewer(
        env,
        str(dem),
        "--globe",
        "--camera",
        str(camera),
        "--size",
        "240x180",
        "--screenshots",
        str(shots),
    )
    from PIL import Image

    want = np.asarray(Image.open(still).convert("RGB")).astype(np.int16)
    try:
        assert _xdo(env, "search", "--sync", "--name", "lodscape")
        got = _screenshot_until(
            env, shots, lambda rgb: float((np.abs(rgb - want).sum(axis=2) > 60).mean()) < 0.02
        )
        _xdo(env, "key", "Escape")
    finally:
        _, err = _finish(proc)
    assert proc.returncode == 0, err
    assert float((np.abs(got - want).sum(axis=2) > 60).mean()) < 0.02
