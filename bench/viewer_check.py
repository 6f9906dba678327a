"""Optional browser check of ``lodscape serve``'s pages (not run by CI): the sample DEM built (and
a copy of it with a void punched in), served with local builds of CesiumJS and MapLibre GL JS,
opened in headless Chromium through Playwright. Each view must load with no page error and no
failed request; it writes a screenshot of each:

- the Cesium page over both poles from orbit, in the default geographic tiling (and in
  ``--tiling mercator``, whose tiles stop at ±85.05°, for comparison);
- the Cesium page 4 km above the void;
- the MapLibre page (the imagery over the Terrarium terrain) at zoom 8 and 12.

Over a pole it counts the near-white pixels around the pole's place on the screen (Cesium's
white disc where no tile reaches).

    npm install cesium maplibre-gl playwright-core       # in some folder: its node_modules
    python bench/viewer_check.py --node-modules /tmp/cz/node_modules --out /tmp/viewer
"""

from __future__ import annotations

import argparse
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

_DRIVER = """
const { chromium } = require(process.argv[2] + "/playwright-core");
const shots = JSON.parse(require("fs").readFileSync(process.argv[4], "utf8"));
(async () => {
  const browser = await chromium.launch({ executablePath: process.argv[3], args: [
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--no-sandbox"] });
  const out = [];
  for (const shot of shots) {
    const page = await browser.newPage({ viewport: { width: 800, height: 500 } });
    const errors = [];
    const failed = [];
    page.on("pageerror", (e) => errors.push(String(e)));
    page.on("requestfailed", (r) => failed.push(r.url()));
    page.on("response", (r) => { if (r.status() >= 400) failed.push(r.status() + " " + r.url()); });
    const t0 = Date.now();
    let timeout = false;
    try {
      await page.goto(shot.url);
      await page.waitForFunction(() => window.ready === true, null, { timeout: 120000 });
      await page.evaluate(shot.setup);
      await page.waitForTimeout(1500);
      if (shot.kind === "cesium") {
        await page.waitForFunction(() => window.viewer.scene.globe.tilesLoaded, null,
                                   { timeout: 240000 });
        await page.waitForTimeout(500);
      } else {
        await page.waitForFunction(() => window.map.loaded() && window.map.areTilesLoaded(),
                                   null, { timeout: 240000 });
        await page.waitForTimeout(500);
      }
    } catch (e) {
      timeout = String(e);
    }
    const seconds = (Date.now() - t0) / 1000;
    await page.screenshot({ path: shot.path });
    const note = await page.evaluate(() => document.getElementById("note").textContent);
    out.push({ name: shot.name, seconds, note, errors, failed: failed.slice(0, 20), timeout });
    await page.close();
  }
  console.log(JSON.stringify(out));
  await browser.close();
})();
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _serve(tileset: Path, port: int, modules: Path, tiling: str) -> subprocess.Popen[str]:
    server = subprocess.Popen(
        [sys.executable, "-m", "lodscape.cli", "serve", str(tileset), "--port", str(port),
         "--viewer-js", str(modules / "cesium" / "Build" / "Cesium"),
         "--maplibre-js", str(modules / "maplibre-gl" / "dist"), "--tiling", tiling],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert server.stdout is not None
    line = server.stdout.readline()
    if not line.startswith("serving"):
        raise SystemExit(
            f"serve did not start: {line} {server.stderr.read() if server.stderr else ''}"
        )
    return server


def _void_copy(dem: Path, out: Path) -> tuple[float, float]:
    """A copy of ``dem`` with a void (nodata) of a fifth of its size at its centre; the void's
    centre (lon, lat)."""
    import rasterio
    from pyproj import Transformer

    with rasterio.open(dem) as src:
        h = src.read(1)
        profile = src.profile
        nodata = src.nodata if src.nodata is not None else -32768
        rows, cols = h.shape
        r0, c0 = rows // 2 - rows // 10, cols // 2 - cols // 10
        h[r0 : r0 + rows // 5, c0 : c0 + cols // 5] = nodata
        x, y = src.xy(rows // 2, cols // 2)
        crs = src.crs
    profile.update(nodata=nodata)
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(h, 1)
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(x, y)
    return float(lon), float(lat)


def _white_share(path: Path) -> float:
    """Share of near-white pixels in the middle fifth of a screenshot (where the pole is)."""
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"), np.int32)
    h, w, _ = img.shape
    mid = img[2 * h // 5 : 3 * h // 5, 2 * w // 5 : 3 * w // 5]
    return float((mid.min(axis=2) > 225).mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dem", nargs="?", help="a DEM (default: the bundled sample)")
    ap.add_argument("--node-modules", type=Path, required=True)
    ap.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    ap.add_argument("--out", type=Path, default=Path("/tmp/viewer_check"))
    args = ap.parse_args()

    from lodscape.build import build
    from lodscape.data import sample_dem_path

    args.out.mkdir(parents=True, exist_ok=True)
    site = Path(tempfile.mkdtemp(prefix="viewer_check_"))
    dem = Path(args.dem or str(sample_dem_path()))
    tileset, holed = site / "site.lods", site / "void.lods"
    build([str(dem)], tileset)
    void_lon, void_lat = _void_copy(dem, site / "void.tif")
    build([str(site / "void.tif")], holed)
    from lodscape.store.tileset import TilesetProvider

    p = TilesetProvider(tileset)
    b = p.bounds_merc
    from lodscape.geo.tiles import merc_to_lonlat

    lon, lat = (float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.bottom + b.top) / 2))
    ground = p.ground_height(void_lon, void_lat - 0.03) or 0.0
    p.close()
    orbit = "viewer.camera.setView({{destination: Cesium.Cartesian3.fromDegrees({}, {}, 1.4e7)}})"
    void = (
        f"viewer.camera.setView({{destination: Cesium.Cartesian3.fromDegrees({void_lon}, "
        f"{void_lat - 0.045}, {ground + 4000.0}), orientation: {{heading: 0, "
        "pitch: Cesium.Math.toRadians(-35), roll: 0}})"
    )
    maplibre = "map.jumpTo({{center: [{}, {}], zoom: {}, pitch: 50}})"
    plan: list[tuple[Path, str, list[dict[str, Any]]]] = [
        (tileset, "geographic", [
            {"name": "cesium-north-pole", "kind": "cesium", "page": "",
             "setup": orbit.format(lon, 90)},
            {"name": "cesium-south-pole", "kind": "cesium", "page": "",
             "setup": orbit.format(lon, -90)},
            {"name": "maplibre-z8", "kind": "maplibre", "page": "maplibre",
             "setup": maplibre.format(lon, lat, 8)},
            {"name": "maplibre-z12", "kind": "maplibre", "page": "maplibre",
             "setup": maplibre.format(lon, lat, 12)},
        ]),
        (tileset, "mercator", [
            {"name": "cesium-north-pole-mercator", "kind": "cesium", "page": "",
             "setup": orbit.format(lon, 90)},
        ]),
        (holed, "geographic", [
            {"name": "cesium-void-4km", "kind": "cesium", "page": "", "setup": void},
        ]),
    ]  # fmt: skip
    driver = site / "driver.js"
    driver.write_text(_DRIVER)
    results = []
    for served, tiling, shots in plan:
        port = _port()
        server = _serve(served, port, args.node_modules, tiling)
        try:
            for shot in shots:
                shot["url"] = f"http://127.0.0.1:{port}/{shot['page']}"
                shot["path"] = str(args.out / f"{shot['name']}.png")
            (site / "shots.json").write_text(json.dumps(shots))
            t = time.perf_counter()
            run = subprocess.run(
                ["node", str(driver), str(args.node_modules), args.chromium,
                 str(site / "shots.json")],
                capture_output=True,
                text=True,
                timeout=900,
            )  # fmt: skip
            if run.returncode != 0:
                raise SystemExit(f"the pages failed:\n{run.stderr[-3000:]}")
            got = json.loads(run.stdout.strip().splitlines()[-1])
            for g, shot in zip(got, shots, strict=True):
                g["tiling"] = tiling
                g["screenshot"] = shot["path"]
                if "pole" in shot["name"]:
                    g["white_share_at_pole"] = round(_white_share(Path(shot["path"])), 4)
            results.extend(got)
            print(f"{served.name} ({tiling}): {time.perf_counter() - t:.1f} s", file=sys.stderr)
        finally:
            server.terminate()
            server.communicate(timeout=10)
    print(json.dumps(results, indent=1))
    bad = [r["name"] for r in results if r["errors"] or r["failed"] or r["timeout"]]
    if bad:
        raise SystemExit(f"views with errors, failed requests or timeouts: {bad}")


if __name__ == "__main__":
    main()
