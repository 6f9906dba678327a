"""Routes: CSV (with and without times), GeoJSON lines, orbits and straight lines, and the
cameras that fly them."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lodscape.errors import LodscapeError
from lodscape.flight import cameras, line_route, orbit_route, read_route
from lodscape.geo.frames import geodetic_to_ecef


def test_csv_routes_with_and_without_times(tmp_path: Path) -> None:
    p = tmp_path / "r.csv"
    p.write_text("lat,lon,alt\n36.5,-84.2,1000\n36.5,-84.19,1000\n")
    r = read_route(p, speed=100.0)
    metres = np.linalg.norm(
        geodetic_to_ecef(-84.19, 36.5, 1000) - geodetic_to_ecef(-84.2, 36.5, 1000)
    )
    assert r.duration == pytest.approx(metres / 100.0)
    p.write_text("lon,lat,alt,time\n-84.2,36.5,1000,10\n-84.19,36.5,1200,40\n")
    r = read_route(p, speed=100.0)
    assert r.duration == pytest.approx(30.0)
    assert r.at(15.0)[2] == pytest.approx(1100.0)


def test_a_pitch_column_sets_each_cameras_pitch(tmp_path: Path) -> None:
    """From orbit straight down to the street looking ahead: the route says how far down."""
    p = tmp_path / "r.csv"
    p.write_text("lon,lat,alt,time,pitch\n-84.25,34,400000,0,-90\n-84.25,36.3,1400,10,-10\n")
    r = read_route(p, speed=100.0)
    pitches = [c.pitch for c in cameras(r, 1.0, 64, 48, pitch=-15.0)]
    assert pitches[0] == -90.0
    assert pitches[5] == pytest.approx(-50.0)
    assert pitches[-1] == -10.0
    # without one, the flight's pitch all along
    p.write_text("lon,lat,alt,time\n-84.25,34,400000,0\n-84.25,36.3,1400,10\n")
    assert {c.pitch for c in cameras(read_route(p, 100.0), 1.0, 64, 48, pitch=-15.0)} == {-15.0}


def test_geojson_lines(tmp_path: Path) -> None:
    p = tmp_path / "r.geojson"
    coords = [[7.0, 46.5, 3000], [7.05, 46.5, 3000], [7.05, 46.52, 3200]]
    p.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "LineString", "coordinates": coords},
                    }
                ],
            }
        )
    )
    r = read_route(p, speed=200.0)
    assert r.lon[-1] == 7.05
    assert r.alt[-1] == 3200
    # heading follows the route: east first, then north
    cams = list(cameras(r, 2.0, 64, 48))
    assert cams[0].heading == pytest.approx(90.0, abs=1.0)
    assert cams[-1].heading == pytest.approx(0.0, abs=2.0) or cams[-1].heading > 358.0


def test_orbits_look_at_their_centre_and_lines_go_straight() -> None:
    o = orbit_route(7.0, 46.5, 2000.0, 2500.0, speed=100.0)
    for cam in cameras(o, 0.05, 32, 24):
        to = geodetic_to_ecef(7.0, 46.5, o.target[2]) - cam.position  # type: ignore[index]
        assert np.dot(cam.forward, to / np.linalg.norm(to)) > 0.999
    line = line_route(7.0, 46.5, 7.1, 46.5, 3000.0, speed=300.0)
    headings = {round(c.heading) for c in cameras(line, 1.0, 32, 24)}
    assert headings <= {89, 90, 91}


@pytest.mark.parametrize(
    ("text", "suffix", "message"),
    [
        ("lon,lat\n1,2\n3,4\n", ".csv", "missing alt"),
        ("lon,lat,alt\n1,2,3\n", ".csv", "at least two"),
        ("lon,lat,alt\n1,2,3\nx,2,3\n", ".csv", "row 3"),
        ("lon,lat,alt,time\n1,2,3,5\n1.1,2,3,5\n", ".csv", "increase"),
        ("lon,lat,alt,pitch\n1,2,3,-95\n1.1,2,3,0\n", ".csv", "pitch must be within"),
        ("lon,lat,alt,pitch\n1,2,3,nan\n1.1,2,3,0\n", ".csv", "pitch must be within"),
        ('{"type": "Point", "coordinates": [1, 2]}', ".geojson", "LineString"),
        ('{"type": "LineString", "coordinates": [[1, 2], [3, 4]]}', ".geojson", "altitude"),
        ("{nope", ".geojson", "not JSON"),
    ],
)
def test_bad_routes_fail_in_one_line(tmp_path: Path, text: str, suffix: str, message: str) -> None:
    p = tmp_path / f"r{suffix}"
    p.write_text(text)
    with pytest.raises(LodscapeError, match=message) as info:
        read_route(p, speed=100.0)
    assert "\n" not in str(info.value)


class _Writer:
    """ffmpeg's stand-in: takes frames slowly, and breaks at ``fail_at`` (None: never)."""

    def __init__(self, fail_at: int | None) -> None:
        self.frames: list[bytes] = []
        self.fail_at = fail_at
        self.closed = False

    def send(self, frame: bytes) -> None:
        import time

        time.sleep(0.01)
        if self.fail_at is not None and len(self.frames) == self.fail_at:
            raise BrokenPipeError("ffmpeg went away")
        self.frames.append(frame)

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("threaded", [True, False])
def test_the_video_gets_every_frame_in_order_or_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, threaded: bool
) -> None:
    from lodscape import flight

    made: list[_Writer] = []

    def writer(path: Path, w: int, h: int, fps: float) -> tuple[_Writer, Path]:
        tmp = path.with_name(".v.tmp.mp4")
        tmp.write_bytes(b"partial")
        made.append(_Writer(made_fail[0]))
        return made[-1], tmp

    made_fail: list[int | None] = [None]
    monkeypatch.setattr(flight, "_video_writer", writer)
    monkeypatch.setattr(flight._Video, "THREADED", threaded)
    out = tmp_path / "v.mp4"
    frames = [np.full((4, 6, 3), i, np.uint8) for i in range(12)]

    def write() -> None:
        with flight._Video(out, 30.0) as v:
            for f in frames:
                v.send(f)
            v.commit()

    write()
    assert [fr[0] for fr in made[0].frames] == list(range(12))  # all, in order
    assert made[0].closed
    assert out.exists()
    # the encoder breaks at the fifth frame: the flight says so, and no file stays
    made_fail[0] = 4
    out.unlink()
    with pytest.raises(BrokenPipeError):
        write()
    assert not out.exists()
    assert not list(tmp_path.glob(".v.tmp*"))


