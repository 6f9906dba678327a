"""``lodscape serve``: a tileset over HTTP (aiohttp) for Cesium, MapLibre or any tile client.

Routes:
- ``/layer.json``: the Cesium terrain layer (TMS rows, as ``lodscape export --cesium``);
- ``/{z}/{x}/{y}.terrain``: quantized-mesh-1.0 with octvertexnormals, gzipped where the client
  accepts it (as stored), plain otherwise; flat tiles above the tileset's roots;
- ``/imagery/{z}/{x}/{y}.png``: the imagery (OSM rows), and ``/imagery.json`` its TileJSON
  (levels, bounds, attribution; for MapLibre, Leaflet or any XYZ client);
- ``/3dtiles/tileset.json`` and ``/3dtiles/{i}.glb``: the stored cities' buildings as 3D Tiles
  1.1, when the tileset holds a city (made at the first request, then kept): groups of box
  models, each replaced by its full buildings up close.

Every answer carries CORS headers and an ETag (a ``If-None-Match`` that matches gets 304);
JSON and glTF are gzipped when the client accepts it. A path that is not one of these exactly,
with numbers in range, is 404: the routes match digits only, so nothing outside the tileset can
be named.
"""

from __future__ import annotations

import asyncio
import gzip
import hashlib
import json
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from lodscape.store.export import cesium_layer
from lodscape.store.manifest import connect_readonly
from lodscape.store.quantized_mesh import ungzip
from lodscape.store.tileset import TilesetProvider

__all__ = ["TileService", "make_app", "run"]

CORS = {
    "Access-Control-Allow-Origin": "*",
    "Access-Control-Allow-Methods": "GET, HEAD, OPTIONS",
    "Access-Control-Allow-Headers": "*",
    "Access-Control-Expose-Headers": "ETag, Content-Encoding, Content-Length",
}
#: Deepest level any route accepts (Web Mercator tiles stop being meaningful well before).
MAX_ZOOM = 30


class TileService:
    """The tileset's bytes by route, read-only; safe from the server's event loop."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        provider = TilesetProvider(self.path)  # refuses what is not a complete tileset
        self.manifest = provider.manifest
        self._provider = provider
        self._db = connect_readonly(self.path)
        self._lock = threading.Lock()
        layer, self._flat = cesium_layer(self._db, self.manifest, self.path.stem)
        self.layer = json.dumps(layer, indent=1).encode()
        self._tiles3d: tuple[bytes, list[bytes]] | None = None
        self.has_city = bool(provider.cities())

    def close(self) -> None:
        self._db.close()
        self._provider.close()

    def terrain(self, z: int, x: int, tms: int) -> bytes | None:
        """Gzipped quantized-mesh of tile z/x/TMS row, or None."""
        if not (0 <= z <= MAX_ZOOM and 0 <= x < (1 << z) and 0 <= tms < (1 << z)):
            return None
        flat = self._flat.get((z, x, tms))
        if flat is not None:
            return gzip.compress(flat, mtime=0)
        with self._lock:
            row = self._db.execute(
                "SELECT data FROM terrain WHERE z = ? AND x = ? AND y = ?",
                (z, x, (1 << z) - 1 - tms),
            ).fetchone()
        return None if row is None else bytes(row[0])

    def imagery(self, z: int, x: int, y: int) -> bytes | None:
        """PNG of imagery tile z/x/y (OSM rows), or None."""
        if not (0 <= z <= MAX_ZOOM and 0 <= x < (1 << z) and 0 <= y < (1 << z)):
            return None
        with self._lock:
            row = self._db.execute(
                "SELECT tile_data FROM tiles WHERE zoom_level = ? AND tile_column = ? "
                "AND tile_row = ?",
                (z, x, (1 << z) - 1 - y),
            ).fetchone()
        return None if row is None else bytes(row[0])

    def tilejson(self, base: str) -> dict[str, object]:
        """The imagery's TileJSON, its tiles under ``base`` (scheme and host)."""
        from lodscape.store.export import imagery_tilejson

        with self._lock:
            return imagery_tilejson(self._db, self.path.stem, base + "/imagery/{z}/{x}/{y}.png")

    def tiles3d(self) -> tuple[bytes, list[bytes]] | None:
        """(tileset.json, glb contents) of the stored cities, or None without a city."""
        if not self.has_city:
            return None
        with self._lock:
            if self._tiles3d is None:
                from lodscape.store.export import city_3dtiles

                made = city_3dtiles(self._provider)
                if made is None:
                    return None
                self._tiles3d = (json.dumps(made[0]).encode(), made[1])
            return self._tiles3d


