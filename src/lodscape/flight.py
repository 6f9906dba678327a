"""Flights: a camera path (a route file, an orbit or a straight line) flown frame by frame on a
simulated clock, streaming as it goes, into an MP4 and per-frame statistics.

Every frame is rendered offline, however long that takes; the streamer's workers and uploads
get exactly the time a real-time viewer at the requested frame rate would have given them
(``SimClock``), so the statistics say what that viewer would have seen.
"""

from __future__ import annotations

import csv
import json
import math
import os
import queue
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from lodscape._tmp import temp_beside
from lodscape.errors import LodscapeError
from lodscape.geo.frames import ecef_to_geodetic, enu_basis, geodetic_to_ecef
from lodscape.lod.camera import Camera

__all__ = [
    "GLOBE_COLUMNS",
    "STAT_COLUMNS",
    "Route",
    "fly",
    "line_route",
    "orbit_route",
    "read_route",
]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Route:
    """Positions (lon°, lat°, alt m) at times (s): the camera's path, and where it looks."""

    times: F64
    lon: F64
    lat: F64
    alt: F64
    #: A point every camera looks at (an orbit's centre), or None to look along the path.
    target: tuple[float, float, float] | None = None
    #: Degrees below the horizon (negative) at each point, from a route's pitch column, or
    #: None: the flight's --pitch all along.
    pitch: F64 | None = None

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def at(self, t: float) -> tuple[float, float, float]:
        return (
            float(np.interp(t, self.times, self.lon)),
            float(np.interp(t, self.times, self.lat)),
            float(np.interp(t, self.times, self.alt)),
        )


def _timed(lon: F64, lat: F64, alt: F64, speed: float, name: str) -> F64:
    """Times along a polyline flown at ``speed`` m/s."""
    if not (math.isfinite(speed) and speed > 0.0):
        raise LodscapeError(f"--speed must be a positive number of m/s, got {speed}")
    p = geodetic_to_ecef(lon, lat, alt)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    times = np.concatenate([[0.0], np.cumsum(step)]) / speed
    if times[-1] <= 0.0:
        raise LodscapeError(f"{name}: the path has no length")
    return times


def read_route(path: str | os.PathLike[str], speed: float) -> Route:
    """A CSV (lon,lat,alt header, optional time column in seconds and pitch column in degrees)
    or a GeoJSON line (coordinates [lon, lat, alt]) as a route."""
    name = os.fspath(path)
    try:
        text = Path(name).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise LodscapeError(f"{name}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LodscapeError(f"{name}: cannot read ({exc})") from None
    pitch = None
    if name.lower().endswith((".geojson", ".json")):
        lon, lat, alt = _geojson(text, name)
        times = None
    else:
        lon, lat, alt, times, pitch = _csv(text, name)
        if pitch is not None and not (np.abs(pitch) <= 90.0).all():
            raise LodscapeError(f"{name}: pitch must be within -90..90 degrees")
    if lon.size < 2:
        raise LodscapeError(f"{name}: a route needs at least two points")
    if np.any(np.abs(lat) > 90.0) or not np.isfinite(np.stack([lon, lat, alt])).all():
        raise LodscapeError(f"{name}: coordinates must be finite lon, lat (within ±90) and alt")
    if times is None:
        times = _timed(lon, lat, alt, speed, name)
    else:
        times = times - times[0]
        if np.any(np.diff(times) <= 0.0):
            raise LodscapeError(f"{name}: the time column must increase from row to row")
    return Route(times, lon, lat, alt, pitch=pitch)


def _csv(text: str, name: str) -> tuple[F64, F64, F64, F64 | None, F64 | None]:
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise LodscapeError(f"{name}: empty route")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in ("lon", "lat", "alt") if c not in header]
    if missing:
        raise LodscapeError(
            f"{name}: the header needs lon, lat and alt columns (missing {', '.join(missing)})"
        )
    cols = [header.index(c) for c in ("lon", "lat", "alt")]
    extra = [c for c in ("time", "pitch") if c in header]
    cols += [header.index(c) for c in extra]
    values = []
    for number, row in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in row):
            continue
        try:
            values.append([float(row[c]) for c in cols])
        except (ValueError, IndexError):
            raise LodscapeError(f"{name}: row {number}: {','.join(row)!r} is not numbers") from None
    if not values:
        raise LodscapeError(f"{name}: the route has no points (a header and no rows)")
    a = np.array(values, dtype=np.float64)
    named = {c: a[:, 3 + i] for i, c in enumerate(extra)}
    return a[:, 0], a[:, 1], a[:, 2], named.get("time"), named.get("pitch")


