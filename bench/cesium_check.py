"""An optional check with a real client: CesiumJS in headless Chromium against ``lodscape export``.

Not part of CI (it needs Chromium and npm packages). It builds a tileset from a DEM (the bundled
sample by default), exports it, serves the folder and Cesium on loopback, and has Cesium fly
from orbit to the ground with lighting on and vertex normals requested: screenshots of each view,
and what Cesium itself reports of the ground's height on the data and on the far side of the
Earth (the ellipsoid there, not the data's lowest height), and the globe's brightness from orbit
(near-black where tiles lack the normals ``layer.json`` promises).

    apt-get install chromium            # Debian
    npm install --prefix /tmp/cz cesium playwright-core
    python bench/cesium_check.py --node-modules /tmp/cz/node_modules --out /tmp/cesium
"""

from __future__ import annotations

import argparse
import functools
import http.server
import json
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

_PAGE = """<!doctype html>
<html><head><meta charset="utf-8">
<script>window.CESIUM_BASE_URL = "Cesium/";</script>
<script src="Cesium/Cesium.js"></script>
<link href="Cesium/Widgets/widgets.css" rel="stylesheet">
<style>html, body, #c { margin: 0; width: 100%; height: 100%; overflow: hidden; }</style>
</head><body><div id="c"></div><script>
(async () => {
  const terrain = await Cesium.CesiumTerrainProvider.fromUrl("terrain/",
                                                             { requestVertexNormals: true });
  const viewer = new Cesium.Viewer("c", {
    terrainProvider: terrain, baseLayer: false, animation: false, timeline: false,
    baseLayerPicker: false, geocoder: false, homeButton: false, sceneModePicker: false,
    navigationHelpButton: false, fullscreenButton: false, infoBox: false,
    selectionIndicator: false, skyBox: false, skyAtmosphere: false,
  });
  const t = TILEJSON;
  viewer.imageryLayers.addImageryProvider(new Cesium.UrlTemplateImageryProvider({
    url: "terrain/imagery/{z}/{x}/{y}.png", tilingScheme: new Cesium.WebMercatorTilingScheme(),
    minimumLevel: t.minzoom, maximumLevel: t.maxzoom,
    rectangle: Cesium.Rectangle.fromDegrees(...t.bounds),
  }));
  viewer.scene.globe.enableLighting = true;
  viewer.scene.globe.baseColor = Cesium.Color.fromCssColorString("#2a4f7a");
  viewer.clock.currentTime = Cesium.JulianDate.fromIso8601(NOON);
  viewer.clock.shouldAnimate = false;
  window.viewer = viewer;
  window.ready = true;
})();
window.fly = (v) => viewer.camera.setView({
  destination: Cesium.Cartesian3.fromDegrees(v.lon, v.lat, v.alt),
  orientation: { heading: Cesium.Math.toRadians(v.heading),
                 pitch: Cesium.Math.toRadians(v.pitch), roll: 0 } });
window.settled = () => viewer.scene.globe.tilesLoaded;
window.heightAt = (lon, lat) =>
  viewer.scene.globe.getHeight(Cesium.Cartographic.fromDegrees(lon, lat)) ?? null;
</script></body></html>
"""

_DRIVER = """
const { chromium } = require(process.argv[2] + "/playwright-core");
(async () => {
  const views = JSON.parse(process.argv[4]);
  const browser = await chromium.launch({ executablePath: process.argv[5], args: [
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--no-sandbox"] });
  const page = await browser.newPage({ viewport: { width: 800, height: 500 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  await page.goto(process.argv[3]);
  await page.waitForFunction(() => window.ready === true, null, { timeout: 120000 });
  const out = [];
  for (const v of views) {
    await page.evaluate((v) => window.fly(v), v);
    await page.waitForTimeout(500);
    await page.waitForFunction(() => window.settled(), null, { timeout: 240000 });
    await page.waitForTimeout(1500);
    await page.waitForFunction(() => window.settled(), null, { timeout: 240000 });
    await page.screenshot({ path: v.png });
    const heights = [];
    for (const [lon, lat] of v.probe) heights.push(await page.evaluate(
      ([lon, lat]) => window.heightAt(lon, lat), [lon, lat]));
    out.push({ name: v.name, heights });
  }
  console.log(JSON.stringify({ views: out, errors }));
  await browser.close();
})();
"""


