"""Paper 004's areas: the memory and cache radii around the camera, larger in front than
behind (the scalar product's correction), pushed ahead by the speed, grown with altitude; the
chunks in them classified at the level their distance asks for; and, in a flight, the tiles
behind a hovering camera already there when it turns round."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_tileset
from lodscape import Camera, SceneOptions
from lodscape.lod.radii import Radii, RadiiOptions, horizon, radii_for
from lodscape.stream import SimClock, StreamOptions


def _radii(speed: float = 0.0, height: float = 300.0, far: float = 1e9) -> Radii:
    east = np.array([1.0, 0.0, 0.0])
    north = np.array([0.0, 1.0, 0.0])
    return radii_for(np.zeros(3), north, east * speed, height, far, RadiiOptions())


def test_larger_in_front_than_behind_and_pushed_ahead_by_the_speed() -> None:
    north, south, east, west = (
        np.array([v]) for v in ([0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0])
    )
    still = _radii()
    assert still.visible == pytest.approx(horizon(300.0))
    front, back = still.radius("cache", north)[0], still.radius("cache", south)[0]
    assert front == pytest.approx(still.visible)
    assert back == pytest.approx(0.35 * still.visible)
    assert still.radius("memory", north)[0] == pytest.approx(0.5 * front)
    # moving east at 600 m/s: three seconds of travel more towards the east, none to the west
    fast = _radii(speed=600.0)
    assert fast.radius("cache", east)[0] == pytest.approx(still.radius("cache", east)[0] + 1800)
    assert fast.radius("memory", east)[0] == pytest.approx(still.radius("memory", east)[0] + 600)
    assert fast.radius("cache", west)[0] == pytest.approx(still.radius("cache", west)[0])
    # higher up, the horizon and the radii reach farther; the far plane caps them
    assert _radii(height=3000.0).visible > 3 * still.visible
    assert _radii(far=5000.0).visible == 5000.0


def test_chunks_are_classified_by_distance_against_the_corrected_radii() -> None:
    r = _radii()
    v = r.visible
    # looking north, still: memory reaches 0.5·v ahead and 0.175·v behind, the cache v ahead
    # and 0.35·v behind
    cases = [  # (direction, distance in v, area)
        ((0, 1, 0), 0.4, 0),
        ((0, -1, 0), 0.1, 0),
        ((0, -1, 0), 0.3, 1),
        ((0, 1, 0), 0.7, 1),
        ((0, -1, 0), 0.5, 2),
        ((0, 1, 0), 1.2, 2),
    ]
    d = np.array([c[1] * v for c in cases])
    centre = np.array([c[0] for c in cases], float) * d[:, None]
    assert r.classify(centre, d).tolist() == [c[2] for c in cases]


@pytest.fixture(scope="module")
def tileset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # holes outside the data: the views here reach past its 5 km to the horizon, where a fill
    # would be flat tiles beyond the cache radius (drawn from an ancestor, as they should be,
    # and out of what the radii are tested for)
    return fbm_tileset(tmp_path_factory.mktemp("radii"), seed=11, fill="none")


def test_the_areas_reach_all_round_at_the_level_their_distance_asks_for(tileset: Path) -> None:
    with lodscape.open(tileset) as scene:
        b = scene.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        cam = scene.prepare(
            Camera(lon, lat, scene.tree.height_range[1] + 300, pitch=-20, width=320, height=180)
        )
        radii = radii_for(cam.position, cam.forward, np.zeros(3), 300.0, cam.far, RadiiOptions())
        memory, cache, counts = scene.view.areas(cam, radii)
        frame = set(scene.view.predict(cam))
    assert counts["area_memory"] > 0
    # all round: the areas hold chunks the frame (its frustum, looking north) does not
    assert len(set(memory) | set(cache)) > len(frame)
    assert set(memory) - frame
    assert not set(memory) & set(cache)


@pytest.mark.gl
@pytest.mark.parametrize("radii", [True, False], ids=["radii", "velocity only"])
def test_a_hovering_camera_that_turns_round_finds_its_tiles_there(
    tileset: Path, radii: bool
) -> None:
    """Hover for two seconds looking north, then look south: with the radii the tiles behind
    were classified into the memory area, decoded and uploaded while there was room, so the
    turn draws them at once; with the velocity alone (no motion, no prediction) it falls back."""
    from lodscape.flight import fly

    stream = StreamOptions(cache_mb=64, memory_mb=64, radii=RadiiOptions() if radii else None)
    opts = SceneOptions(gpu_budget_mb=64, stream=stream)
    with lodscape.open(tileset, opts, clock=SimClock()) as scene:
        b = scene.provider.bounds_merc
        from lodscape.geo.tiles import merc_to_lonlat

        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.top + b.bottom) / 2)
        )
        alt = scene.tree.height_range[1] + 150
        cams = [Camera(lon, lat, alt, heading=0, pitch=-25, width=320, height=180)] * 60
        cams += [Camera(lon, lat, alt, heading=180, pitch=-25, width=320, height=180)] * 3
        rows = fly(scene, iter(cams), 30.0)
    turn = rows[60]
    if radii:
        assert rows[59]["area_memory"] > 0
        assert rows[59]["units_gpu"] > 0
        assert turn["fallback_max"] <= 1, turn
    else:
        assert turn["fallback_max"] > 1, turn
