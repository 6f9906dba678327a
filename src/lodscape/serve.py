"""``lodscape serve``: a tileset over HTTP (aiohttp) for Cesium, MapLibre or any tile client.

Routes:
- ``/``: a page that shows the tileset in CesiumJS (terrain, imagery, buildings), its scripts
  from ``--viewer-js`` (a URL, or a local build of CesiumJS served under ``/viewer-js/``);
  ``/maplibre``: a page that shows it in MapLibre GL JS (the imagery over the Terrarium
  terrain), its scripts from ``--maplibre-js`` (likewise, under ``/maplibre-js/``);
  ``/index.json``: what is served, by relative URL;
- ``/layer.json``: the Cesium terrain layer (TMS rows, as ``lodscape export --cesium``), in the
  geographic tiling (EPSG:4326, to the poles; its tiles made from the stored ones as they are
  asked for) or, with ``--tiling mercator``, the stored Web Mercator one;
- ``/{z}/{x}/{y}.terrain``: quantized-mesh-1.0 with octvertexnormals, gzipped where the client
  accepts it, plain otherwise; filler tiles of the ellipsoid above the tileset's roots;
- ``/imagery/{z}/{x}/{y}.png``: the imagery (OSM rows; alpha 0 where there is no data, and a
  transparent tile for one the TileJSON's range holds and the tileset does not), and
  ``/imagery.json`` its TileJSON (levels, bounds, attribution; for MapLibre, Leaflet or any
  XYZ client);
- ``/terrarium/{z}/{x}/{y}.png``: the terrain as Terrarium PNG (``store.pmtiles.TerrariumTiles``:
  levels 0 to the data's own, no-data at the fill's height with alpha 0), and
  ``/terrarium.json`` its TileJSON (MapLibre's raster-dem source, deck.gl, pydeck);
- ``/3dtiles/tileset.json`` and ``/3dtiles/{i}.glb``: the stored cities' buildings as 3D Tiles
  1.1, when the tileset holds a city (as ``city add`` made and stored them): groups of box
  models, each replaced by its full buildings up close.

Every answer carries CORS headers and a strong ETag of the bytes sent (the gzipped and the
plain body differ, and so do their tags; ``If-None-Match`` with a list, weak tags or ``*`` is
honoured with 304, which carries ``Vary`` too). JSON and glTF are gzipped when the client's
``Accept-Encoding`` allows gzip (q-values read: ``gzip;q=0`` refuses it). A path that is not one
of these exactly, with ASCII numbers in range and without leading zeros, is 404: nothing outside
the tileset can be named, and no tile has two names.

SQLite reads run on a pool of threads, each with its own read-only connection, never on the
event loop: a request never waits for another's read, and a writer (``city add`` keeps a
write-ahead log) never blocks the readers.

The file is watched (its and its log's inode, size and time, looked at no more than twice a
second): a file renamed into place, or a city added or removed, is served from the next request
on (the answers kept in memory, the layer and the 3D Tiles made again); a file that is not a
complete tileset at that moment (a build writing it) leaves the last one served, said once.
A connection must send its request's headers within ``HEADER_TIMEOUT`` seconds of opening (or of
its last answer): one that trickles them, or holds them half-sent, is closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import hashlib
import json
import logging
import mimetypes
import os
import re
import sqlite3
import sys
import threading
import time
from collections.abc import Awaitable, Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from lodscape._lru import ByteLRU
from lodscape.errors import LodscapeError
from lodscape.store.export import ImageryTiles, cesium_layer, geographic_layer
from lodscape.store.geographic import TILINGS, available_tiles, geographic_tile
from lodscape.store.manifest import connect_readonly
from lodscape.store.pmtiles import TerrariumTiles
from lodscape.store.quantized_mesh import ungzip
from lodscape.store.tileset import TilesetProvider

if TYPE_CHECKING:
    from aiohttp import web

__all__ = ["HeaderDeadlines", "TileService", "make_app", "run", "serve"]

CORS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
    "Access-Control-Allow-Headers": "*",
    "Access-Control-Expose-Headers": "ETag, Content-Encoding, Content-Length",
}
#: Deepest level any route accepts (Web Mercator tiles stop being meaningful well before).
MAX_ZOOM = 30
#: Threads reading the tileset (each with its own SQLite connection).
READERS = 4
#: Tile bytes kept in memory, answered from the event loop without a thread hop (a tileset's
#: tiles never change once built; a city add touches only the city's tables).
HOT_BYTES = 64 << 20
#: Seconds a connection has to send a request's headers (nginx's client_header_timeout is 60).
HEADER_TIMEOUT = 10.0
#: Seconds between looks at the file for a change.
WATCH_EVERY = 0.5

T = TypeVar("T")


def _file_key(path: Path) -> tuple[int, ...] | None:
    """What changes when the file is replaced or written: its and its log's identity, size and
    time (None: no file there now)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    key = (st.st_ino, st.st_dev, st.st_size, st.st_mtime_ns)
    try:
        wal = os.stat(str(path) + "-wal")
        return (*key, wal.st_size, wal.st_mtime_ns)
    except OSError:
        return key


