"""Optional browser check of the notebook widget in a real JupyterLab (not run by CI): JupyterLab
4 started on loopback, a notebook that opens the sample DEM and shows ``scene.widget()``, run in
headless Chromium through Playwright; the W key is held on the view for 5 s, and every picture
the kernel sends back is counted (the status line under the view changes with each). With
ipykernel 7 the widget's messages come on another thread than the cell's: before the scene's
GL thread the first held key froze the view. Writes a screenshot.

    pip install 'jupyterlab>=4'; npm install playwright-core   # its node_modules
    python bench/notebook_check.py --node-modules /tmp/cz/node_modules --out /tmp/nb
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
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
  const browser = await chromium.launch({ executablePath: process.argv[3], args: [
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"] });
  const page = await browser.newPage({ viewport: { width: 1100, height: 800 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(String(e)));
  await page.goto(process.argv[4]);
  await page.waitForSelector(".jp-Notebook .jp-Cell", { timeout: 120000 });
  await page.waitForSelector(".jp-Notebook-ExecutionIndicator[data-status='idle']",
                             { timeout: 120000 }).catch(() => {});
  await page.waitForTimeout(3000);
  await page.click(".jp-Notebook .jp-Cell .jp-InputArea-editor");
  await page.keyboard.press("Shift+Enter");
  const img = await page.waitForSelector("img.lodscape-view[src]", { timeout: 180000 })
    .catch(async (e) => {
      await page.screenshot({ path: process.argv[5] });
      const out = await page.$$eval(".jp-OutputArea-output",
                                    (els) => els.map((x) => x.textContent));
      console.log(JSON.stringify({ failed: String(e), outputs: out, errors }));
      throw e;
    });
  const status = async () => page.$eval(".lodscape-status", (e) => e.textContent);
  const first = await status();
  await img.click();
  const seen = new Set([first]);
  const t0 = Date.now();
  await page.keyboard.down("w");
  while (Date.now() - t0 < 5000) {
    seen.add(await status());
    await page.waitForTimeout(50);
  }
  await page.keyboard.up("w");
  await page.waitForTimeout(500);
  const last = await status();
  await page.screenshot({ path: process.argv[5] });
  console.log(JSON.stringify({ frames_in_5s: seen.size - 1, first, last, errors }));
  await browser.close();
})();
"""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--node-modules", type=Path, required=True)
    ap.add_argument("--chromium", default=shutil.which("chromium") or "chromium")
    ap.add_argument("--out", type=Path, default=Path("/tmp/notebook_check"))
    args = ap.parse_args()

    import nbformat

    args.out.mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="notebook_check_"))
    nb = nbformat.v4.new_notebook()
    nb.cells.append(
        nbformat.v4.new_code_cell(
            "import lodscape\n"
            "from lodscape.data import sample_dem_path\n"
            "scene = lodscape.open(sample_dem_path())\n"
            "w = scene.widget(width=320, height=200)\n"
            "w"
        )
    )
    nb.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    nbformat.write(nb, root / "check.ipynb")
    port, token = _port(), secrets.token_hex(8)
    env = {**os.environ, "JUPYTER_CONFIG_DIR": str(root / "config")}
    lab = subprocess.Popen(
        [sys.executable, "-m", "jupyter", "lab", "--no-browser", f"--port={port}",
         f"--ServerApp.token={token}", f"--ServerApp.root_dir={root}",
         "--ServerApp.ip=127.0.0.1", "--LabApp.news_url=", "--ServerApp.disable_check_xsrf=True",
         *(["--allow-root"] if hasattr(os, "geteuid") and os.geteuid() == 0 else [])],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=1):
                    break
            except OSError:
                if time.monotonic() > deadline or lab.poll() is not None:
                    raise SystemExit("JupyterLab did not start") from None
                time.sleep(0.5)
        driver = root / "driver.js"
        driver.write_text(_DRIVER)
        shot = args.out / "notebook.png"
        url = f"http://127.0.0.1:{port}/lab/tree/check.ipynb?token={token}"
        run = subprocess.run(
            ["node", str(driver), str(args.node_modules), args.chromium, url, str(shot)],
            capture_output=True,
            text=True,
            timeout=600,
        )
        if run.returncode != 0:
            raise SystemExit(f"the notebook check failed:\n{run.stderr[-3000:]}")
        got = json.loads(run.stdout.strip().splitlines()[-1])
        got["screenshot"] = str(shot)
        print(json.dumps(got, indent=1))
        if got["errors"] or got["frames_in_5s"] < 5 or "!" in got["last"]:
            raise SystemExit("the widget did not fly: errors, or under 5 pictures in 5 s")
    finally:
        lab.terminate()
        try:
            lab.wait(20)
        except subprocess.TimeoutExpired:
            lab.kill()


if __name__ == "__main__":
    main()
