"""Time from a DEM on disk to its first picture, by the DEM's size (issue 36).

DEMs of spectral fBm (2 m, UTM 17N): 1025² and 4097² GeoTIFFs without overviews, and VRT
mosaics of a seamless 1024² tile, 16385² and 65537² (``--sizes``). The 65537² mosaic has
overviews of its own (VRTs of the tile's GDAL averages: building them over its 4·10⁹ pixels
would take the bench longer than everything else); the others get lodscape's sidecar
overviews on their first open.

Each run is a fresh process timing, from the path: open, then the first 1280×720 picture of
the overview camera read back (``lodscape.open`` + ``Scene.render``); its peak RSS
(``VmHWM``) and the bytes it read (``/proc/self/io`` rchar). Engines, in rounds, alternating:

- ``lazy cold``: lodscape (its tree made as views reach it, above 2,049²) with an empty
  cache folder (the sidecar overviews built, where the file has none of its own);
- ``lazy warm``: lodscape again with that cache;
- ``eager``: lodscape's tile tree walked whole before the first picture (``build_tree``, what
  it did before the lazy tree), warm cache; only up to 4097² (``--eager-max``);
- ``stm``: Panda3D's ShaderTerrainMesh from the same file, its clock around reading the
  raster (rasterio), tinting it (lodscape's hypsometric tint × hillshade at the raster's
  size), making the context, generating the terrain and the first frame read back; only up to
  4097² (a heightfield texture of the whole raster).

Prints per size and engine the median and range of the seconds, the peak RSS and bytes read;
then lodscape's warm first picture against the smallest size's.

    python bench/bench_open.py [--rounds 3] [--sizes 1025,4097,16385,65537]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from _synthetic import mosaic_dem, periodic_fbm, write_dem  # noqa: E402

_COMMON = r"""
import json, os, sys, time
t0 = time.perf_counter()
def _io():
    with open("/proc/self/io") as f:
        return int(dict(line.split(": ") for line in f.read().splitlines())["rchar"])
def _peak():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
io0 = _io()
"""

LODSCAPE = (
    _COMMON
    + r"""
import lodscape
if sys.argv[2] == "eager":
    import lodscape.store.provider as p
    from lodscape.terrain.pyramid import build_tree
    p.open_tree = build_tree
with lodscape.open(sys.argv[1]) as scene:
    t_open = time.perf_counter() - t0
    rgb, _ = scene.render(scene.overview_camera(1280, 720))
    t = time.perf_counter() - t0
    made = getattr(scene.tree, "made", None)
print(json.dumps({"s": t, "open_s": t_open, "peak_mb": _peak(), "read_mb": (_io() - io0) / 2**20,
                  "chunks": made, "lit": float((rgb.sum(axis=2) > 0).mean())}))
"""
)

STM = (
    _COMMON
    + r"""
import numpy as np, rasterio
sys.path.insert(0, sys.argv[3])
from bench_peers import _frame, _panda, _readback, stm_terrain
from lodscape.imagery.tint import tint
with rasterio.open(sys.argv[1]) as ds:
    z = ds.read(1).astype(np.float32)
    dx, dy = abs(ds.transform.a), abs(ds.transform.e)