def _geojson(text: str, name: str) -> tuple[F64, F64, F64]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise LodscapeError(f"{name}: not JSON ({exc.msg} at line {exc.lineno})") from None
    geom = doc
    if isinstance(doc, dict) and doc.get("type") == "FeatureCollection":
        feats = doc.get("features") or []
        geom = feats[0] if feats else {}
    if isinstance(geom, dict) and geom.get("type") == "Feature":
        geom = geom.get("geometry") or {}
    if not isinstance(geom, dict) or geom.get("type") not in ("LineString", "MultiLineString"):
        raise LodscapeError(f"{name}: expected a GeoJSON LineString (or a feature holding one)")
    coords = geom.get("coordinates") or []
    if geom["type"] == "MultiLineString":
        coords = [c for part in coords for c in part]
    try:
        a = np.array(coords, dtype=np.float64)
    except (TypeError, ValueError):
        raise LodscapeError(f"{name}: coordinates must be [lon, lat, alt] numbers") from None
    if a.ndim != 2 or a.shape[1] < 3:
        raise LodscapeError(f"{name}: every coordinate needs an altitude: [lon, lat, alt]")
    return a[:, 0], a[:, 1], a[:, 2]


def orbit_route(lon: float, lat: float, radius: float, alt: float, speed: float) -> Route:
    """A circle of ``radius`` metres around (lon, lat) at ``alt``, looking at its centre."""
    if not (radius > 0.0 and math.isfinite(radius)):
        raise LodscapeError(f"--orbit radius must be positive, got {radius}")
    a = np.linspace(0.0, 2.0 * math.pi, 361)
    east, north = radius * np.sin(a), radius * np.cos(a)
    basis = enu_basis(lon, lat)
    centre = geodetic_to_ecef(lon, lat, alt)
    p = centre + east[:, None] * basis[0] + north[:, None] * basis[1]
    plon, plat, _ = ecef_to_geodetic(p)
    palt = np.full(a.size, alt)
    times = _timed(plon, plat, palt, speed, "--orbit")
    return Route(times, plon, plat, palt, target=(lon, lat, alt - 2.0 * radius / 3.0))


def line_route(
    lon1: float, lat1: float, lon2: float, lat2: float, alt: float, speed: float
) -> Route:
    """A straight line at ``alt`` from the first point to the second."""
    lon = np.linspace(lon1, lon2, 64)
    lat = np.linspace(lat1, lat2, 64)
    altv = np.full(64, float(alt))
    return Route(_timed(lon, lat, altv, speed, "--line"), lon, lat, altv)


def cameras(
    route: Route,
    fps: float,
    width: int,
    height: int,
    *,
    pitch: float = -15.0,
    fov: float = 60.0,
    duration: float | None = None,
) -> Iterator[Camera]:
    """One camera per frame: along the route, looking where it goes (or at its target), at the
    route's own pitch where it has one, else ``pitch``."""
    end = route.duration if duration is None else min(duration, route.duration)
    frames = max(1, math.floor(end * fps) + 1)
    for i in range(frames):
        t = i / fps
        lon, lat, alt = route.at(t)
        if route.target is not None:
            yield Camera.looking_at(
                lon, lat, alt, route.target, fov_y=fov, width=width, height=height
            )
            continue
        # the direction of travel: towards where the route will be a moment later
        here = (lon, lat, alt)
        ahead = route.at(min(t + 1.0, route.duration))
        # at the route's end there is no ahead: the direction it came from
        a, b = (here, ahead) if ahead != here else (route.at(max(t - 1.0, 0.0)), here)
        e, n, _ = enu_basis(lon, lat) @ (geodetic_to_ecef(*b) - geodetic_to_ecef(*a))
        heading = math.degrees(math.atan2(e, n)) % 360.0
        p = pitch if route.pitch is None else float(np.interp(t, route.times, route.pitch))
        yield Camera(lon, lat, alt, heading=heading, pitch=p, fov_y=fov, width=width, height=height)


STAT_COLUMNS = (
    "frame",
    "time_s",
    "draw_ms",
    "frame_cpu_ms",
    "over_budget",
    "stall_ms",
    "tiles",
    "triangles",
    "max_sse_px",
    "fallback_max",
    "gpu_bytes",
    "memory_bytes",
    "cache_bytes",
    "requested",
    "fetched",
    "decoded",
    "uploaded",
    "failed",
    "retried",
    "cache_hits",
    "memory_hits",
    "in_flight",
    # imagery layers: tiles drawn with an ancestor's layer tile or none, failed layer tiles
    "layer_fallbacks",
    "imagery_failed",
    # the terrain server's failed tiles (retried; a coarser tile or the ellipsoid drawn)
    "terrain_failed",
    # a tile server's HTTP requests and the HTTP client's own retries, since the flight began
    "http_requests",
    "http_retries",
    # the city's objects drawn (0 without a city)
    "city_objects_drawn",
    # bytes fetched from the source (disk, a server) this frame
    "fetched_bytes",
    # paper 004: chunks in the memory and cache areas at the last classification, and the
    # resource units they hold by state (on disk, cached, in memory, on the GPU)
    "area_memory",
    "area_cache",
    "units_disk",
    "units_cached",
    "units_memory",
    "units_gpu",
)