def _m(h: float | None) -> str:
    return "not loaded" if h is None else f"{h:.1f} m"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dem", nargs="?", help="a DEM (default: the bundled sample)")
    ap.add_argument("--node-modules", type=Path, required=True)
    ap.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    ap.add_argument("--out", type=Path, default=Path("/tmp/cesium_check"))
    args = ap.parse_args()

    import lodscape
    from lodscape.build import build
    from lodscape.data import sample_dem_path
    from lodscape.geo.tiles import merc_to_lonlat
    from lodscape.store.export import export_cesium

    dem = args.dem or str(sample_dem_path())
    args.out.mkdir(parents=True, exist_ok=True)
    site = Path(tempfile.mkdtemp(prefix="cesium_check_"))
    tileset = site / "site.lods"
    build([dem], tileset)
    export_cesium(tileset, site / "terrain")
    shutil.copytree(args.node_modules / "cesium" / "Build" / "Cesium", site / "Cesium")
    with lodscape.open(dem) as scene:
        b = scene.provider.bounds_merc
        lon, lat = (
            float(v) for v in merc_to_lonlat((b.left + b.right) / 2, (b.bottom + b.top) / 2)
        )
        ground = scene.ground_height(lon, lat)
        lo, hi = scene.tree.height_range
    tilejson = json.loads((site / "terrain" / "imagery.json").read_text())
    # local noon at the data, so the lit side is the side we look at
    hour = (12.0 - lon / 15.0) % 24.0
    noon = f"2024-06-21T{int(hour):02d}:{int(hour % 1 * 60):02d}:00Z"
    (site / "index.html").write_text(
        _PAGE.replace("TILEJSON", json.dumps(tilejson)).replace("NOON", json.dumps(noon))
    )

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_address[1]}/index.html"
    # the data's centre, and ground beside the data (east and north of its box, in view of the
    # two lower cameras): the ellipsoid there, not the data's lowest height
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    probe = [[lon, lat], [e + 0.5 * (e - w), lat], [lon, n + 0.5 * (n - s)]]
    views = [
        {"name": "orbit", "lon": lon, "lat": lat, "alt": 2.0e7, "heading": 0, "pitch": -90},
        {"name": "100 km", "lon": lon, "lat": lat - 0.9, "alt": 1.0e5, "heading": 0, "pitch": -45},
        {
            "name": "1 km",
            "lon": lon,
            "lat": lat - 0.03,
            "alt": hi + 1000,
            "heading": 0,
            "pitch": -25,
        },
    ]
    for v in views:
        v["png"] = str(args.out / f"cesium-{str(v['name']).replace(' ', '')}.png")
        v["probe"] = probe
    driver = site / "driver.js"
    driver.write_text(_DRIVER)
    try:
        run = subprocess.run(
            ["node", str(driver), str(args.node_modules), url, json.dumps(views), args.chromium],
            capture_output=True,
            text=True,
            timeout=1200,
            check=False,
        )
    finally:
        server.shutdown()
    if run.returncode != 0:
        sys.exit(f"cesium check: node failed:\n{run.stderr[-2000:]}")
    result = json.loads(run.stdout.strip().splitlines()[-1])
    from PIL import Image

    print(f"DEM {dem}: centre {lon:.4f}, {lat:.4f}, ground {ground} m, heights {lo:.1f}..{hi:.1f}")
    for v, got in zip(views, result["views"], strict=True):
        rgb = np.asarray(Image.open(v["png"]).convert("RGB"), np.float64)
        h = got["heights"]
        print(
            f"{v['name']:>7}: mean brightness {rgb.mean():.1f}; Cesium's ground height at the "
            f"data's centre {_m(h[0])}, east of the data {_m(h[1])}, north of it {_m(h[2])}"
        )
    if result["errors"]:
        print("page errors:", *result["errors"][:5], sep="\n  ")
    shutil.rmtree(site, ignore_errors=True)


if __name__ == "__main__":
    main()