class TileService:
    """The tileset's bytes by route, read-only; safe from the server's event loop."""

    def __init__(self, path: str | Path, tiling: str = "geographic") -> None:
        if tiling not in TILINGS:
            raise LodscapeError(f"tiling {tiling!r}: expected one of {', '.join(TILINGS)}")
        self.path = Path(path)
        self.tiling = tiling
        self._local = threading.local()
        self._lock = threading.RLock()  # a reader thread may come back for its connection
        self._connections: list[sqlite3.Connection] = []
        self._pool = ThreadPoolExecutor(READERS, thread_name_prefix="lodscape-serve")
        #: Counts the versions of the file served; a reader's connection is to one of them.
        self.generation = 0
        self._key = _file_key(self.path)
        self._looked = time.monotonic()
        self._said: tuple[int, ...] | None = None
        self._load()  # a file that is not a complete tileset fails here

    def _load(self) -> None:
        """Open the file as it is now (``TilesetError`` if it is not a complete tileset)."""
        provider = TilesetProvider(self.path)  # refuses what is not a complete tileset
        # the readers' connections opened now, to this file: a later rename or overwrite of
        # the path leaves them reading it until the next load
        conns: list[sqlite3.Connection] = []
        try:
            for _ in range(READERS):
                conns.append(connect_readonly(self.path))
                conns[-1].execute("SELECT count(*) FROM sqlite_master").fetchone()
            available: dict[int, set[tuple[int, int]]] = {}
            if self.tiling == "geographic":
                available = available_tiles(conns[0])
                flat: dict[tuple[int, int, int], bytes] = {}
                layer = geographic_layer(conns[0], provider.manifest, self.path.stem, available)
            else:
                layer, flat = cesium_layer(conns[0], provider.manifest, self.path.stem)
            has_city = bool(provider.cities())
            imagery = ImageryTiles(
                self._db, int(provider.manifest.get("tile_size", 256)), db=conns[0]
            )
        except BaseException:
            provider.close()
            for db in conns:
                db.close()
            raise
        old = getattr(self, "_provider", None)
        with self._lock:
            for db in getattr(self, "_free", []):
                db.close()  # the last version's, never taken by a reader
            self._free = conns
            provider.read_with(self._db)  # its tiles from the file loaded, as the others
            self._provider = provider
            self.manifest = provider.manifest
            self._flat = flat
            self._available = available
            self._imagery = imagery
            self._terrarium = TerrariumTiles(provider)
            self.layer = json.dumps(layer, indent=1).encode()
            self._tiles3d: tuple[bytes, list[bytes]] | None = None
            self.has_city = has_city
            self._hot: ByteLRU[tuple[str, int, int, int], bytes | None] = ByteLRU()
            self.generation += 1
        if old is not None:
            old.close()

    async def watch(self) -> None:
        """Serve the file as it is now, where it changed since the last look (event loop)."""
        now = time.monotonic()
        if now - self._looked < WATCH_EVERY:
            return
        self._looked = now
        key = _file_key(self.path)
        if key is None or key == self._key:
            return
        try:
            await self.run(self._load)
        except LodscapeError as exc:
            if self._said != key:  # said once for each state of the file
                self._said = key
                print(f"lodscape: serve: {exc}; still serving the last tileset", file=sys.stderr)
            return
        self._key = key

    def _db(self) -> sqlite3.Connection:
        """This thread's read-only connection, to the file as last loaded (one of the
        connections opened by the load: a thread per connection)."""
        db: sqlite3.Connection | None = getattr(self._local, "db", None)
        if db is not None and getattr(self._local, "generation", 0) == self.generation:
            return db
        with self._lock:
            if db is not None:
                self._connections.remove(db)
                db.close()  # to the file as it was
            self._local.generation = self.generation
            db = self._local.db = self._free.pop()
            self._connections.append(db)
        return db

    async def run(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` on a reader thread, awaited from the event loop."""
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    async def tile(self, kind: str, z: int, x: int, y: int) -> bytes | None:
        """``terrain`` (TMS row) or ``imagery`` (OSM row) bytes, from memory where they were read
        lately, else from a reader thread. Event loop only (the memory is not locked)."""
        key = (kind, z, x, y)
        if key in self._hot:
            return self._hot.get(key)
        fn = {"terrain": self.terrain, "imagery": self.imagery, "terrarium": self.terrarium}[kind]
        data = await self.run(fn, z, x, y)
        self._hot.put(key, data, 64 + (0 if data is None else len(data)))
        self._hot.shrink(HOT_BYTES)
        return data

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        with self._lock:
            for db in [*self._connections, *self._free]:
                db.close()
            self._connections.clear()
            self._free = []
        self._provider.close()

    def terrain(self, z: int, x: int, tms: int) -> bytes | None:
        """Gzipped quantized-mesh of tile z/x/TMS row, or None."""
        if self.tiling == "geographic":
            if (x, tms) not in self._available.get(z, ()):
                return None
            zmax = int(self.manifest["levels"]["zmax"])
            made = geographic_tile(self._provider, z, x, tms, zmax)
            return None if made is None else gzip.compress(made, mtime=0)
        if not (0 <= z <= MAX_ZOOM and 0 <= x < (1 << z) and 0 <= tms < (1 << z)):
            return None
        flat = self._flat.get((z, x, tms))
        if flat is not None:
            return gzip.compress(flat, mtime=0)
        row = (
            self._db()
            .execute(
                "SELECT data FROM terrain WHERE z = ? AND x = ? AND y = ?",
                (z, x, (1 << z) - 1 - tms),
            )
            .fetchone()
        )
        return None if row is None else bytes(row[0])

    def imagery(self, z: int, x: int, y: int) -> bytes | None:
        """PNG of imagery tile z/x/y (OSM rows) of the advertised range (``ImageryTiles``: the
        stored ones, overviews above them, transparent ones where no data is); else None."""
        if not (0 <= z <= MAX_ZOOM and 0 <= x < (1 << z) and 0 <= y < (1 << z)):
            return None
        return self._imagery.tile(z, x, y)

    def terrarium(self, z: int, x: int, y: int) -> bytes | None:
        """Terrarium PNG of tile z/x/y (OSM rows) over the data, levels 0 to the data's own;
        else None."""
        if not (0 <= z <= MAX_ZOOM and 0 <= x < (1 << z) and 0 <= y < (1 << z)):
            return None
        if not self._terrarium.contains(z, x, y):
            return None
        return self._terrarium.tile(z, x, y)

    def terrarium_tilejson(self, base: str) -> dict[str, object]:
        """The Terrarium tiles' TileJSON (for MapLibre's raster-dem source, deck.gl, pydeck),
        its tiles under ``base``."""
        t = self._terrarium
        w, s, e, n = t.bounds
        meta = t.metadata(self.path.stem)
        return {
            "tilejson": "3.0.0",
            "name": str(meta["name"]),
            "description": str(meta["description"]),
            "attribution": str(meta["attribution"]),
            "scheme": "xyz",
            "format": "png",
            "encoding": "terrarium",
            "tileSize": 256,
            "tiles": [base + "/terrarium/{z}/{x}/{y}.png"],
            "vector_layers": [],
            "minzoom": 0,
            "maxzoom": t.maxzoom,
            "bounds": [w, s, e, n],
            "center": [(w + e) / 2.0, (s + n) / 2.0, t.maxzoom],
            "fill": t.fill,
            "nodata_height": t.nodata_height,
        }

    def tilejson(self, base: str) -> dict[str, object]:
        """The imagery's TileJSON, its tiles under ``base`` (scheme and host)."""
        from lodscape.store.export import imagery_tilejson

        return imagery_tilejson(self._db(), self.path.stem, base + "/imagery/{z}/{x}/{y}.png")

    def tiles3d(self) -> tuple[bytes, list[bytes]] | None:
        """(tileset.json, glb contents) of the stored cities, or None without a city."""
        if not self.has_city:
            return None
        with self._lock:
            if self._tiles3d is None:
                from lodscape.store.city_tiles import city_tiles

                # as city add stored them (made now only for a city stored without them)
                self._tiles3d = city_tiles(self._provider)
            return self._tiles3d


def accepts_gzip(header: str) -> bool:
    """Whether an ``Accept-Encoding`` header allows gzip (RFC 9110 §12.5.3: q-values, ``*``,
    ``identity``; ``gzip;q=0`` refuses it, ``nogzip`` does not name it)."""
    gz = star = None
    for part in header.split(","):
        name, _, params = part.strip().partition(";")
        name = name.strip().lower()
        q = 1.0
        for param in params.split(";"):
            key, _, value = param.strip().partition("=")
            if key.strip().lower() == "q":
                try:
                    q = float(value)
                except ValueError:
                    q = 0.0
        if name in ("gzip", "x-gzip"):
            gz = q if gz is None else max(gz, q)
        elif name == "*":
            star = q
    if gz is not None:
        return gz > 0.0
    return star is not None and star > 0.0


def etag_matches(header: str, etag: str) -> bool:
    """Whether ``If-None-Match`` names ``etag``: ``*``, or a list of (weak or strong) tags,
    compared weakly as RFC 9110 §13.1.2 has it for GET."""
    if header.strip() == "*":
        return True
    tags = [t.strip() for t in header.split(",")]
    return any(t.removeprefix("W/") == etag for t in tags if t)


#: Route numbers: ASCII digits, no leading zero (``\d`` takes any Unicode digit, and ``int``
#: reads fullwidth and Devanagari ones: ``/１２/…`` and ``/12/01126/…`` named real tiles).
_NUMBER = r"(?:0|[1-9][0-9]{0,9})"


class HeaderDeadlines:
    """Connections that owe a request's headers, and by when: from their opening, and again
    from each answer (a keep-alive connection's next request). ``sweep`` closes the late."""

    def __init__(self, timeout: float = HEADER_TIMEOUT) -> None:
        self.timeout = timeout
        self._due: dict[Any, float] = {}
        #: Connections closed for want of headers in time.
        self.closed = 0

    def waiting(self, transport: Any) -> None:
        self._due[transport] = time.monotonic() + self.timeout

    def started(self, transport: Any) -> None:
        self._due.pop(transport, None)

    def sweep(self) -> None:
        now = time.monotonic()
        for transport, due in list(self._due.items()):
            if transport.is_closing():
                del self._due[transport]
            elif now >= due:
                del self._due[transport]
                self.closed += 1
                transport.abort()

    def protocol(self, factory: Callable[[], Any]) -> Callable[[], asyncio.Protocol]:
        """``factory``'s protocols (aiohttp's request handlers), each watched from its
        connection's opening."""
        return lambda: _Watched(factory(), self)


class _Watched(asyncio.Protocol):
    """A protocol passing every event to ``inner``, its connection put under a header deadline
    as it opens (aiohttp's handlers have slots: they cannot be given a hook of their own)."""

    def __init__(self, inner: Any, deadlines: HeaderDeadlines) -> None:
        self.inner, self.deadlines = inner, deadlines

    def connection_made(self, transport: Any) -> None:
        self.inner.connection_made(transport)
        self.deadlines.waiting(transport)

    def data_received(self, data: bytes) -> None:
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        out: bool | None = self.inner.eof_received()
        return out

    def connection_lost(self, exc: Exception | None) -> None:
        self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


_HOST = re.compile(r"^[A-Za-z0-9.\-]+(:\d{1,5})?$|^\[[0-9A-Fa-f:.]+\](:\d{1,5})?$")


def public_base(
    scheme: str, host: str, headers: Mapping[str, str], public_url: str | None = None
) -> str:
    """The scheme and host a client reaches the server by: ``public_url`` where given, else
    what a reverse proxy says (``X-Forwarded-Proto``, ``X-Forwarded-Host``: the first, nearest
    the client, of a list; values that are not a scheme or a host name are ignored), else the
    request's own."""
    if public_url:
        return public_url.rstrip("/")
    proto = headers.get("X-Forwarded-Proto", "").split(",")[0].strip().lower()
    forwarded = headers.get("X-Forwarded-Host", "").split(",")[0].strip()
    if proto not in ("http", "https"):
        proto = scheme
    if not _HOST.match(forwarded):
        forwarded = host
    return f"{proto}://{forwarded}"


#: Where the viewer page loads CesiumJS from by default (the npm package's build, on a CDN).
VIEWER_JS = "https://cdn.jsdelivr.net/npm/cesium@1.145.0/Build/Cesium/"


def viewer_page(name: str, viewer_js: str) -> bytes:
    """The HTML page ``/`` answers: CesiumJS (from ``viewer_js``, a URL or path ending in ``/``
    that holds ``Cesium.js``) over the served terrain, imagery and buildings."""
    import html

    from lodscape.data import data_path

    page = data_path("viewer.html").read_text()
    page = page.replace("VIEWER_JS_FILE", html.escape(viewer_js + "Cesium.js"))
    page = page.replace("VIEWER_CSS_FILE", html.escape(viewer_js + "Widgets/widgets.css"))
    page = page.replace("VIEWER_JS", json.dumps(viewer_js).replace("</", "<\\/"))
    return page.replace("NAME", html.escape(name)).encode()


#: Where the MapLibre page loads MapLibre GL JS from by default (the npm package, on a CDN).
MAPLIBRE_JS = "https://cdn.jsdelivr.net/npm/maplibre-gl@6.17.0/dist/"


# MapLibre GL JS 6 is ES modules: a browser runs them only with a JavaScript MIME type (Python
# knows .mjs from 3.12, or from the system's mime.types)
mimetypes.add_type("text/javascript", ".mjs")


def maplibre_page(name: str, maplibre_js: str) -> bytes:
    """The HTML page ``/maplibre`` answers: MapLibre GL JS (from ``maplibre_js``, a URL or path
    ending in ``/`` that holds ``maplibre-gl.mjs`` and ``maplibre-gl.css``) with the served
    imagery over the Terrarium terrain."""
    import html

    from lodscape.data import data_path

    page = data_path("maplibre.html").read_text()
    script = json.dumps(maplibre_js + "maplibre-gl.mjs").replace("</", "<\\/")
    page = page.replace("MAPLIBRE_JS_FILE", script)
    page = page.replace("MAPLIBRE_CSS_FILE", html.escape(maplibre_js + "maplibre-gl.css"))
    page = page.replace("MAPLIBRE_JS", json.dumps(maplibre_js).replace("</", "<\\/"))
    return page.replace("NAME", html.escape(name)).encode()


def maplibre_source(maplibre_js: str | None) -> tuple[str, Path | None]:
    """``--maplibre-js`` as the MapLibre page's script base and the local folder to serve it
    from (None: a URL): a folder must hold ``maplibre-gl.mjs`` and ``maplibre-gl.css`` (the npm
    package's ``dist``, version 6 or later: an ES module)."""
    return _script_source(
        "--maplibre-js",
        maplibre_js,
        MAPLIBRE_JS,
        "maplibre-js/",
        ("maplibre-gl.mjs", "maplibre-gl.css"),
        "MapLibre GL JS's build",
        "node_modules/maplibre-gl/dist",
    )


def viewer_source(viewer_js: str | None) -> tuple[str, Path | None]:
    """``--viewer-js`` as the page's script base and the local folder to serve it from (None:
    a URL): a folder must hold CesiumJS's build (``Cesium.js``, ``Widgets/``)."""
    return _script_source(
        "--viewer-js",
        viewer_js,
        VIEWER_JS,
        "viewer-js/",
        ("Cesium.js", "Widgets/"),
        "CesiumJS's build",
        "node_modules/cesium/Build/Cesium",
    )


def _script_source(
    flag: str,
    given: str | None,
    default: str,
    route: str,
    needed: tuple[str, ...],
    what: str,
    example: str,
) -> tuple[str, Path | None]:
    """A page's script base (``default`` when not ``given``; a URL as given, ending in ``/``)
    and the local folder to serve under ``route`` (None: a URL); a folder must hold ``needed``
    (names ending in ``/`` are folders), else a one-line error naming ``flag``."""
    if given is None:
        return default, None
    if given.startswith(("http://", "https://", "//")):
        return given if given.endswith("/") else given + "/", None
    folder = Path(given)
    for name in needed:
        there = folder / name.rstrip("/")
        if not (there.is_dir() if name.endswith("/") else there.is_file()):
            raise LodscapeError(
                f"{flag} {given}: not {what} (a folder holding {' and '.join(needed)}, e.g. "
                f"{example}) nor an http(s) URL"
            )
    return route, folder.resolve()


def make_app(
    service: TileService,
    deadlines: HeaderDeadlines | None = None,
    public_url: str | None = None,
    viewer_js: str | None = None,
    maplibre_js: str | None = None,
) -> Any:
    """The aiohttp application serving ``service`` (``deadlines``: the connections' header
    deadlines, kept as their requests start and end)."""
    from aiohttp import web

    Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

    @web.middleware
    async def watched(request: web.Request, handler: Handler) -> web.StreamResponse:
        transport = request.transport
        if deadlines is not None and transport is not None:
            deadlines.started(transport)
        try:
            await service.watch()
            return await handler(request)
        finally:
            if deadlines is not None and transport is not None:
                deadlines.waiting(transport)

    @web.middleware
    async def cors(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method == "OPTIONS":
            # a preflight for a route that exists; any other path is 404 as for GET
            match = await request.app.router.resolve(
                request.clone(method="GET")  # type: ignore[no-untyped-call]
            )
            if match.http_exception is not None:
                raise web.HTTPNotFound(headers=CORS)
            return web.Response(status=204, headers=CORS)
        try:
            response = await handler(request)
        except web.HTTPException as exc:
            exc.headers.update(CORS)
            raise
        response.headers.update(CORS)
        return response

    script, local = viewer_source(viewer_js)
    maplibre_script, maplibre_local = maplibre_source(maplibre_js)

    async def page(request: web.Request) -> web.Response:
        body = viewer_page(service.path.stem, script)
        return _reply(request, body, "text/html", compress=True)

    async def maplibre(request: web.Request) -> web.Response:
        body = maplibre_page(service.path.stem, maplibre_script)
        return _reply(request, body, "text/html", compress=True)

    async def index(request: web.Request) -> web.Response:
        body = json.dumps(
            {
                "name": service.path.stem,
                "terrain": "layer.json",
                "imagery": "imagery/{z}/{x}/{y}.png",
                "imagery_tilejson": "imagery.json",
                "terrarium": "terrarium/{z}/{x}/{y}.png",
                "terrarium_tilejson": "terrarium.json",
                "buildings": "3dtiles/tileset.json" if service.has_city else None,
            }
        ).encode()
        return _reply(request, body, "application/json", compress=True)

    async def layer(request: web.Request) -> web.Response:
        return _reply(request, service.layer, "application/json", compress=True)

    async def terrain(request: web.Request) -> web.Response:
        z, x, y = _ints(request, "z", "x", "y")
        data = await service.tile("terrain", z, x, y)
        if data is None:
            raise web.HTTPNotFound()
        return _reply(request, data, "application/vnd.quantized-mesh", gzipped=True)

    async def imagery(request: web.Request) -> web.Response:
        z, x, y = _ints(request, "z", "x", "y")
        data = await service.tile("imagery", z, x, y)
        if data is None:
            raise web.HTTPNotFound()
        return _reply(request, data, "image/png")

    async def terrarium(request: web.Request) -> web.Response:
        z, x, y = _ints(request, "z", "x", "y")
        data = await service.tile("terrarium", z, x, y)
        if data is None:
            raise web.HTTPNotFound()
        return _reply(request, data, "image/png")

    async def terrarium_json(request: web.Request) -> web.Response:
        base = public_base(request.scheme, request.host, request.headers, public_url)
        made = await service.run(service.terrarium_tilejson, base)
        return _reply(request, json.dumps(made).encode(), "application/json", compress=True)

    async def tilejson(request: web.Request) -> web.Response:
        base = public_base(request.scheme, request.host, request.headers, public_url)
        made = await service.run(service.tilejson, base)
        return _reply(request, json.dumps(made).encode(), "application/json", compress=True)

    async def tileset(request: web.Request) -> web.Response:
        made = await service.run(service.tiles3d)
        if made is None:
            raise web.HTTPNotFound()
        return _reply(request, made[0], "application/json", compress=True)

    async def content(request: web.Request) -> web.Response:
        (i,) = _ints(request, "i")
        made = await service.run(service.tiles3d)
        if made is None or not 0 <= i < len(made[1]):
            raise web.HTTPNotFound()
        return _reply(request, made[1][i], "model/gltf-binary", compress=True)

    app = web.Application(middlewares=[watched, cors])
    num = "{%s:" + _NUMBER + "}"
    app.router.add_get("/", page)
    app.router.add_get("/index.json", index)
    if local is not None:
        app.router.add_static("/viewer-js/", local)
    app.router.add_get("/maplibre", maplibre)
    if maplibre_local is not None:
        app.router.add_static("/maplibre-js/", maplibre_local)
    app.router.add_get("/layer.json", layer)
    app.router.add_get(f"/{num % 'z'}/{num % 'x'}/{num % 'y'}.terrain", terrain)
    app.router.add_get(f"/imagery/{num % 'z'}/{num % 'x'}/{num % 'y'}.png", imagery)
    app.router.add_get("/imagery.json", tilejson)
    app.router.add_get(f"/terrarium/{num % 'z'}/{num % 'x'}/{num % 'y'}.png", terrarium)
    app.router.add_get("/terrarium.json", terrarium_json)
    app.router.add_get("/3dtiles/tileset.json", tileset)
    app.router.add_get(f"/3dtiles/{num % 'i'}.glb", content)
    return app


def _reply(
    request: web.Request,
    body: bytes,
    content_type: str,
    *,
    gzipped: bool = False,
    compress: bool = False,
) -> web.Response:
    """A tile or document answered with a strong ETag (304 where the client has it), gzipped
    where the client takes it (``gzipped``: the body is stored gzipped already; ``compress``:
    gzip a body worth it)."""
    from aiohttp import web

    gz = accepts_gzip(request.headers.get("Accept-Encoding", ""))
    encoded = False
    if gzipped:
        if gz:
            encoded = True
        else:
            body = ungzip(body)
    elif compress and gz and len(body) > 512:
        body = gzip.compress(body, mtime=0)
        encoded = True
    # a strong tag names the bytes sent: the gzipped and the plain body have their own
    etag = '"' + hashlib.sha1(body).hexdigest()[:20] + ('-gz"' if encoded else '"')
    headers = {
        "ETag": etag,
        "Cache-Control": "public, max-age=3600",
        "Vary": "Accept-Encoding",
    }
    if etag_matches(request.headers.get("If-None-Match", ""), etag):
        return web.Response(status=304, headers=headers)
    if encoded:
        headers["Content-Encoding"] = "gzip"
    return web.Response(body=body, headers=headers, content_type=content_type)


def _ints(request: web.Request, *names: str) -> list[int]:
    """The request's integer path parts (404 where one is not)."""
    from aiohttp import web

    try:
        return [int(request.match_info[n]) for n in names]
    except (KeyError, ValueError):
        raise web.HTTPNotFound() from None


class _OneLine(logging.Formatter):
    """aiohttp's server errors (a malformed request, a client gone mid-answer) as one line on
    stderr, without the traceback aiohttp attaches."""

    def format(self, record: logging.LogRecord) -> str:
        reason = ""
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            reason = f": {type(exc).__name__}: {' '.join(str(exc).split())}"[:300]
        return f"lodscape serve: {record.getMessage()}{reason}"

    def formatException(self, ei: Any) -> str:
        return ""


def _quiet_server_logs() -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLine())
    for name in ("aiohttp.server", "aiohttp.web", "aiohttp.internal"):
        log = logging.getLogger(name)
        log.handlers[:] = [handler]
        log.propagate = False


def run(
    path: str | Path,
    host: str = "127.0.0.1",
    port: int = 8000,
    *,
    ready: Callable[[str], None] | None = None,
    public_url: str | None = None,
    viewer_js: str | None = None,
    tiling: str = "geographic",
    maplibre_js: str | None = None,
) -> None:
    """Serve the tileset until interrupted; ``ready(url)`` once the port is bound (not before:
    a bad file or a busy port fails first, and nothing says "serving"). ``public_url``: the
    scheme and host clients reach it by (behind a proxy), in the URLs it writes."""

    viewer_source(viewer_js)  # a bad --viewer-js fails before anything is opened
    maplibre_source(maplibre_js)
    service = TileService(path, tiling)  # a file that is not a complete tileset fails here
    _quiet_server_logs()
    try:
        asyncio.run(
            serve(
                service,
                host,
                port,
                ready=ready,
                public_url=public_url,
                viewer_js=viewer_js,
                maplibre_js=maplibre_js,
            )
        )
    finally:
        service.close()


async def serve(
    service: TileService,
    host: str,
    port: int,
    *,
    ready: Callable[[str], None] | None = None,
    stop: asyncio.Event | None = None,
    header_timeout: float = HEADER_TIMEOUT,
    public_url: str | None = None,
    viewer_js: str | None = None,
    maplibre_js: str | None = None,
) -> None:
    """Serve ``service`` on ``host:port`` until ``stop`` is set (never, without one)."""
    from aiohttp import web

    deadlines = HeaderDeadlines(header_timeout)
    app = make_app(service, deadlines, public_url, viewer_js, maplibre_js)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    loop = asyncio.get_running_loop()
    try:
        server = await loop.create_server(
            deadlines.protocol(runner.server),  # type: ignore[arg-type]
            host,
            port,
            backlog=1024,
            reuse_address=True,
        )
    except OSError as exc:
        await runner.cleanup()
        raise LodscapeError(
            f"cannot listen on {host}:{port} ({exc.strerror or exc}); "
            "is another server there? choose another --port"
        ) from None
    if ready is not None:
        ready(f"http://{host}:{port}/")
    try:
        while stop is None or not stop.is_set():
            deadlines.sweep()
            if stop is None:
                await asyncio.sleep(min(1.0, header_timeout / 4))
            else:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), min(1.0, header_timeout / 4))
    finally:
        server.close()
        await runner.cleanup()
        await server.wait_closed()
