"""Imagery from elsewhere: OSM-style z/x/y servers over HTTP (paper 000), MBTiles files and tile
folders, behind one small fetch protocol (``fetch(z, x, y) -> bytes``).

The HTTP source goes through httpx with a connection limit, timeouts, retries with exponential
backoff on timeouts, connection errors and 5xx answers, a User-Agent naming lodscape, and a
persistent SQLite cache that keeps each tile with its validators: a fresh tile (Cache-Control
max-age or Expires) is served from the cache, a stale one is revalidated (If-None-Match,
If-Modified-Since) and a 304 refreshes it. A 404 is "no tile here" (not retried). An answer
that is not an image, or is cut short, is an error: never cached, retried later.
"""

from __future__ import annotations

import email.utils
import io
import os
import random
import re
import sqlite3
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from lodscape._sqlite import readonly_uri
from lodscape.errors import LodscapeError, SourceError

__all__ = [
    "DirectorySource",
    "HttpSource",
    "ImageryError",
    "ImageryFetcher",
    "MBTilesSource",
    "TileCache",
    "TileMissing",
    "decode_image",
    "open_image",
]

USER_AGENT = "lodscape/0.1 (terrain engine; +https://pypi.org/project/lodscape/)"
#: The most pixels an imagery tile may have (4096²): a PNG of 12000² is 450 KB on the wire and
#: 576 MB decoded. Larger tiles are refused from their header, before decoding.
MAX_TILE_PIXELS = 4096 * 4096
#: The largest imagery tile body taken over HTTP.
MAX_TILE_BYTES = 32 << 20


class ImageryError(LodscapeError):
    """An imagery tile that could not be had (after retries) or is not an image. ``kind`` names
    the failure for the counts and the warnings: "missing" (404, no row, no file), "http" (an
    error status), "not-image" (HTML, garbage, a truncated image), "cut-short" (the connection
    closed mid-body), "unreachable" (nothing listens), "timeout" (no answer in time)."""

    def __init__(self, message: str, kind: str = "error") -> None:
        super().__init__(message)
        self.kind = kind


class TileMissing(ImageryError):
    """The source has no tile there (HTTP 404, no row, no file)."""

    def __init__(self, message: str) -> None:
        super().__init__(message, "missing")


class ImageryFetcher(Protocol):
    #: For messages: the template, file or folder.
    name: str
    #: The levels the source has tiles at.
    min_zoom: int
    max_zoom: int

    def fetch(self, z: int, x: int, y: int) -> bytes:
        """The tile's stored bytes; b"" where the source has no data (transparent)."""
        ...

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        """What ``fetch`` gave as (size, size, 4) RGBA."""
        ...

    def covers(self, z: int, x: int, y: int) -> bool:
        """Whether the source has data over tile z/x/y (False: it is transparent there, not
        missing)."""
        ...

    def close(self) -> None: ...


def open_image(data: bytes, what: str) -> Any:
    """Pillow's lazy image of ``data`` (only its header read), refused when it is larger than
    ``MAX_TILE_PIXELS``: a decompression bomb never reaches the decoder."""
    import warnings

    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            # the size is judged below, against a tile's limit, not Pillow's 89 M pixels
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(io.BytesIO(data))
    except Image.DecompressionBombError as exc:
        raise ImageryError(f"{what}: {exc}; not decoded", "too-large") from None
    except UnidentifiedImageError:
        # Pillow's own message names its BytesIO, not the tile
        raise ImageryError(f"{what}: not an image (no format Pillow reads)", "not-image") from None
    w, h = im.size
    if w * h > MAX_TILE_PIXELS:
        im.close()
        raise ImageryError(
            f"{what}: a tile of {w}×{h} pixels (the most taken is {MAX_TILE_PIXELS:,} pixels, "
            "4096²); not decoded",
            "too-large",
        )
    return im


def _check_image(data: bytes, what: str) -> bytes:
    """The bytes, if Pillow reads them as a whole image of a sane size; else ImageryError."""
    try:
        with open_image(data, what) as im:
            im.load()
    except ImageryError:
        raise
    except Exception as exc:  # Pillow raises several unrelated classes on bad data
        raise ImageryError(
            f"{what}: not an image ({type(exc).__name__}: {exc})", "not-image"
        ) from None
    return data