def make_app(service: TileService) -> Any:
    """The aiohttp application serving ``service``."""
    from aiohttp import web

    Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]

    @web.middleware
    async def cors(request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.method == "OPTIONS":
            return web.Response(status=204, headers=CORS)
        try:
            response = await handler(request)
        except web.HTTPException as exc:
            exc.headers.update(CORS)
            raise
        response.headers.update(CORS)
        return response

    def reply(
        request: web.Request,
        body: bytes,
        content_type: str,
        *,
        gzipped: bool = False,
        compress: bool = False,
    ) -> web.Response:
        etag = '"' + hashlib.sha1(body).hexdigest()[:20] + '"'
        headers = {"ETag": etag, "Cache-Control": "public, max-age=3600"}
        if request.headers.get("If-None-Match") == etag:
            return web.Response(status=304, headers=headers)
        accepts = "gzip" in request.headers.get("Accept-Encoding", "")
        if gzipped:
            if accepts:
                headers["Content-Encoding"] = "gzip"
            else:
                body = ungzip(body)
        elif compress and accepts and len(body) > 512:
            body = gzip.compress(body, mtime=0)
            headers["Content-Encoding"] = "gzip"
        headers["Vary"] = "Accept-Encoding"
        return web.Response(body=body, headers=headers, content_type=content_type)

    def ints(request: web.Request, *names: str) -> list[int]:
        try:
            return [int(request.match_info[n]) for n in names]
        except (KeyError, ValueError):
            raise web.HTTPNotFound() from None

    async def index(request: web.Request) -> web.Response:
        body = json.dumps(
            {
                "name": service.path.stem,
                "terrain": "layer.json",
                "imagery": "imagery/{z}/{x}/{y}.png",
                "imagery_tilejson": "imagery.json",
                "buildings": "3dtiles/tileset.json" if service.has_city else None,
            }
        ).encode()
        return reply(request, body, "application/json", compress=True)

    async def layer(request: web.Request) -> web.Response:
        return reply(request, service.layer, "application/json", compress=True)

    async def terrain(request: web.Request) -> web.Response:
        z, x, y = ints(request, "z", "x", "y")
        data = service.terrain(z, x, y)
        if data is None:
            raise web.HTTPNotFound()
        return reply(request, data, "application/vnd.quantized-mesh", gzipped=True)

    async def imagery(request: web.Request) -> web.Response:
        z, x, y = ints(request, "z", "x", "y")
        data = service.imagery(z, x, y)
        if data is None:
            raise web.HTTPNotFound()
        return reply(request, data, "image/png")

    async def tilejson(request: web.Request) -> web.Response:
        body = json.dumps(service.tilejson(f"{request.scheme}://{request.host}")).encode()
        return reply(request, body, "application/json", compress=True)

    async def tileset(request: web.Request) -> web.Response:
        made = await asyncio.get_running_loop().run_in_executor(None, service.tiles3d)
        if made is None:
            raise web.HTTPNotFound()
        return reply(request, made[0], "application/json", compress=True)

    async def content(request: web.Request) -> web.Response:
        (i,) = ints(request, "i")
        made = await asyncio.get_running_loop().run_in_executor(None, service.tiles3d)
        if made is None or not 0 <= i < len(made[1]):
            raise web.HTTPNotFound()
        return reply(request, made[1][i], "model/gltf-binary", compress=True)

    app = web.Application(middlewares=[cors])
    num = r"{%s:\d{1,10}}"
    app.router.add_get("/", index)
    app.router.add_get("/layer.json", layer)
    app.router.add_get(f"/{num % 'z'}/{num % 'x'}/{num % 'y'}.terrain", terrain)
    app.router.add_get(f"/imagery/{num % 'z'}/{num % 'x'}/{num % 'y'}.png", imagery)
    app.router.add_get("/imagery.json", tilejson)
    app.router.add_get("/3dtiles/tileset.json", tileset)
    app.router.add_get(f"/3dtiles/{num % 'i'}.glb", content)
    return app


def run(path: str | Path, host: str = "127.0.0.1", port: int = 8000) -> None:
    """Serve the tileset until interrupted."""
    from aiohttp import web

    service = TileService(path)
    try:
        web.run_app(make_app(service), host=host, port=port, print=None)
    finally:
        service.close()