#: The columns of ``fly --globe --stats``: the terrain's (its tiles where they are drawn, and
#: the streaming figures of its tiles and of the globe's imagery together), then the globe's:
#: its facets, deepest level, vertices moved onto coarser edges, on-screen error, selection
#: time, the pixels the terrain's own tiles drew, and the imagery tiles drawn, drawn from an
#: ancestor more than one level up, and not drawn for want of any.
GLOBE_COLUMNS = (
    *STAT_COLUMNS,
    "facets",
    "max_level",
    "extended",
    "screen_error_px",
    "select_ms",
    "terrain_pixels",
    "imagery_tiles",
    "imagery_fallbacks",
    "imagery_missing",
)


class FlightRows(Sequence[dict[str, float]]):
    """A flight's per-frame statistics, one row of ``columns`` a frame, held as one float64
    array (272 bytes a frame for the 34 columns; a dict a frame took 1.8 KB, which a long flight
    kept growing by 50 KB a second). Rows read back as dicts, integer columns as ints."""

    def __init__(self, columns: tuple[str, ...]) -> None:
        self.columns = columns
        self._data = np.zeros((64, len(columns)))
        self._ints = np.zeros(len(columns), bool)
        self._n = 0

    def append(self, row: Mapping[str, float]) -> None:
        if self._n == 0:
            self._ints = np.array([isinstance(row.get(c, 0), int) for c in self.columns])
        if self._n == len(self._data):
            self._data = np.concatenate([self._data, np.zeros_like(self._data)])
        self._data[self._n] = [float(row.get(c, 0)) for c in self.columns]
        self._n += 1

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> dict[str, float]: ...

    @overload
    def __getitem__(self, i: slice) -> list[dict[str, float]]: ...

    def __getitem__(self, i: int | slice) -> dict[str, float] | list[dict[str, float]]:
        if isinstance(i, slice):
            return [self._row(j) for j in range(*i.indices(self._n))]
        if not -self._n <= i < self._n:
            raise IndexError(i)
        return self._row(i % self._n)

    def _row(self, j: int) -> dict[str, float]:
        values = self._data[j].tolist()
        return {
            c: (int(v) if k else v)
            for c, v, k in zip(self.columns, values, self._ints.tolist(), strict=True)
        }


def fly(
    scene: Any,
    frames: Iterator[Camera],
    fps: float,
    *,
    video: Path | None = None,
    stats: Path | None = None,
    on_frame: Callable[[int], None] | None = None,
) -> FlightRows:
    """Render every camera on a simulated clock; write the MP4 (whole or not at all) and the
    statistics CSV (a row as each frame is drawn, flushed: a flight that is killed keeps the
    rows of its frames). Returns the per-frame statistics.

    ``scene`` is a ``Scene`` or a ``lodscape.globe.Globe`` streaming on a ``SimClock``: one
    frame loop for both; its rows have the scene's ``columns``."""
    from lodscape.stream import SimClock

    clock = scene.clock
    if not scene.streaming or not isinstance(clock, SimClock):
        raise ValueError(
            "fly needs a Scene or Globe streaming on a SimClock (Scene(..., clock=SimClock()))"
        )
    columns = scene.columns
    # the pictures come through the pixel-pack ring, RING - 1 frames late
    ring = 0 if video is None else RING
    budget = 1000.0 / fps
    rows = FlightRows(columns)
    with _Video(video, fps) as out, _StatsFile(stats, columns) as csv_rows:
        try:
            for i, cam in enumerate(frames):
                if ring:
                    late = scene.render_behind(cam, ring)
                    if late is not None:
                        out.send(late)
                else:
                    # no video: the picture is read (part of a frame's cost), not the distance
                    rgb, _ = scene.render(cam, depth=False)
                    out.send(rgb)
                d = scene.frame_stats()
                row = {c: d.get(c, 0) for c in columns}
                row.update(
                    frame=i,
                    time_s=round(clock.now(), 4),
                    draw_ms=d["draw_ms"],
                    over_budget=int(d.get("frame_cpu_ms", 0.0) > budget),
                )
                rows.append(row)
                csv_rows.write(rows[-1])
                clock.advance(1.0 / fps)
                if on_frame is not None:
                    on_frame(i)
            for late in scene.drain() if ring else ():
                out.send(late)
        finally:
            if ring:
                scene.drain()  # a flight cut short leaves nothing in the ring
        out.commit()
    return rows