def test_a_flight_reads_its_pictures_through_the_ring_in_order(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Through the ring of pixel-pack buffers a flight's video gets the same pictures, in the
    same order, as reading each when drawn; a flight cut short leaves none in the ring. (One
    scene flies the route first until a flight asks for nothing, so every tile is resident and
    each flight draws the same pictures.)"""
    import lodscape
    from lodscape import flight
    from lodscape.data import sample_dem_path
    from lodscape.stream import SimClock, StreamOptions

    route = flight.orbit_route(-84.25, 36.55, 2000.0, 2500.0, 400.0)
    cams = list(flight.cameras(route, 10.0, 64, 48))[:7]
    got: dict[int, list[bytes]] = {}

    def writer(path: Path, w: int, h: int, fps: float) -> tuple[_Writer, Path]:
        tmp = path.with_name(".v.tmp.mp4")
        tmp.write_bytes(b"partial")
        w_ = _Writer(None)
        got[flight.RING] = w_.frames
        return w_, tmp

    monkeypatch.setattr(flight, "_video_writer", writer)
    opts = lodscape.SceneOptions(stream=StreamOptions(), morph=False)
    with lodscape.open(sample_dem_path(), opts, clock=SimClock()) as scene:
        # a tile's TIN at each rung its distance asks is a load of its own: a flight may ask
        # for some the flight before drew from others while they came (the sample's route:
        # asks for nothing from the fourth flight with sixteen rungs, the fifth with
        # twenty-four)
        for _ in range(8):
            if sum(row["requested"] for row in flight.fly(scene, iter(cams), 10.0)) == 0:
                break
        else:
            pytest.fail("the route kept asking for tiles after eight flights")
        for ring in (0, 3, 2):
            monkeypatch.setattr(flight, "RING", ring)
            flight.fly(scene, iter(cams), 10.0, video=tmp_path / f"v{ring}.mp4")
        # the ring is empty afterwards: a plain render works and reads the distance too
        rgb, depth = scene.render(cams[0])
        assert depth.shape == rgb.shape[:2]
    assert len(got[0]) == len(cams)
    assert got[3] == got[0]
    assert got[2] == got[0]
    assert len(set(got[0])) > 1  # the pictures differ from frame to frame

    def stop(i: int) -> None:
        if i == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(flight, "RING", 3)
    with lodscape.open(sample_dem_path(), opts, clock=SimClock()) as scene:
        with pytest.raises(KeyboardInterrupt):
            flight.fly(scene, iter(cams), 10.0, video=tmp_path / "cut.mp4", on_frame=stop)
        assert not (tmp_path / "cut.mp4").exists()
        assert scene.drain() == []
        scene.render(cams[0])


def test_render_behind_returns_each_picture_ring_minus_one_frames_late() -> None:
    import lodscape
    from lodscape.data import sample_dem_path

    with lodscape.open(sample_dem_path()) as scene:
        cams = [scene.overview_camera(48, 32)]
        cams += [replace(cams[0], heading=float(h)) for h in (30, 60, 90)]
        direct = [scene.render(c)[0] for c in cams]
        late = [scene.render_behind(c, 3) for c in cams]
        assert late[0] is None
        assert late[1] is None
        assert np.array_equal(late[2], direct[0])
        assert np.array_equal(late[3], direct[1])
        with pytest.raises(RuntimeError, match="drain"):
            scene.render(cams[0])
        rest = scene.drain()
        assert len(rest) == 2
        assert np.array_equal(rest[0], direct[2])
        assert np.array_equal(rest[1], direct[3])
        with pytest.raises(ValueError, match="ring"):
            scene.render_behind(cams[0], 0)