def decode_image(data: bytes, size: int) -> NDArray[np.uint8]:
    """An encoded tile (PNG, JPEG, WebP; RGB, RGBA, grey or palette) as (size, size, 4) RGBA,
    its transparency kept; resampled with a Lanczos filter when its size differs. A tile over
    ``MAX_TILE_PIXELS`` is refused before decoding (ImageryError "too-large")."""
    from PIL import Image

    with open_image(data, "imagery tile") as im:
        rgba = im.convert("RGBA")
        if rgba.size != (size, size):
            rgba = rgba.resize((size, size), Image.Resampling.LANCZOS)
        return np.ascontiguousarray(np.asarray(rgba, dtype=np.uint8))


class TileCache:
    """A persistent tile cache: one SQLite file, safe to share between threads."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute(
                "CREATE TABLE IF NOT EXISTS tiles (url TEXT PRIMARY KEY, data BLOB NOT NULL, "
                "etag TEXT, last_modified TEXT, expires REAL NOT NULL)"
            )
        except (OSError, sqlite3.Error) as exc:
            # a cache folder that is a file, not writable, or a cache that is not SQLite
            folder = self.path.parent
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            if folder.exists() and not folder.is_dir():
                why = "it is a file, not a folder"
            raise SourceError(f"{folder}: cannot hold the imagery cache ({why})") from None

    def get(self, url: str) -> tuple[bytes, str | None, str | None, float] | None:
        with self._lock:
            row = self._db.execute(
                "SELECT data, etag, last_modified, expires FROM tiles WHERE url = ?", (url,)
            ).fetchone()
        return None if row is None else (bytes(row[0]), row[1], row[2], float(row[3]))

    def put(
        self, url: str, data: bytes, etag: str | None, modified: str | None, expires: float
    ) -> None:
        with self._lock:
            self._db.execute(
                "INSERT OR REPLACE INTO tiles VALUES (?, ?, ?, ?, ?)",
                (url, data, etag, modified, expires),
            )

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _expires(headers: Mapping[str, str], now: float, default: float) -> float:
    """When a response stops being fresh: Cache-Control max-age/no-cache, else Expires."""
    cc = str(headers.get("cache-control") or "").lower()
    if "no-store" in cc or "no-cache" in cc:
        return now
    m = re.search(r"max-age\s*=\s*(\d+)", cc)
    if m:
        return now + int(m.group(1))
    exp = headers.get("expires")
    if exp:
        try:
            dt = email.utils.parsedate_to_datetime(exp)
            return dt.timestamp()
        except (TypeError, ValueError):
            return now
    return now + default


class _Overdue(Exception):
    """A request still going at its tile's deadline; ``answered``: its answer had begun (a
    trickling server), else nothing came at all (a hung one)."""

    def __init__(self, answered: bool = False) -> None:
        super().__init__()
        self.answered = answered


#: The monotonic time by which this thread's request must be over (``at``), where one is set.
_DEADLINE = threading.local()


def _bounded(timeout: float | None) -> float | None:
    """A socket operation's timeout cut to this thread's request deadline."""
    at: float | None = getattr(_DEADLINE, "at", None)
    if at is None:
        return timeout
    left = at - time.monotonic()
    if left <= 0.0:
        import httpcore

        raise httpcore.ReadTimeout("the tile's deadline passed")
    return left if timeout is None else min(timeout, left)


class _DeadlineStream:
    """A network stream whose every read and write ends by the thread's request deadline, so a
    server trickling its headers a line at a time cannot hold the request thread past it."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return bytes(self._stream.read(max_bytes, _bounded(timeout)))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, _bounded(timeout))

    def close(self) -> None:
        self._stream.close()

    def start_tls(self, *args: Any, **kwargs: Any) -> _DeadlineStream:
        return _DeadlineStream(self._stream.start_tls(*args, **kwargs))

    def get_extra_info(self, info: str) -> Any:
        return self._stream.get_extra_info(info)


class _DeadlineBackend:
    """httpcore's network backend with ``_DeadlineStream`` connections."""

    def __init__(self, backend: Any) -> None:
        self._backend = backend

    def connect_tcp(self, *args: Any, **kwargs: Any) -> _DeadlineStream:
        return _DeadlineStream(self._backend.connect_tcp(*args, **kwargs))

    def connect_unix_socket(self, *args: Any, **kwargs: Any) -> _DeadlineStream:
        return _DeadlineStream(self._backend.connect_unix_socket(*args, **kwargs))

    def sleep(self, seconds: float) -> None:
        self._backend.sleep(seconds)


