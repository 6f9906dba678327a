"""Optional browser check of ``lodscape serve``'s viewer page (not run by CI): the sample DEM built,
served with a local CesiumJS build, opened in headless Chromium through Playwright; the page
must load, fly to the data and finish loading its tiles with no page error. Writes a screenshot.

    npm install cesium playwright-core            # in some folder: its node_modules
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

_DRIVER = """
const { chromium } = require(process.argv[2] + "/playwright-core");
(async () => {
  const browser = await chromium.launch({ executablePath: process.argv[5], args: [
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
    "--no-sandbox"] });
  const page = await browser.newPage({ viewport: { width: 800, height: 500 } });
  const errors = [];
  const failed = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  page.on("requestfailed", (r) => failed.push(r.url()));
  page.on("response", (r) => { if (r.status() >= 400) failed.push(r.status() + " " + r.url()); });
  const t0 = Date.now();
  await page.goto(process.argv[3]);
  await page.waitForFunction(() => window.ready === true, null, { timeout: 120000 });
  await page.waitForTimeout(1000);
  await page.waitForFunction(() => window.viewer.scene.globe.tilesLoaded, null,
                             { timeout: 240000 }).catch(async (e) => {
    console.log(JSON.stringify({ timeout: true, errors, failed: failed.slice(0, 20) }));
    throw e;
  });
  const seconds = (Date.now() - t0) / 1000;
  await page.screenshot({ path: process.argv[4] });
  const note = await page.evaluate(() => document.getElementById("note").textContent);
  console.log(JSON.stringify({ seconds, note, errors, failed }));
  await browser.close();
})();
"""


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
    tileset = site / "site.lods"
    build([args.dem or str(sample_dem_path())], tileset)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    cesium = args.node_modules / "cesium" / "Build" / "Cesium"
    server = subprocess.Popen(
        [sys.executable, "-m", "lodscape.cli", "serve", str(tileset), "--port", str(port),
         "--viewer-js", str(cesium)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        assert server.stdout is not None
        line = server.stdout.readline()
        if not line.startswith("serving"):
            raise SystemExit(
                f"serve did not start: {line} {server.stderr.read() if server.stderr else ''}"
            )
        driver = site / "driver.js"
        driver.write_text(_DRIVER)
        shot = args.out / "viewer.png"
        t = time.perf_counter()
        run = subprocess.run(
            ["node", str(driver), str(args.node_modules), f"http://127.0.0.1:{port}/", str(shot),
             args.chromium],
            capture_output=True,
            text=True,
            timeout=600,
        )  # fmt: skip
        if run.returncode != 0:
            raise SystemExit(f"the page failed:\n{run.stderr[-3000:]}")
        got = json.loads(run.stdout.strip().splitlines()[-1])
        got["wall_s"] = round(time.perf_counter() - t, 1)
        got["screenshot"] = str(shot)
        print(json.dumps(got, indent=1))
        if got["errors"] or got["failed"]:
            raise SystemExit("the page logged errors or failed requests")
    finally:
        server.terminate()
        server.communicate(timeout=10)


if __name__ == "__main__":
    main()