class _StatsFile:
    """A flight's statistics CSV, a row written and flushed as each frame is drawn (``path``
    None: none); created at the first frame, so a flight that fails before it leaves none."""

    def __init__(self, path: Path | None, columns: tuple[str, ...]) -> None:
        self.path, self.columns = path, columns
        self._file: Any = None
        self._writer: Any = None

    def __enter__(self) -> _StatsFile:
        return self

    def write(self, row: Mapping[str, float]) -> None:
        if self.path is None:
            return
        if self._writer is None:
            try:
                self._file = self.path.open("w", newline="")
            except OSError as exc:
                raise LodscapeError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
            self._writer = csv.DictWriter(self._file, fieldnames=list(self.columns))
            self._writer.writeheader()
        self._writer.writerow(row)
        self._file.flush()

    def __exit__(self, *exc: object) -> None:
        if self._file is not None:
            self._file.close()


#: Pixel-pack buffers a flight's pictures pass through (0: each read when drawn).
RING = 3


class _Video:
    """An MP4 written under a temporary name (opened at the first frame, which sets its size)
    and put in place by ``commit``; left unfinished, nothing of it stays. ``path`` None: no
    video.

    Frames go to the encoder on a thread of their own through a queue of ``AHEAD`` frames, so
    the next frame renders while ffmpeg takes the last ones (paper 001's triple buffering, on
    the encoder's side: the renderer waits only when three frames are still queued)."""

    AHEAD = 3
    #: False: each frame written before the next renders (what a flight did before).
    THREADED = True

    def __init__(self, path: Path | None, fps: float) -> None:
        self.path, self.fps = path, fps
        self.writer: Any = None
        self.tmp: Path | None = None
        self._queue: queue.Queue[bytes | None] | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def send(self, rgb: NDArray[np.uint8]) -> None:
        if self.path is None:
            return
        if self.writer is None:
            self.writer, self.tmp = _video_writer(self.path, rgb.shape[1], rgb.shape[0], self.fps)
            if self.THREADED:
                self._queue = queue.Queue(self.AHEAD)
                self._thread = threading.Thread(
                    target=self._encode, name="lodscape-video", daemon=True
                )
                self._thread.start()
        self._raise()
        frame = np.ascontiguousarray(rgb).tobytes()
        if self._queue is None:  # each frame in turn
            self.writer.send(frame)
        else:
            self._queue.put(frame)

    def _encode(self) -> None:
        assert self._queue is not None
        while True:
            frame = self._queue.get()
            if frame is None:
                return
            if self._error is None:
                try:
                    self.writer.send(frame)
                except BaseException as exc:  # said by the next send or the commit
                    self._error = exc

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def _stop(self) -> None:
        if self._thread is not None and self._queue is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    def commit(self) -> None:
        self._stop()
        self._raise()
        if self.writer is not None:
            self.writer.close()
            self.writer = None
            assert self.tmp is not None
            assert self.path is not None
            os.replace(self.tmp, self.path)
            self.tmp = None

    def __enter__(self) -> _Video:
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop()
        if self.writer is not None:
            self.writer.close()
        if self.tmp is not None and self.tmp.exists():
            self.tmp.unlink()


def _video_writer(path: Path, width: int, height: int, fps: float) -> tuple[Any, Path]:
    import imageio_ffmpeg

    if width % 2 or height % 2:
        raise LodscapeError(
            f"an MP4 (H.264, 4:2:0) needs an even width and height, got {width}x{height}"
        )
    tmp = temp_beside(path, path.suffix)
    # imageio-ffmpeg starts ffmpeg with preexec_fn=os.setpgrp (to keep Ctrl-C from it), which
    # runs Python between fork and exec: with other threads alive (the stream's workers, an
    # imagery server's requests) the child can hang for good on a lock one of them held (its
    # issue #58; seen here in CI). Without it ffmpeg shares Ctrl-C, and the unfinished file is
    # removed as before.
    os.environ.setdefault("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1")
    writer = imageio_ffmpeg.write_frames(
        str(tmp),
        (width, height),
        fps=fps,
        codec="libx264",
        pix_fmt_out="yuv420p",
        macro_block_size=1,
        quality=7,
        ffmpeg_log_level="error",
    )
    writer.send(None)
    return writer, tmp