def _bound_by_deadlines(client: Any) -> None:
    """Give the client's connection pool ``_DeadlineBackend`` (httpx exposes no setting for a
    total deadline; where its internals differ, the request threads' wait still bounds a tile)."""
    pool = getattr(getattr(client, "_transport", None), "_pool", None)
    backend = getattr(pool, "_network_backend", None)
    if backend is not None:
        pool._network_backend = _DeadlineBackend(backend)  # type: ignore[union-attr]


class HttpSource:
    """An XYZ URL template, e.g. ``https://{s}.tile.example.org/{z}/{x}/{y}.png``."""

    def __init__(
        self,
        template: str,
        *,
        subdomains: str = "abc",
        timeout: float = 10.0,
        retries: int = 3,
        backoff: float = 0.25,
        max_connections: int = 8,
        cache: TileCache | None = None,
        default_max_age: float = 86400.0,
        min_zoom: int = 0,
        max_zoom: int = 19,
        deadline: float | None = None,
        check: Callable[[bytes, str], bytes] | None = None,
        accept: str | None = None,
    ) -> None:
        """``check`` says whether a body is a tile (raising ``ImageryError``; default: an
        image); ``accept`` is the Accept header sent (terrain servers want theirs)."""
        import httpx

        for field in ("{z}", "{x}", "{y}"):
            if field not in template:
                raise ImageryError(f"imagery URL {template!r} lacks {field}")
        self.name = template
        self.min_zoom = min_zoom
        self.max_zoom = max_zoom
        self.timeout = timeout
        #: Seconds one tile may take, retries included (None: no bound): with it, a server that
        #: never answers costs a tile one request's timeout, not one per retry.
        self.deadline = deadline
        self.template = template
        self.subdomains = subdomains or "a"
        self.retries = retries
        self.backoff = backoff
        self.cache = cache
        self.default_max_age = default_max_age
        self.check = check or _check_image
        headers = {"User-Agent": USER_AGENT}
        if accept is not None:
            headers["Accept"] = accept
        self._client = httpx.Client(
            timeout=httpx.Timeout(timeout, connect=min(timeout, 5.0)),
            limits=httpx.Limits(max_connections=max_connections),
            headers=headers,
            follow_redirects=True,
        )
        _bound_by_deadlines(self._client)
        self._requests = ThreadPoolExecutor(max_connections, thread_name_prefix="lodscape-http")
        self.requests = 0
        self.retried = 0

    def url(self, z: int, x: int, y: int) -> str:
        s = self.subdomains[(x + y) % len(self.subdomains)]
        return self.template.format(z=z, x=x, y=y, s=s)

    def fetch(self, z: int, x: int, y: int) -> bytes:
        import httpx

        url = self.url(z, x, y)
        now = time.time()
        cached = self.cache.get(url) if self.cache is not None else None
        if cached is not None and cached[3] > now:
            return cached[0]
        headers = {}
        if cached is not None:
            if cached[1]:
                headers["If-None-Match"] = cached[1]
            if cached[2]:
                headers["If-Modified-Since"] = cached[2]
        last, kind = "", "error"
        start = time.monotonic()
        tries = 0
        for attempt in range(self.retries + 1):
            if attempt:
                # exponential backoff with jitter, so many tiles do not retry in step
                pause = self.backoff * 2 ** (attempt - 1) * (0.5 + random.random())
                if self.deadline is not None and (
                    time.monotonic() - start + pause >= self.deadline
                ):
                    break  # the tile's time is up
                self.retried += 1
                time.sleep(pause)
            self.requests += 1
            tries += 1
            try:
                r, data = self._get(url, headers, start)
            except _Overdue as exc:
                if exc.answered:
                    last = f"no whole answer in {self.deadline:g} s (a trickling server)"
                else:
                    last = f"no answer in {self.deadline:g} s (the server hangs)"
                kind = "timeout"
                break  # the tile's time is up: no retry can finish sooner
            except httpx.TimeoutException:
                last, kind = f"no answer in {self.timeout:g} s", "timeout"
                continue
            except httpx.RemoteProtocolError as exc:
                # the server closed the connection before the whole body came
                last, kind = f"body cut short ({exc})", "cut-short"
                continue
            except httpx.TransportError as exc:
                last, kind = f"connection failed ({exc})", "unreachable"
                continue
            except httpx.HTTPError as exc:  # a body that cannot be decoded (bad gzip…)
                last, kind = f"body unreadable ({exc})", "cut-short"
                continue
            if r.status_code == 304 and cached is not None:
                expires = _expires(r.headers, time.time(), self.default_max_age)
                if self.cache is not None:
                    self.cache.put(url, cached[0], cached[1], cached[2], expires)
                return cached[0]
            if r.status_code == 404:
                raise TileMissing(f"{url}: no tile (404)")
            if r.status_code >= 500 or r.status_code == 429:
                last, kind = f"HTTP {r.status_code}", "http"
                continue
            if r.status_code != 200:
                raise ImageryError(f"{url}: HTTP {r.status_code}", "http")
            if data is None:
                last, kind = f"a body over {MAX_TILE_BYTES >> 20} MiB", "too-large"
                break
            try:
                self.check(data, url)
            except ImageryError as exc:
                last, kind = str(exc).split(": ", 1)[-1], exc.kind
                if kind == "too-large":
                    break  # the same tile again would be as large
                continue
            if self.cache is not None:
                self.cache.put(
                    url,
                    data,
                    r.headers.get("etag"),
                    r.headers.get("last-modified"),
                    _expires(r.headers, time.time(), self.default_max_age),
                )
            return data
        tried = "after 1 try" if tries == 1 else f"after {tries} tries"
        raise ImageryError(f"{url}: {last} {tried}", kind)

    def _get(self, url: str, headers: dict[str, str], start: float) -> tuple[Any, bytes | None]:
        """One GET: the response and its whole body (None when it is over ``MAX_TILE_BYTES``);
        ``_Overdue`` when the tile's deadline passes first.

        httpx's timeouts bound each read, so a server that trickles a few bytes every few
        seconds would hold a tile for minutes: with a deadline, the request runs on one of the
        source's request threads and is waited for only until the deadline (the body is read
        chunk by chunk and dropped there too; a request stuck in trickling headers ends with its
        per-read timeout or the server, on its thread, while the tile has already failed)."""
        answered: list[bool] = []  # set once the answer begins
        if self.deadline is None:
            return self._request(url, headers, start, self.timeout, answered)
        left = self.deadline - (time.monotonic() - start)
        if left <= 0.0:
            raise _Overdue()
        job = self._requests.submit(
            self._request, url, headers, start, min(self.timeout, left), answered
        )
        try:
            return job.result(timeout=left)
        except FutureTimeout:
            job.cancel()
            raise _Overdue(bool(answered)) from None

    def _request(
        self,
        url: str,
        headers: dict[str, str],
        start: float,
        timeout: float,
        answered: list[bool],
    ) -> tuple[Any, bytes | None]:
        import httpx

        _DEADLINE.at = None if self.deadline is None else start + self.deadline
        try:
            return self._stream(url, headers, start, timeout, answered)
        except httpx.TimeoutException:
            if self.deadline is not None and time.monotonic() - start >= self.deadline:
                raise _Overdue(bool(answered)) from None
            raise
        finally:
            _DEADLINE.at = None

    def _stream(
        self,
        url: str,
        headers: dict[str, str],
        start: float,
        timeout: float,
        answered: list[bool],
    ) -> tuple[Any, bytes | None]:
        with self._client.stream("GET", url, headers=headers, timeout=timeout) as r:
            answered.append(True)
            chunks: list[bytes] = []
            size = 0
            for chunk in r.iter_bytes():
                chunks.append(chunk)
                size += len(chunk)
                if size > MAX_TILE_BYTES:
                    return r, None
                if self.deadline is not None and time.monotonic() - start > self.deadline:
                    raise _Overdue(True)
            if self.deadline is not None and time.monotonic() - start > self.deadline:
                raise _Overdue(True)
            return r, b"".join(chunks)

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        return decode_image(data, size)

    def covers(self, z: int, x: int, y: int) -> bool:
        return True

    def close(self) -> None:
        self._requests.shutdown(wait=False, cancel_futures=True)
        self._client.close()
        if self.cache is not None:
            self.cache.close()