lo, hi = float(z.min()), float(z.max())
rows, cols = z.shape
size = max(64, 2 ** int(np.ceil(np.log2(max(rows, cols) - 1))))
# lodscape's tint as bench_peers gives it: a square bordered grid, cropped back
n = max(rows, cols)
sq = np.pad(np.pad(z, 1, mode="edge"), ((0, n - rows), (0, n - cols)), mode="edge")
colour = tint(sq, np.ones(sq.shape, bool), float(np.sqrt(dx * dy)), (lo, hi))[:rows, :cols]
base = _panda()
col, dep = _readback(base)
stm_terrain(base, z, np.asarray(colour)[..., :3], size, dx, dy)
ext = max(rows * dy, cols * dx)
base.camera.setPos(cols * dx / 2, -0.25 * ext, hi + 0.75 * ext)
base.camera.lookAt(cols * dx / 2, rows * dy / 2, lo)
_frame(base, col, dep)
t = time.perf_counter() - t0
print(json.dumps({"s": t, "open_s": None, "peak_mb": _peak(), "read_mb": (_io() - io0) / 2**20}))
"""
)


def _dem(folder: Path, n: int) -> Path:
    if n <= 4097:
        path = folder / f"dem{n}.tif"
        write_dem(str(path), periodic_fbm(n - 1), crs="EPSG:32617", west=500000.0,
                  north=4000000.0, res=2.0)  # fmt: skip
        return path
    sub = folder / f"m{n}"
    sub.mkdir()
    path = mosaic_dem(sub, (n - 1) // 1024)
    if n > 16385:
        _overviews(path, (n - 1) // 1024)
    return path


def _overviews(vrt: Path, copies: int, tile: int = 1024) -> None:
    """Give the mosaic overviews of its own without reading its 4·10⁹ pixels: the tile gets
    GDAL's (averages), and each overview of the mosaic is a VRT of the tile's overview of the
    same factor, copies² times (what a user's pyramid of a seamless mosaic would hold)."""
    from html import escape

    import rasterio
    from rasterio.enums import Resampling

    base = vrt.parent / "tile.tif"
    factors = [2**k for k in range(1, 9)]
    with rasterio.open(base, "r+") as ds:
        ds.build_overviews(factors, Resampling.average)
    with rasterio.open(base) as ds:
        wkt = ds.crs.to_wkt()
    size = tile * copies + 1
    refs = []
    for level, f in enumerate(factors):
        side = -(-size // f)
        step = tile / f
        src = -(-(tile + 1) // f)
        sources = "".join(
            '<SimpleSource><SourceFilename relativeToVRT="1">tile.tif</SourceFilename>'
            f'<OpenOptions><OOI key="OVERVIEW_LEVEL">{level}</OOI></OpenOptions>'
            "<SourceBand>1</SourceBand>"
            f'<SrcRect xOff="0" yOff="0" xSize="{src}" ySize="{src}"/>'
            f'<DstRect xOff="{i * step}" yOff="{j * step}" xSize="{src}" ySize="{src}"/>'
            "</SimpleSource>"
            for j in range(copies)
            for i in range(copies)
        )
        name = f"{vrt.stem}.ov{f}.vrt"
        (vrt.parent / name).write_text(
            f'<VRTDataset rasterXSize="{side}" rasterYSize="{side}"><SRS>{escape(wkt)}</SRS>'
            f"<GeoTransform>500000.0, {2.0 * f}, 0.0, 4000000.0, 0.0, {-2.0 * f}</GeoTransform>"
            f'<VRTRasterBand dataType="Float32" band="1">{sources}</VRTRasterBand></VRTDataset>'
        )
        refs.append(
            f'<Overview><SourceFilename relativeToVRT="1">{name}</SourceFilename>'
            "<SourceBand>1</SourceBand></Overview>"
        )
    text = vrt.read_text()
    vrt.write_text(text.replace("</VRTRasterBand>", "".join(refs) + "</VRTRasterBand>"))


def _run(code: str, path: Path, mode: str, cache: Path) -> dict[str, float]:
    env = {**os.environ, "LODSCAPE_CACHE": str(cache)}
    proc = subprocess.run(
        [sys.executable, "-c", code, str(path), mode, str(HERE)],
        capture_output=True, text=True, env=env, timeout=1800,
    )  # fmt: skip
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-3:]
        raise RuntimeError(f"{mode} on {path.name} failed: {' | '.join(tail)}")
    if proc.stderr.strip():
        print(f"  [{mode} stderr] {proc.stderr.strip().splitlines()[-1]}", file=sys.stderr)
    out: dict[str, float] = json.loads(proc.stdout.strip().splitlines()[-1])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", default="1025,4097,16385,65537")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--eager-max", type=int, default=4097)
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    try:
        import panda3d  # noqa: F401

        stm = True
    except ImportError:
        stm = False
        print("Panda3D is not installed (pip install panda3d): no ShaderTerrainMesh runs")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        warm_first: dict[int, float] = {}
        for n in sizes:
            path = _dem(folder, n)
            results: dict[str, list[dict[str, float]]] = {}
            for r in range(args.rounds):
                cold = folder / f"cache-{n}-{r}"
                order = ["lazy cold", "lazy warm"]
                if n <= args.eager_max:
                    order.append("eager")
                if stm and n <= 4097:
                    order.append("stm")
                # alternate which engine starts each round
                order = order[r % len(order) :] + order[: r % len(order)]
                for mode in order:
                    if mode == "lazy warm" and not cold.exists():
                        _run(LODSCAPE, path, "lazy", cold)  # the cache the warm run finds
                    if mode == "stm":
                        got = _run(STM, path, "stm", cold)
                    elif mode == "lazy cold":
                        shutil.rmtree(cold, ignore_errors=True)
                        got = _run(LODSCAPE, path, "lazy", cold)
                    else:
                        got = _run(LODSCAPE, path, "eager" if mode == "eager" else "lazy", cold)
                    results.setdefault(mode, []).append(got)
            print(f"{n}² ({path.name}):")
            for mode, runs in results.items():
                s = [x["s"] for x in runs]
                line = (
                    f"  {mode:>9}: first picture {statistics.median(s):6.2f} s "
                    f"({min(s):.2f}–{max(s):.2f}), peak RSS "
                    f"{statistics.median(x['peak_mb'] for x in runs):5.0f} MB, read "
                    f"{statistics.median(x['read_mb'] for x in runs):8.1f} MB"
                )
                if runs[0].get("open_s") is not None:
                    line += f", open {statistics.median(x['open_s'] for x in runs):.2f} s"
                if runs[0].get("chunks") is not None:
                    line += f", {int(runs[0]['chunks'])} chunks"
                print(line, flush=True)
            if "lazy warm" in results:
                warm_first[n] = statistics.median(x["s"] for x in results["lazy warm"])
            if "stm" in results and "lazy cold" in results:
                a = statistics.median(x["s"] for x in results["lazy cold"])
                b = statistics.median(x["s"] for x in results["stm"])
                print(f"  lodscape cold / ShaderTerrainMesh: ×{a / b:.2f}")
            if "eager" in results and "lazy warm" in results:
                a = statistics.median(x["s"] for x in results["eager"])
                print(f"  eager / lazy (warm): ×{a / warm_first[n]:.2f}")
            shutil.rmtree(path.parent / f"m{n}", ignore_errors=True)
        if warm_first:
            small = min(warm_first)
            for n, s in warm_first.items():
                print(f"warm first picture {n}² / {small}²: ×{s / warm_first[small]:.2f}")


if __name__ == "__main__":
    main()