class MBTilesSource:
    """An MBTiles file's ``tiles`` table (rows counted from the south)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.name = os.fspath(path)
        if not os.path.exists(self.name):
            raise ImageryError(f"{self.name}: no such file")
        self._local = threading.local()
        uri = readonly_uri(self.name)
        try:
            with sqlite3.connect(uri, uri=True) as db:
                lo, hi = db.execute("SELECT MIN(zoom_level), MAX(zoom_level) FROM tiles").fetchone()
        except sqlite3.Error as exc:
            raise ImageryError(f"{self.name}: not an MBTiles file ({exc})") from None
        if hi is None:
            raise ImageryError(f"{self.name}: an MBTiles file with no tiles")
        self.min_zoom, self.max_zoom = int(lo), int(hi)
        #: Where it has tiles (its metadata's ``bounds``, Web Mercator), None: not said.
        self.bounds: tuple[float, float, float, float] | None = _mbtiles_bounds(uri)

    def fetch(self, z: int, x: int, y: int) -> bytes:
        db = getattr(self._local, "db", None)
        if db is None:
            try:
                db = self._local.db = sqlite3.connect(readonly_uri(self.name), uri=True)
                row = db.execute(
                    "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                    "AND tile_row = ?",
                    (z, x, (1 << z) - 1 - y),
                ).fetchone()
            except sqlite3.Error as exc:
                raise ImageryError(f"{self.name}: not an MBTiles file ({exc})") from None
        else:
            row = db.execute(
                "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                "AND tile_row = ?",
                (z, x, (1 << z) - 1 - y),
            ).fetchone()
        if row is None:
            raise TileMissing(f"{self.name}: no tile {z}/{x}/{y}")
        return _check_image(bytes(row[0]), f"{self.name} {z}/{x}/{y}")

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        return decode_image(data, size)

    def covers(self, z: int, x: int, y: int) -> bool:
        return self.bounds is None or _overlaps(self.bounds, z, x, y)

    def close(self) -> None:
        pass


class DirectorySource:
    """A folder of ``{z}/{x}/{y}.png`` (or .jpg, .jpeg, .webp) tiles, OSM rows."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.name = os.fspath(root)
        if not os.path.isdir(self.name):
            raise ImageryError(f"{self.name}: no such folder")
        levels = [int(p.name) for p in Path(self.name).iterdir() if p.name.isdigit()]
        if not levels:
            raise ImageryError(f"{self.name}: no z/x/y tile folders in it")
        self.min_zoom, self.max_zoom = min(levels), max(levels)

    def fetch(self, z: int, x: int, y: int) -> bytes:
        for ext in ("png", "jpg", "jpeg", "webp"):
            p = Path(self.name) / str(z) / str(x) / f"{y}.{ext}"
            if p.exists():
                return _check_image(p.read_bytes(), str(p))
        raise TileMissing(f"{self.name}: no tile {z}/{x}/{y}")

    def decode(self, data: bytes, size: int) -> NDArray[np.uint8]:
        return decode_image(data, size)

    def covers(self, z: int, x: int, y: int) -> bool:
        return True

    def close(self) -> None:
        pass


def _mbtiles_bounds(uri: str) -> tuple[float, float, float, float] | None:
    """An MBTiles file's ``bounds`` metadata (west,south,east,north degrees) in Web Mercator
    metres, or None where it has none that reads."""
    from lodscape.geo.tiles import lonlat_to_merc

    try:
        with sqlite3.connect(uri, uri=True) as db:
            row = db.execute("SELECT value FROM metadata WHERE name = 'bounds'").fetchone()
        w, s, e, n = (float(v) for v in str(row[0]).split(","))
    except (sqlite3.Error, TypeError, ValueError):
        return None
    if not (w < e and s < n):
        return None
    (left, right), (bottom, top) = lonlat_to_merc([w, e], [max(s, -85.05), min(n, 85.05)])
    return float(left), float(bottom), float(right), float(top)


def _overlaps(b: tuple[float, float, float, float], z: int, x: int, y: int) -> bool:
    from lodscape.geo.tiles import Tile, xy_bounds

    left, bottom, right, top = xy_bounds(Tile(x, y, z))
    return left < b[2] and right > b[0] and bottom < b[3] and top > b[1]
