"""lodscape against Panda3D's terrains, same machine, same DEM, same cameras, same texture.

Peers (Panda3D from PyPI: ``pip install 'lodscape[bench]'`` or ``pip install panda3d``),
offscreen on EGL as lodscape is:

- ``GeoMipTerrain`` (CPU geomipmapping), its LOD factor tuned per camera, by bisection, to the
  coarsest setting whose *measured* screen-space error stays within 2 px. The rule is
  lodscape's: a block's error is the largest vertical difference between its drawn mesh and the
  DEM's samples within it, projected at the distance from the eye to the block's box
  (H = h·d/dist, d = viewport height / (2·tan(fovy/2))), over the blocks in view. Block sizes
  32, 64 and 128 are tried and the one drawing fewest triangles kept; blocks are flattened
  into few geoms (``AFM_strong``) for the timed frames.
- ``ShaderTerrainMesh`` (GPU chunked LOD with CLOD, Panda3D's recommended terrain), chunk
  size 16, its target triangle width tuned per camera, by bisection over 0.5..64 px, to the
  widest whose measured error per pixel (below) stays within 2 px; where none does (its finest
  level cannot follow the DEM: its vertices sit at texel corners, their heights filtered
  between texel centres), its finest setting. Its error at the default width (10 px) is
  printed too.
- lodscape: ``lodscape.open(dem)`` with its defaults (max SSE 2 px, its own bound: a tile's
  recorded error as the projection draws it anywhere in its box), timed with the ellipsoid
  (its default) and without it ("bare": the peers clear those pixels), measured without it
  (where the data's edge lets the ellipsoid through, its points are not the terrain's).

Measured error per pixel, the same for all three: each drawn pixel's surface point (Panda3D: a
second draw writing world positions into a float target; lodscape: its distance read back,
through geodetic coordinates and the DEM's CRS) against the DEM's bilinear surface there: the
point and the DEM's point above or below it both projected with the camera, and the pixels
between them counted (a height error seen along the line of sight does not show; seen across
it, whole), as the 99.9th percentile and the largest value over the pixels on the DEM. The
older measure (the vertical difference at the pixel's distance, h·d/dist, whatever the
direction) is kept in the JSON as ``vertical_*``. The full-resolution mesh itself measures up
to about 0.8 px this way (a triangle is not the bilinear patch).

DEMs: the sample (``jacksboro.tif``, 403×344 geographic) and a 4097² spectral fBm (5 m, UTM
17N, ``bench_spine``'s). Panda3D gets the DEM's own grid in metres (a geographic grid by its
cell size at the centre latitude; flat, where lodscape draws it on the ellipsoid: 18 m of drop
15 km off centre), padded with its edge values to the size each terrain needs, and one texture:
lodscape's own tint (hypsometric colour × hillshade) of the whole DEM at its resolution.
Cameras are given over the DEM's grid and converted for both.

Per engine and DEM, a fresh process (its own GL context; peak RSS is ``VmHWM``): the time from
opening the DEM to the first frame read back, then per camera 3 warm-up frames and the median
of ``--repeat`` (20) frames at 1280×720 (``--resolution``), colour and depth read back by both
(lodscape its RGB and float32 distance, Panda3D its RGBA and depth textures copied to RAM).

The first picture from the file is timed apart, every engine in a fresh process per round
(reading the DEM, the peers' tint, the GL context and the terrain inside the clock; the peers
at their tuned settings for the first camera; lodscape with an empty cache, none of the tile
tree's statistics kept by the runs before; its modules compiled to bytecode first, as an
installed package's are). Each engine runs ``--rounds`` times (3),
alternating in fresh processes, with per-round figures;
a peer's stderr is kept, and a warning or error there fails its rows (Panda3D's notices are on
at warning level; the container's own notices, ``ENVIRONMENT``, are printed apart), as does a
measured error that is not a number. ShaderTerrainMesh's chunk limit is raised from 2048 to
``STM_MAX_CHUNKS`` (16384; ``BENCH_STM_CHUNKS``): at 2048 it drops half of the 4097² terrain,
at 65536 it draws nothing here. The detailed table below the rounds is the first round's.

    python bench/bench_peers.py [--repeat 20] [--rounds 3] [--size 4097] [--dem sample|fbm|both]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

#: The frames' size: 1280×720, or ``--resolution`` (``BENCH_PEERS_SIZE``, which the workers
#: inherit), e.g. 1920x1080 on a GPU.
W, H = (int(v) for v in os.environ.get("BENCH_PEERS_SIZE", "1280x720").split("x"))
FOV_Y = 60.0
MAX_SSE = 2.0
#: ShaderTerrainMesh's chunk limit (Panda3D's default 2048 drops half of a 4097² terrain).
STM_MAX_CHUNKS = int(os.environ.get("BENCH_STM_CHUNKS", "16384"))
#: Cameras over the DEM: position as fractions of its width (east) and height (from the north
#: edge), altitude above the DEM's highest point as a share of its extent, heading (clockwise
#: from grid north) and pitch.
CAMERAS = {
    "overview": (0.5, 1.25, 0.75, 0.0, -35.0),
    "oblique": (0.5, 0.9, 0.12, 0.0, -25.0),
    "low": (0.3, 0.75, 0.015, 30.0, -10.0),
    "down": (0.5, 0.5, 0.25, 0.0, -89.0),
}


def peak_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


# --- the data ---------------------------------------------------------------------------------


def read_dem(dem: Path) -> tuple[np.ndarray, float, float, np.ndarray, Any, Any]:
    """What a peer's user does first: the DEM's heights, its grid in metres (dx, dy), the shared
    texture (lodscape's tint of the whole DEM), its transform and CRS."""
    import rasterio

    from lodscape.imagery.tint import tint

    with rasterio.open(dem) as ds, warnings.catch_warnings():
        # rasterio 1.4 sets an array's shape, which NumPy 2.5 deprecates: said on the bench's
        # own line (its __main__ shows DeprecationWarnings), not a peer's warning
        warnings.simplefilter("ignore", DeprecationWarning)
        z = ds.read(1).astype(np.float32)
        tr, crs = ds.transform, ds.crs
    rows, cols = z.shape
    if crs.is_geographic:
        lat0 = math.radians(tr.f + tr.e * rows / 2)
        a, e2 = 6378137.0, 6.69437999014e-3
        s = 1 - e2 * math.sin(lat0) ** 2
        m_lat = math.radians(1) * a * (1 - e2) / s**1.5
        m_lon = math.radians(1) * a * math.cos(lat0) / math.sqrt(s)
        dx, dy = abs(tr.a) * m_lon, abs(tr.e) * m_lat
    else:
        dx, dy = abs(tr.a), abs(tr.e)
    lo, hi = float(z.min()), float(z.max())
    bordered = np.pad(z, 1, mode="edge")
    # tint wants a square grid: pad to a square and crop the colours back
    n = max(rows, cols)
    sq = np.pad(bordered, ((0, n - rows), (0, n - cols)), mode="edge")
    rgb = tint(sq, np.ones(sq.shape, bool), math.sqrt(dx * dy), (lo, hi))[:rows, :cols]
    return z, dx, dy, np.ascontiguousarray(rgb), tr, crs


def prepare(dem: Path, out: Path) -> dict[str, Any]:
    """The DEM's heights, its grid in metres, the shared texture and the cameras."""
    from rasterio.warp import transform as warp

    z, dx, dy, rgb, tr, crs = read_dem(dem)
    rows, cols = z.shape
    lo, hi = float(z.min()), float(z.max())
    np.save(out / "heights.npy", z)
    np.save(out / "texture.npy", rgb)
    extent = max(rows * dy, cols * dx)
    cams = {}
    for name, (fx, fy, fa, heading, pitch) in CAMERAS.items():
        col, row = fx * (cols - 1), fy * (rows - 1)
        alt = hi + fa * extent
        x, y = tr * (col + 0.5, row + 0.5)
        lon, lat = (v[0] for v in warp(crs, "EPSG:4326", [x], [y]))
        # grid north as a true bearing at the camera (meridian convergence)
        x2, y2 = tr * (col + 0.5, row + 0.5 - 100.0)
        lon2, lat2 = (v[0] for v in warp(crs, "EPSG:4326", [x2], [y2]))
        east = (lon2 - lon) * math.cos(math.radians(lat))
        conv = math.degrees(math.atan2(east, lat2 - lat))
        cams[name] = {
            "col": col, "row": row, "alt": alt, "heading": heading, "pitch": pitch,
            "lon": lon, "lat": lat, "true_heading": heading + conv,
        }  # fmt: skip
    meta = {"dem": str(dem), "dx": dx, "dy": dy, "lo": lo, "hi": hi, "cameras": cams}
    (out / "meta.json").write_text(json.dumps(meta))
    return meta


# --- the measured error, per pixel, the same for every engine ---------------------------------


def _dem_at(z: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear DEM heights at fractional (col, row) of its samples; NaN outside the samples."""
    rows, cols = z.shape
    inside = (col >= 0) & (col <= cols - 1) & (row >= 0) & (row <= rows - 1)
    c = np.clip(col, 0, cols - 1.000001)
    r = np.clip(row, 0, rows - 1.000001)
    c0, r0 = np.floor(c).astype(np.int64), np.floor(r).astype(np.int64)
    fc, fr = c - c0, r - r0
    top = z[r0, c0] * (1 - fc) + z[r0, c0 + 1] * fc
    bottom = z[r0 + 1, c0] * (1 - fc) + z[r0 + 1, c0 + 1] * fc
    return np.where(inside, top * (1 - fr) + bottom * fr, np.nan)


def screen_shift(
    world: np.ndarray,
    normal: np.ndarray,
    dh: np.ndarray,
    eye: np.ndarray,
    axes: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """Pixels between each drawn point and the DEM's point above or below it (``dh`` metres
    along its ``normal``, the vertical), both projected with the camera at ``eye`` whose
    ``axes`` are (right, up, forward): the error as the picture shows it."""
    d = H / (2 * math.tan(math.radians(FOV_Y / 2)))
    right, up, fwd = axes

    def image(p: np.ndarray) -> np.ndarray:
        rel = p - eye
        z = rel @ fwd
        return d * np.stack([rel @ right / z, rel @ up / z], axis=-1)

    with np.errstate(invalid="ignore"):
        there = world - dh[:, None] * normal
        out: np.ndarray = np.linalg.norm(image(world) - image(there), axis=-1)
    return out


def pixel_sse(dh: np.ndarray, dist: np.ndarray, shift: np.ndarray) -> dict[str, float]:
    """Per pixel on the DEM: ``shift``, the pixels between the drawn point and the DEM's at the
    same place, both projected (``screen_shift``); its largest value and its 99.9th
    percentile. Beside it (``vertical_*``) the older measure: the vertical difference ``dh``
    taken at the pixel's distance (h·d/dist), whatever the direction it is seen from."""
    d = H / (2 * math.tan(math.radians(FOV_Y / 2)))
    ok = np.isfinite(dh) & np.isfinite(dist) & (dist > 0) & np.isfinite(shift)
    if not ok.any():
        nan = float("nan")
        return {"pixel_sse_max": nan, "pixel_sse_p999": nan, "vertical_p999": nan, "pixels": 0}
    vertical = np.abs(dh[ok]) * d / dist[ok]
    return {
        "pixel_sse_max": float(shift[ok].max()),
        "pixel_sse_p999": float(np.percentile(shift[ok], 99.9)),
        "vertical_max": float(vertical.max()),
        "vertical_p999": float(np.percentile(vertical, 99.9)),
        "pixels": int(ok.sum()),
    }


# --- lodscape ---------------------------------------------------------------------------------


def _lodscape_error(
    meta: dict[str, Any], z: np.ndarray, cam: Any, depth: np.ndarray
) -> dict[str, float]:
    """lodscape's frame measured as the peers' are: each pixel's point, from its distance,
    to geodetic height and the DEM's grid (through the DEM's CRS)."""
    import rasterio
    from pyproj import Transformer

    from lodscape.geo.frames import ecef_to_geodetic

    t = math.tan(math.radians(cam.fov_y) / 2)
    x = ((np.arange(W) + 0.5) / W * 2 - 1) * t * W / H
    y = (1 - (np.arange(H) + 0.5) / H * 2) * t
    xx, yy = np.meshgrid(x, y)
    ok = np.isfinite(depth.ravel())
    far = np.where(np.isfinite(depth), depth, 0.0)[..., None].astype(np.float64)
    view = np.stack([xx, yy, -np.ones_like(xx)], -1) * far
    world = cam.position + view.reshape(-1, 3) @ cam.rotation
    lon, lat, h = ecef_to_geodetic(world[ok])
    with rasterio.open(meta["dem"]) as ds:
        to = Transformer.from_crs("EPSG:4326", ds.crs, always_xy=True)
        inv = ~ds.transform
    gx, gy = to.transform(lon, lat)
    col, row = inv * (np.asarray(gx), np.asarray(gy))
    dh = np.full(depth.size, np.nan)
    dh[ok] = h - _dem_at(z, np.asarray(col) - 0.5, np.asarray(row) - 0.5)
    dist = np.linalg.norm(world - cam.position, axis=1)
    lam, phi = np.radians(lon), np.radians(lat)
    normal = np.zeros((depth.size, 3))
    normal[ok] = np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)], -1)
    rot = cam.rotation
    shift = screen_shift(world, normal, dh, cam.position, (rot[0], rot[1], -rot[2]))
    return pixel_sse(dh, dist, shift)


def _camera(c: dict[str, float]) -> Any:
    """A bench camera as lodscape's (true heading: grid north turned by the convergence)."""
    from lodscape import Camera

    return Camera(
        c["lon"], c["lat"], c["alt"], heading=c["true_heading"], pitch=c["pitch"],
        fov_y=FOV_Y, width=W, height=H,
    )  # fmt: skip


def lodscape_views(rounds: int) -> tuple[Any, Path, dict[str, Any]]:
    """For the benches that time lodscape alone at these cameras (bench_readback,
    bench_meshes): their arguments (``--dem``, the sample by default; ``--resolution``;
    ``--rounds``; ``--repeat``), the DEM and its four cameras at that resolution."""
    import lodscape.data

    ap = argparse.ArgumentParser()
    ap.add_argument("--dem", type=Path, help="a GeoTIFF (default: the sample)")
    ap.add_argument("--resolution", default="1280x720")
    ap.add_argument("--rounds", type=int, default=rounds)
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    w, h = (int(v) for v in args.resolution.split("x"))
    dem = args.dem or Path(lodscape.data.__file__).parent / "jacksboro.tif"
    with tempfile.TemporaryDirectory() as tmp:
        meta = prepare(dem, Path(tmp))
    cams = {name: replace(_camera(c), width=w, height=h) for name, c in meta["cameras"].items()}
    return args, dem, cams


def ground_depth(scene: Any, cam: Any) -> np.ndarray:
    """The distances of a frame of ``cam`` drawn without the ellipsoid: the ground alone (where
    the data's edge lets the ellipsoid through, its points are not the terrain's)."""
    renderer = scene.renderer
    assert renderer is not None
    renderer.ellipsoid = False
    try:
        depth: np.ndarray = scene.render(cam)[1]
    finally:
        renderer.ellipsoid = True
    return depth


def run_lodscape(data: Path, repeat: int) -> dict[str, Any]:
    import lodscape

    meta = json.loads((data / "meta.json").read_text())
    z = np.load(data / "heights.npy").astype(np.float64)
    t0 = time.perf_counter()
    scene = lodscape.open(meta["dem"], lodscape.SceneOptions(anisotropy=1.0))
    out: dict[str, Any] = {"cameras": {}}
    for i, (name, c) in enumerate(meta["cameras"].items()):
        cam = _camera(c)
        scene.render(cam)
        if i == 0:
            out["first_frame_s"] = time.perf_counter() - t0
        for _ in range(3):
            scene.render(cam)
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            rgb, depth = scene.render(cam)
            times.append(time.perf_counter() - t)
        assert depth.shape == (H, W)
        assert rgb.shape == (H, W, 3)
        st = scene.frame_stats()
        # the same frame without the ellipsoid: the peers leave those pixels the clear colour
        renderer = scene.renderer
        assert renderer is not None
        renderer.ellipsoid = False
        bare = []
        for k in range(2 + repeat):
            t = time.perf_counter()
            _, depth = scene.render(cam)
            if k >= 2:
                bare.append(time.perf_counter() - t)
        renderer.ellipsoid = True
        # measured on the last frame without it (``ground_depth``'s reason)
        out["cameras"][name] = {
            "frame_ms": statistics.median(times) * 1e3,
            "bare_ms": statistics.median(bare) * 1e3,
            "triangles": int(st["triangles"]),
            "max_sse": float(st["max_sse_px"]),
            "draw_calls": int(st["draw_calls"]),
            "ground": float(np.isfinite(depth).mean()),
            **_lodscape_error(meta, z, scene.prepare(cam), depth),
        }
    out["peak_rss_mb"] = peak_rss_mb()
    if os.environ.get("BENCH_PEERS_TUNE", "1") == "0":
        scene.close()
        return out
    # the same frames with the bound loosened, per camera, as far as the error measured per
    # pixel stays within 2 px (its 99.9th percentile, as ShaderTerrainMesh is tuned): the
    # bound holds at a tile's worst point, the measure is what was drawn
    base_options = scene.view.options
    for name, c in meta["cameras"].items():
        cam = _camera(c)
        loose, tight = 64.0, MAX_SSE
        for _ in range(10):
            mid = math.sqrt(loose * tight)
            scene.view.options = replace(base_options, max_sse=mid)
            scene.view.previous = None  # a fresh selection: no hysteresis from another bound
            got = _lodscape_error(meta, z, scene.prepare(cam), ground_depth(scene, cam))
            if got["pixel_sse_p999"] <= MAX_SSE:
                tight = mid
            else:
                loose = mid
            if loose / tight < 1.05:
                break
        scene.view.options = replace(base_options, max_sse=tight)
        scene.view.previous = None
        for _ in range(3):
            scene.render(cam)
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            scene.render(cam)
            times.append(time.perf_counter() - t)
        got = _lodscape_error(meta, z, scene.prepare(cam), ground_depth(scene, cam))
        out["cameras"][name]["tuned"] = {
            "max_sse": tight,
            "frame_ms": statistics.median(times) * 1e3,
            "triangles": int(scene.frame_stats()["triangles"]),
            **got,
        }
    scene.view.options = base_options
    scene.close()
    return out


# --- Panda3D ----------------------------------------------------------------------------------


def _panda() -> Any:
    from panda3d.core import loadPrcFileData

    loadPrcFileData(
        "",
        f"load-display p3headlessgl\nwindow-type offscreen\nwin-size {W} {H}\n"
        "audio-library-name null\nsync-video false\nnotify-level warning\n"
        "framebuffer-srgb false\n"
        # ShaderTerrainMesh draws at most 2048 chunks by default and drops the rest of the
        # terrain with an error (half the 4097² DEM): raised so it draws it all
        f"stm-max-chunk-count {STM_MAX_CHUNKS}\n",
    )
    from direct.showbase.ShowBase import ShowBase

    base = ShowBase(windowType="offscreen")
    hfov = 2 * math.degrees(math.atan(math.tan(math.radians(FOV_Y / 2)) * W / H))
    base.camLens.setFov(hfov, FOV_Y)
    base.camLens.setNearFar(1.0, 2.0e5)
    base.disableMouse()
    return base


def _readback(base: Any) -> tuple[Any, Any]:
    from panda3d.core import GraphicsOutput, Texture

    colour, depth = Texture(), Texture()
    base.win.addRenderTexture(colour, GraphicsOutput.RTMCopyRam, GraphicsOutput.RTPColor)
    base.win.addRenderTexture(depth, GraphicsOutput.RTMCopyRam, GraphicsOutput.RTPDepth)
    return colour, depth


def _frame(base: Any, colour: Any, depth: Any) -> tuple[np.ndarray, np.ndarray]:
    base.graphicsEngine.renderFrame()
    rgb = np.frombuffer(colour.getRamImage(), np.uint8)
    z = np.frombuffer(depth.getRamImage(), np.uint8)
    return rgb, z


class _Probe:
    """A float target the terrain is drawn into a second time, by a shader writing each
    fragment's world position: the surface Panda3D drew, exactly, to measure against the DEM."""

    def __init__(self, base: Any) -> None:
        from panda3d.core import (
            FrameBufferProperties,
            GraphicsOutput,
            GraphicsPipe,
            Texture,
            WindowProperties,
        )

        fbp = FrameBufferProperties()
        fbp.setRgbaBits(32, 32, 32, 32)
        fbp.setFloatColor(True)
        fbp.setDepthBits(24)
        self.base = base
        self.buffer = base.graphicsEngine.makeOutput(
            base.pipe, "probe", -2, fbp, WindowProperties.size(W, H),
            GraphicsPipe.BF_refuse_window, base.win.getGsg(), base.win,
        )  # fmt: skip
        self.texture = Texture()
        self.buffer.addRenderTexture(self.texture, GraphicsOutput.RTMCopyRam)
        self.buffer.setClearColor((0, 0, 0, 0))
        self.camera = base.makeCamera(self.buffer, lens=base.camLens)
        self.camera.reparentTo(base.camera)
        self.buffer.setActive(False)

    def measure(self, node: Any, shader: Any, meta: dict[str, Any], z: np.ndarray,
                size: int) -> dict[str, float]:  # fmt: skip
        """Draw ``node`` with ``shader`` into the float target; the per-pixel error."""
        base = self.base
        main = node.getShader()
        node.setShader(shader, 100)
        base.win.setActive(False)
        self.buffer.setActive(True)
        base.graphicsEngine.renderFrame()
        base.graphicsEngine.renderFrame()
        self.buffer.setActive(False)
        base.win.setActive(True)
        if main is not None:
            node.setShader(main)
        else:
            node.clearShader()
        img = np.frombuffer(self.texture.getRamImage(), np.float32).reshape(H, W, 4)
        world = img[..., 2::-1].astype(np.float64).reshape(-1, 3)  # Panda3D keeps BGRA
        drawn = img[..., 3].ravel() > 0.5
        col = world[:, 0] / meta["dx"]
        row = (size - 1) - world[:, 1] / meta["dy"]
        dh = np.where(drawn, world[:, 2] - _dem_at(z, col, row), np.nan)
        eye = np.array(base.camera.getPos(base.render))
        mat = base.camera.getMat(base.render)  # rows: right, forward, up (Panda3D is Z-up)
        axes = (np.array(mat.getRow3(0)), np.array(mat.getRow3(2)), np.array(mat.getRow3(1)))
        axes = tuple(a / np.linalg.norm(a) for a in axes)
        shift = screen_shift(world, np.array([0.0, 0.0, 1.0]), dh, eye, axes)  # type: ignore[arg-type]
        return pixel_sse(dh, np.linalg.norm(world - eye, axis=1), shift)


_PROBE_VERTEX = """
#version 330
in vec4 p3d_Vertex;
uniform mat4 p3d_ModelViewProjectionMatrix;
uniform mat4 p3d_ModelMatrix;
out vec3 world;
void main() {
  gl_Position = p3d_ModelViewProjectionMatrix * p3d_Vertex;
  world = (p3d_ModelMatrix * p3d_Vertex).xyz;
}
"""

_PROBE_FRAGMENT = """
#version 330
in vec3 world;
out vec4 color;
void main() { color = vec4(world, 1.0); }
"""


def _load(data: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray]:
    """What ``prepare`` wrote: the metadata, the heights (float32 and float64), the texture."""
    z = np.load(data / "heights.npy")
    meta = json.loads((data / "meta.json").read_text())
    return meta, z, z.astype(np.float64), np.load(data / "texture.npy")


def _texture(rgb: np.ndarray, size: int) -> Any:
    """The shared texture on a size² canvas (edge padded or cropped), Panda's rows bottom-up,
    BGR."""
    from panda3d.core import SamplerState, Texture

    rows, cols, _ = rgb.shape
    pad = ((0, max(0, size - rows)), (0, max(0, size - cols)), (0, 0))
    img = np.pad(rgb, pad, mode="edge")[:size, :size]
    tex = Texture("ground")
    tex.setup2dTexture(size, size, Texture.T_unsigned_byte, Texture.F_rgb)
    tex.setRamImage(np.ascontiguousarray(img[::-1, :, ::-1]).tobytes())
    tex.setMinfilter(SamplerState.FT_linear_mipmap_linear)
    tex.setMagfilter(SamplerState.FT_linear)
    tex.setWrapU(SamplerState.WM_clamp)
    tex.setWrapV(SamplerState.WM_clamp)
    return tex


def _place(base: Any, c: dict[str, float], size: int, dx: float, dy: float) -> None:
    """A camera over the grid: image row r is at y = (size - 1 - r)·dy; heading clockwise."""
    base.camera.setPos(c["col"] * dx, (size - 1 - c["row"]) * dy, c["alt"])
    base.camera.setHpr(-c["heading"], c["pitch"], 0.0)


def _geoms(root: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every GeomNode under ``root``: vertices (N, 3) in root space and triangles (M, 3)."""
    out = []
    for path in root.findAllMatches("**/+GeomNode"):
        mat = np.array(path.getMat(root), dtype=np.float64).reshape(4, 4)
        node = path.node()
        for g in range(node.getNumGeoms()):
            geom = node.getGeom(g)
            vdata = geom.getVertexData()
            fmt = vdata.getFormat().getArray(0)
            col = fmt.getColumn("vertex")
            stride = fmt.getStride() // 4
            raw = np.frombuffer(memoryview(vdata.getArray(0)), np.float32)
            rows = raw.reshape(-1, stride)[: vdata.getNumRows()]
            # rows a geom holds but no triangle uses may be unset (any bits, signalling NaNs
            # included): read as they are, never used as a vertex
            with np.errstate(invalid="ignore", over="ignore"):
                v = rows[:, col.getStart() // 4 : col.getStart() // 4 + 3].astype(np.float64)
                good = np.isfinite(v).all(axis=1) & (np.abs(v) < 1e9).all(axis=1)
            v = np.c_[np.where(good[:, None], v, 0.0), np.ones(len(v))] @ mat[:, :3]
            for p in range(geom.getNumPrimitives()):
                prim = geom.getPrimitive(p).decompose()
                if prim.isIndexed():
                    dt = {1: np.uint8, 2: np.uint16, 4: np.uint32}[prim.getIndexStride()]
                    idx = np.frombuffer(memoryview(prim.getVertices()), dt).astype(np.int64)
                else:
                    first = prim.getFirstVertex()
                    idx = np.arange(first, first + prim.getNumVertices(), dtype=np.int64)
                tris = idx.reshape(-1, 3)
                if not good[tris].all():
                    raise RuntimeError("GeoMipTerrain drew a vertex that is not a number")
                out.append((v, tris))
    return out


def _mesh_errors(
    geoms: list[tuple[np.ndarray, np.ndarray]], hf: np.ndarray, cache: dict[Any, Any]
) -> np.ndarray:
    """Per geom (a block): the largest |DEM − mesh| over the DEM samples under its triangles
    (heightfield units), and the box of those samples: (B, 7) err, x0, y0, z0, x1, y1, z1 in
    grid units. ``cache`` keeps blocks already measured (same corner, same triangles)."""
    size = hf.shape[0]
    rows = []
    for v, tris in geoms:
        gx = np.rint(v[:, 0]).astype(np.int64)
        gy = np.rint(v[:, 1]).astype(np.int64)
        used = np.unique(tris)
        x0, x1 = int(gx[used].min()), int(gx[used].max())
        y0, y1 = int(gy[used].min()), int(gy[used].max())
        key = (x0, y0, x1, y1, hash(tris.tobytes()))
        got = cache.get(key)
        if got is None:
            got = _block_error(gx, gy, v[:, 2], tris, hf)
            block = hf[size - 1 - y1 : size - y0, x0 : x1 + 1]
            got = (got, x0, y0, float(block.min()), x1, y1, float(block.max()))
            cache[key] = got
        rows.append(got)
    return np.array(rows, dtype=np.float64).reshape(-1, 7)


def _block_error(
    gx: np.ndarray, gy: np.ndarray, z: np.ndarray, tris: np.ndarray, hf: np.ndarray
) -> float:
    """The largest |DEM − mesh| over the DEM samples under a block's triangles."""
    size = hf.shape[0]
    p = np.stack([gx[tris], gy[tris]], -1)  # (M, 3, 2)
    zt = z[tris]
    # canonical order per triangle, then group triangles of one shape
    order = np.lexsort((p[:, :, 1], p[:, :, 0]), axis=1)
    p = np.take_along_axis(p, order[:, :, None], 1)
    zt = np.take_along_axis(zt, order, 1)
    rel = (p[:, 1:] - p[:, :1]).reshape(len(p), 4)
    shapes, inverse = np.unique(rel, axis=0, return_inverse=True)
    err = 0.0
    for k, (ax, ay, bx, by) in enumerate(shapes):
        det = ax * by - ay * bx
        if det == 0 or max(abs(ax), abs(ay), abs(bx), abs(by)) <= 1:
            continue  # degenerate or full-resolution: no sample between its corners
        sel = np.flatnonzero(inverse.ravel() == k)
        xs = np.arange(min(0, ax, bx), max(0, ax, bx) + 1)
        ys = np.arange(min(0, ay, by), max(0, ay, by) + 1)
        ox, oy = (a.ravel() for a in np.meshgrid(xs, ys))
        # barycentric weights of the offsets in this shape
        w1 = (ox * by - oy * bx) / det
        w2 = (ax * oy - ay * ox) / det
        w0 = 1 - w1 - w2
        inside = (w0 >= -1e-9) & (w1 >= -1e-9) & (w2 >= -1e-9)
        ox, oy, w = ox[inside], oy[inside], np.stack([w0, w1, w2], -1)[inside]
        sx = p[sel, 0, 0][:, None] + ox[None]
        sy = p[sel, 0, 1][:, None] + oy[None]
        ok = (sx >= 0) & (sx < size) & (sy >= 0) & (sy < size)
        truth = hf[np.clip(size - 1 - sy, 0, size - 1), np.clip(sx, 0, size - 1)]
        d = np.where(ok, np.abs(truth - zt[sel] @ w.T), 0.0)
        err = max(err, float(d.max(initial=0.0)))
    return err


def _view_sse(blocks: np.ndarray, c: dict[str, float], size: int, meta: dict[str, Any]) -> float:
    """The largest block error in pixels, over the blocks whose box is (partly) in view."""
    dx, dy, lo, hi = meta["dx"], meta["dy"], meta["lo"], meta["hi"]
    blocks = blocks[blocks[:, 0] > 0]
    if not len(blocks):
        return 0.0
    scale = np.array([dx, dy, hi - lo])
    offset = np.array([0.0, 0.0, lo])
    a = blocks[:, 1:4] * scale + offset
    b = blocks[:, 4:7] * scale + offset
    eye = np.array([c["col"] * dx, (size - 1 - c["row"]) * dy, c["alt"]])
    h, p = math.radians(c["heading"]), math.radians(c["pitch"])
    fwd = np.array([math.sin(h) * math.cos(p), math.cos(h) * math.cos(p), math.sin(p)])
    right = np.array([math.cos(h), -math.sin(h), 0.0])
    up = np.cross(right, fwd)
    ty = math.tan(math.radians(FOV_Y / 2))
    tx = ty * W / H
    # the boxes' eight corners, relative to the eye: (B, 8, 3)
    pick = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)
    corners = np.where(pick[None], b[:, None, :], a[:, None, :]) - eye
    zc, xc, yc = corners @ fwd, corners @ right, corners @ up
    # outside the frustum when all corners are beyond one of its planes
    out = (
        (zc <= 0).all(1)
        | (xc > tx * zc).all(1)
        | (xc < -tx * zc).all(1)
        | (yc > ty * zc).all(1)
        | (yc < -ty * zc).all(1)
    )
    dist = np.linalg.norm(np.maximum(np.maximum(a - eye, 0.0), eye - b), axis=1)
    sse = blocks[:, 0] * (hi - lo) * (H / (2 * ty)) / np.maximum(dist, 1e-3)
    return float(sse[~out].max(initial=0.0))


def _triangles(root: Any, base: Any = None) -> int:
    """The triangles of the terrain's geoms; with ``base``, of those Panda3D draws from its
    camera (their bounds meet the lens's frustum: it culls the rest, lodscape's counts are
    after its own culling)."""
    from panda3d.core import BoundingBox, BoundingVolume

    frustum = None if base is None else base.camLens.makeBounds()
    n = 0
    for path in root.findAllMatches("**/+GeomNode"):
        if frustum is not None:
            lo, hi = path.getTightBounds(base.cam)
            if frustum.contains(BoundingBox(lo, hi)) == BoundingVolume.IF_no_intersection:
                continue
        node = path.node()
        for g in range(node.getNumGeoms()):
            geom = node.getGeom(g)
            for p in range(geom.getNumPrimitives()):
                n += geom.getPrimitive(p).decompose().getNumFaces()
    return n


def _hf_image(hf: np.ndarray) -> Any:
    from panda3d.core import PNMImage, StringStream

    size = hf.shape[0]
    q = np.rint(np.clip(hf, 0, 1) * 65535).astype(">u2")
    img = PNMImage()
    if not img.read(StringStream(f"P5 {size} {size} 65535\n".encode() + q.tobytes()), "hf.pgm"):
        raise RuntimeError("Panda3D could not read the heightfield")
    return img


def geomip_heights(z: np.ndarray, size: int) -> np.ndarray:
    """The heightfield GeoMipTerrain gets: 0..1 over the DEM's range, padded with its edge to
    size², as its 16-bit image holds it."""
    rows, cols = z.shape
    lo, hi = float(z.min()), float(z.max())
    hf = np.pad((z - lo) / (hi - lo), ((0, size - rows), (0, size - cols)), mode="edge")
    out: np.ndarray = np.rint(hf * 65535) / 65535
    return out


def geomip_terrain(
    base: Any,
    hf: np.ndarray,
    tex: Any,
    grid: tuple[float, float, float, float],
    block: int,
    factor: float,
    flatten: bool,
) -> Any:
    """A GeoMipTerrain of ``hf`` placed in metres (``grid``: dx, dy, lo, hi), not generated."""
    from panda3d.core import GeoMipTerrain

    dx, dy, lo, hi = grid
    t = GeoMipTerrain("terrain")
    t.setHeightfield(_hf_image(hf))
    t.setBlockSize(block)
    t.setMinLevel(0)
    t.setBruteforce(False)
    t.setFactor(factor)
    t.setFocalPoint(base.camera)
    t.setAutoFlatten(GeoMipTerrain.AFM_strong if flatten else GeoMipTerrain.AFM_off)
    root = t.getRoot()
    root.setScale(dx, dy, hi - lo)
    root.setZ(lo)
    root.setTexture(tex)
    return t


def run_geomip(data: Path, repeat: int) -> dict[str, Any]:
    from panda3d.core import Shader

    meta, z, z64, rgb = _load(data)
    lo, hi, dx, dy = meta["lo"], meta["hi"], meta["dx"], meta["dy"]
    rows, cols = z.shape
    size = 2 ** math.ceil(math.log2(max(rows, cols) - 1)) + 1
    base = _panda()
    colour, depth = _readback(base)
    hf = geomip_heights(z, size)
    tex = _texture(rgb, size)
    probe = _Probe(base)
    probe_shader = Shader.make(Shader.SL_GLSL, _PROBE_VERTEX, _PROBE_FRAGMENT)

    def terrain(block: int, factor: float, flatten: bool) -> Any:
        return geomip_terrain(base, hf, tex, (dx, dy, lo, hi), block, factor, flatten)

    cache: dict[Any, Any] = {}

    def sse(t: Any, c: dict[str, float]) -> float:
        return _view_sse(_mesh_errors(_geoms(t.getRoot()), hf, cache), c, size, meta)

    out: dict[str, Any] = {"cameras": {}}
    tuned: dict[str, tuple[int, float]] = {}
    t_tune = time.perf_counter()
    for name, c in meta["cameras"].items():
        _place(base, c, size, dx, dy)
        best: tuple[int, float, int, float] | None = None
        # small blocks follow the error more closely but make many nodes: on a large DEM the
        # tuning (and Panda3D's culling) would take too long
        for block in (32, 64, 128) if size <= 1025 else (64,):
            if block >= size:
                continue
            # the level is floor(distance / factor) (GeoMipTerrain's rule): a larger factor
            # draws finer. One terrain per block size, updated as the factor changes (as a
            # moving camera's would be: only the blocks whose level changes are rebuilt)
            fine, coarse = 1e6, 1e-2
            t = terrain(block, math.sqrt(fine * coarse), False)
            t.generate()
            for step in range(18):
                mid = math.sqrt(fine * coarse)
                t.setFactor(mid)
                base.camera.setX(base.camera.getX() + (1e-3 if step % 2 else -1e-3))
                t.update()
                if sse(t, c) <= MAX_SSE:
                    fine = mid
                else:
                    coarse = mid
                if fine / coarse < 1.05:
                    break
            t.getRoot().removeNode()
            _place(base, c, size, dx, dy)
            t = terrain(block, fine, False)
            t.generate()
            tris, err = _triangles(t.getRoot()), sse(t, c)
            t.getRoot().removeNode()
            if best is None or tris < best[2]:
                best = (block, fine, tris, err)
        assert best is not None
        tuned[name] = (best[0], best[1])
        out["cameras"][name] = {"block": best[0], "factor": best[1], "triangles": best[2],
                                "max_sse": best[3]}  # fmt: skip
    out["tuning_s"] = time.perf_counter() - t_tune

    for i, (name, c) in enumerate(meta["cameras"].items()):
        _place(base, c, size, dx, dy)
        block, factor = tuned[name]
        # two ways to draw it: its blocks as they are, updated every frame (a moving camera's
        # loop), or flattened into few geoms and never updated (the static camera's best; an
        # update after flattening loses the LOD and draws every sample): the faster is kept
        best: dict[str, Any] | None = None
        for flatten in (False, True):
            t0 = time.perf_counter()
            t = terrain(block, factor, flatten)
            t.getRoot().reparentTo(base.render)
            t.generate()
            _frame(base, colour, depth)
            first = time.perf_counter() - t0
            times = []
            for k in range(3 + repeat):
                s = time.perf_counter()
                if not flatten:
                    t.update()
                _frame(base, colour, depth)
                if k >= 3:
                    times.append(time.perf_counter() - s)
            got = {
                "frame_ms": statistics.median(times) * 1e3,
                "first_s": first,
                "flattened": flatten,
                "drawn_triangles": _triangles(t.getRoot()),
                "triangles_in_view": _triangles(t.getRoot(), base),
                **probe.measure(t.getRoot(), probe_shader, meta, z64, size),
            }
            t.getRoot().removeNode()
            if best is None or got["frame_ms"] < best["frame_ms"]:
                best = got
        assert best is not None
        if i == 0:
            out["first_frame_s"] = best["first_s"]
        out["cameras"][name].update(best)
    out["peak_rss_mb"] = peak_rss_mb()
    # the measure's floor: the full-resolution mesh (every sample a vertex) measured the same way
    t = terrain(64 if size > 64 else size - 1, 1.0, True)
    t.setBruteforce(True)
    t.getRoot().reparentTo(base.render)
    t.generate()
    for name, c in meta["cameras"].items():
        _place(base, c, size, dx, dy)
        full = probe.measure(t.getRoot(), probe_shader, meta, z64, size)
        out["cameras"][name]["floor_max"] = full["pixel_sse_max"]
        out["cameras"][name]["floor_p999"] = full["pixel_sse_p999"]
    t.getRoot().removeNode()
    return out


_STM_VERTEX = """
#version 330
in vec4 p3d_Vertex;
uniform mat4 p3d_ModelViewProjectionMatrix;
uniform mat4 p3d_ModelMatrix;
uniform struct {
  sampler2D data_texture;
  sampler2D heightfield;
  int view_index;
  int terrain_size;
  int chunk_size;
} ShaderTerrainMesh;
out vec2 terrain_uv;
out vec3 world;
void main() {
  vec4 terrain_data = texelFetch(ShaderTerrainMesh.data_texture,
                                 ivec2(gl_InstanceID, ShaderTerrainMesh.view_index), 0);
  vec3 pos = p3d_Vertex.xyz;
  float clod = smoothstep(0, 1, terrain_data.w);
  pos.xy -= clod * fract(pos.xy * ShaderTerrainMesh.chunk_size / 2.0) * 2.0
            / ShaderTerrainMesh.chunk_size;
  pos *= terrain_data.z * float(ShaderTerrainMesh.chunk_size)
         / float(ShaderTerrainMesh.terrain_size);
  pos.z *= ShaderTerrainMesh.chunk_size;
  pos.xy += terrain_data.xy / float(ShaderTerrainMesh.terrain_size);
  terrain_uv = pos.xy;
  pos.z += texture(ShaderTerrainMesh.heightfield, terrain_uv).x;
  gl_Position = p3d_ModelViewProjectionMatrix * vec4(pos, 1);
  world = (p3d_ModelMatrix * vec4(pos, 1)).xyz;
}
"""

_STM_FRAGMENT = """
#version 330
in vec2 terrain_uv;
uniform sampler2D p3d_Texture0;
out vec4 color;
void main() { color = vec4(texture(p3d_Texture0, terrain_uv).rgb, 1.0); }
"""


def stm_terrain(
    base: Any, z: np.ndarray, rgb: np.ndarray, size: int, dx: float, dy: float
) -> tuple[Any, Any]:
    """A ShaderTerrainMesh of heights ``z`` (rows north first) with texture ``rgb`` on a size²
    heightfield, placed in metres and shaded by its shader: (terrain, node)."""
    from panda3d.core import SamplerState, Shader, ShaderTerrainMesh, Texture

    rows, cols = z.shape
    lo, hi = float(z.min()), float(z.max())
    # a power of two: a 2^k + 1 grid loses its last row and column
    pad = ((0, max(0, size - rows)), (0, max(0, size - cols)))
    hf = np.pad((z - lo) / (hi - lo), pad, mode="edge")[:size, :size]
    htex = Texture("heightfield")
    htex.setup2dTexture(size, size, Texture.T_unsigned_short, Texture.F_r16)
    htex.setRamImage(np.ascontiguousarray(np.rint(hf[::-1] * 65535).astype(np.uint16)).tobytes())
    htex.setMinfilter(SamplerState.FT_linear)
    htex.setMagfilter(SamplerState.FT_linear)
    htex.setWrapU(SamplerState.WM_clamp)
    htex.setWrapV(SamplerState.WM_clamp)
    stm = ShaderTerrainMesh()
    stm.setHeightfield(htex)
    stm.setTargetTriangleWidth(10.0)
    stm.setChunkSize(16)
    if not stm.generate():
        raise RuntimeError("ShaderTerrainMesh.generate failed")
    node = base.render.attachNewNode(stm)
    # pixel centres at (i + 0.5)/size: the sample i at i·dx
    node.setScale(size * dx, size * dy, hi - lo)
    node.setPos(-0.5 * dx, -0.5 * dy, lo)
    node.setShader(Shader.make(Shader.SL_GLSL, _STM_VERTEX, _STM_FRAGMENT))
    node.setShaderInput("camera", base.camera)
    node.setTexture(_texture(rgb, size))
    return stm, node


def run_stm(data: Path, repeat: int) -> dict[str, Any]:
    from panda3d.core import Shader

    meta, z, z64, rgb = _load(data)
    dx, dy = meta["dx"], meta["dy"]
    rows, cols = z.shape
    size = max(64, 2 ** math.ceil(math.log2(max(rows, cols) - 1)))
    base = _panda()
    colour, depth = _readback(base)
    out: dict[str, Any] = {"cameras": {}}
    t0 = time.perf_counter()
    stm, node = stm_terrain(base, z, rgb, size, dx, dy)
    _place(base, next(iter(meta["cameras"].values())), size, dx, dy)
    _frame(base, colour, depth)
    out["first_frame_s"] = time.perf_counter() - t0
    probe = _Probe(base)
    probe_shader = Shader.make(Shader.SL_GLSL, _STM_VERTEX, _PROBE_FRAGMENT)
    t_tune = time.perf_counter()
    for name, c in meta["cameras"].items():
        _place(base, c, size, dx, dy)
        # the widest target triangle width (pixels) whose measured error is within the bound
        # (its 99.9th percentile over the pixels: the largest is the measure's own floor
        # near the eye, where a triangle and the bilinear patch part)
        wide, narrow = 64.0, 0.5
        for _ in range(12):
            mid = math.sqrt(wide * narrow)
            stm.setTargetTriangleWidth(mid)
            if probe.measure(node, probe_shader, meta, z64, size)["pixel_sse_p999"] <= MAX_SSE:
                narrow = mid
            else:
                wide = mid
            if wide / narrow < 1.05:
                break
        out["cameras"][name] = {"target_px": narrow}
    out["tuning_s"] = time.perf_counter() - t_tune
    for name, c in meta["cameras"].items():
        _place(base, c, size, dx, dy)
        stm.setTargetTriangleWidth(out["cameras"][name]["target_px"])
        _frame(base, colour, depth)
        for _ in range(3):
            _frame(base, colour, depth)
        times = []
        for _ in range(repeat):
            s = time.perf_counter()
            _frame(base, colour, depth)
            times.append(time.perf_counter() - s)
        out["cameras"][name]["frame_ms"] = statistics.median(times) * 1e3
        out["cameras"][name].update(probe.measure(node, probe_shader, meta, z64, size))
        # its default, for reference
        stm.setTargetTriangleWidth(10.0)
        default = probe.measure(node, probe_shader, meta, z64, size)
        out["cameras"][name]["default_sse_max"] = default["pixel_sse_max"]
    out["peak_rss_mb"] = peak_rss_mb()
    return out


ENGINES = {"lodscape": run_lodscape, "geomip": run_geomip, "stm": run_stm}


# --- the first picture from the file ----------------------------------------------------------


def first_lodscape(data: Path, params: dict[str, Any]) -> dict[str, Any]:
    """From the DEM's file to the first camera's picture read back: lodscape's open (reading,
    its tile tree, tint, GL context) and render."""
    meta = json.loads((data / "meta.json").read_text())
    cam_spec = next(iter(meta["cameras"].values()))
    with tempfile.TemporaryDirectory() as cache:
        # a cold open: none of the tree's statistics that the frames' runs kept in the cache
        # (the peers keep nothing between runs)
        os.environ["LODSCAPE_CACHE"] = cache
        t0 = time.perf_counter()
        import lodscape

        scene = lodscape.open(meta["dem"], lodscape.SceneOptions(anisotropy=1.0))
        scene.render(_camera(cam_spec))
        first = time.perf_counter() - t0
        scene.close()
    return {"first_picture_s": first}


def first_geomip(data: Path, params: dict[str, Any]) -> dict[str, Any]:
    """The same for GeoMipTerrain at its tuned settings for that camera: reading the DEM and
    tinting it (as ``prepare``), Panda3D's window and context, the terrain, one frame."""
    meta = json.loads((data / "meta.json").read_text())
    c = next(iter(meta["cameras"].values()))
    t0 = time.perf_counter()
    z, dx, dy, rgb, _, _ = read_dem(Path(meta["dem"]))
    rows, cols = z.shape
    size = 2 ** math.ceil(math.log2(max(rows, cols) - 1)) + 1
    base = _panda()
    colour, depth = _readback(base)
    grid = (dx, dy, float(z.min()), float(z.max()))
    t = geomip_terrain(
        base, geomip_heights(z, size), _texture(rgb, size), grid,
        int(params["block"]), float(params["factor"]), bool(params["flattened"]),
    )  # fmt: skip
    t.getRoot().reparentTo(base.render)
    _place(base, c, size, dx, dy)
    t.generate()
    _frame(base, colour, depth)
    return {"first_picture_s": time.perf_counter() - t0}


def first_stm(data: Path, params: dict[str, Any]) -> dict[str, Any]:
    """The same for ShaderTerrainMesh at its tuned width for that camera."""
    meta = json.loads((data / "meta.json").read_text())
    c = next(iter(meta["cameras"].values()))
    t0 = time.perf_counter()
    z, dx, dy, rgb, _, _ = read_dem(Path(meta["dem"]))
    rows, cols = z.shape
    size = max(64, 2 ** math.ceil(math.log2(max(rows, cols) - 1)))
    base = _panda()
    colour, depth = _readback(base)
    stm, _ = stm_terrain(base, z, rgb, size, dx, dy)
    stm.setTargetTriangleWidth(float(params["target_px"]))
    _place(base, c, size, dx, dy)
    _frame(base, colour, depth)
    return {"first_picture_s": time.perf_counter() - t0}


FIRST = {"lodscape": first_lodscape, "geomip": first_geomip, "stm": first_stm}


def first_params(engine: str, got: dict[str, Any]) -> dict[str, Any]:
    """What a first-picture worker needs of its engine's run: the first camera's settings."""
    c = next(iter(got["cameras"].values()))
    if engine == "geomip":
        return {"block": c["block"], "factor": c["factor"], "flattened": c["flattened"]}
    if engine == "stm":
        return {"target_px": c["target_px"]}
    return {}


# --- the comparison ---------------------------------------------------------------------------


def _px(c: dict[str, float]) -> str:
    return f"{c['pixel_sse_p999']:4.2f}/{c['pixel_sse_max']:4.2f}"


def worker(
    engine: str, data: Path, repeat: int, params: dict[str, Any] | None = None
) -> dict[str, Any]:
    """``engine`` on ``data`` in a fresh process (``first-<engine>``: its first picture from
    the file, with ``params``); its figures."""
    res = subprocess.run(
        [
            sys.executable,
            __file__,
            "--worker",
            engine,
            "--data",
            str(data),
            "--repeat",
            str(repeat),
            "--params",
            json.dumps(params or {}),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    if res.returncode != 0:
        raise RuntimeError(f"{engine} failed:\n{res.stderr[-3000:]}")
    got: dict[str, Any] = json.loads(res.stdout.strip().splitlines()[-1])
    # a peer's warnings are part of its result: kept, and they fail its rows, but for the
    # container's notices every Panda3D process prints (ENVIRONMENT: no input devices, no
    # default EGL display before it takes a device's), listed apart
    lines = [line.strip() for line in res.stderr.splitlines() if line.strip()]
    said = [
        line
        for line in lines
        if "(warning)" in line or "(error)" in line or "Warning" in line or "Error" in line
    ]
    got["environment"] = [w for w in said if any(e in w for e in ENVIRONMENT)]
    got["warnings"] = [w for w in said if not any(e in w for e in ENVIRONMENT)]
    # a camera whose measured error is not a number drew nothing the probe could read
    for name, c in got.get("cameras", {}).items():
        if not math.isfinite(float(c.get("pixel_sse_p999", 0.0))):
            got["warnings"].append(f"{engine} {name}: the measured error is not a number")
    return got


#: stderr lines that say where the bench runs, not how an engine did (printed, not failing).
ENVIRONMENT = (
    "/dev/input",
    "Couldn't initialize the default EGL display",
)


def _bytecode() -> None:
    """lodscape's modules compiled to bytecode before any engine runs, as ``pip install``
    leaves an installed package (and the peers' Python modules): an editable install where
    ``PYTHONDONTWRITEBYTECODE`` is set (this development machine) compiled every module again in
    every fresh process, 0.16–0.18 s of lodscape's first picture of the sample in a profile."""
    import compileall

    import lodscape

    compileall.compile_dir(str(Path(lodscape.__file__).parent), quiet=1)


def compare(
    label: str,
    dem: Path,
    repeat: int,
    tmp: Path,
    engines: tuple[str, ...] = tuple(ENGINES),
    rounds: int = 1,
) -> None:
    data = tmp / label
    if (data / "meta.json").exists():
        meta = json.loads((data / "meta.json").read_text())  # a kept --workdir: reused
    else:
        data.mkdir(parents=True, exist_ok=True)
        meta = prepare(dem, data)
    print(f"\n## {label}: {dem.name}, grid {meta['dx']:.1f}×{meta['dy']:.1f} m")
    # the engines in fresh processes, alternating, round after round (each round starting
    # with the next engine), so a shared machine's load falls on all of them alike
    runs: dict[str, list[dict[str, Any]]] = {e: [] for e in engines}
    for r in range(rounds):
        order = [*engines[r % len(engines) :], *engines[: r % len(engines)]]
        for e in order:
            kept = data / f"{e}.{r}.json"
            if kept.exists():
                runs[e].append(json.loads(kept.read_text()))  # a kept --workdir
                continue
            runs[e].append(worker(e, data, repeat))
            kept.write_text(json.dumps(runs[e][-1]))
    # the first picture from the file, every engine in a fresh process, alternating
    first: dict[str, list[float]] = {e: [] for e in engines}
    for r in range(rounds):
        order = [*engines[r % len(engines) :], *engines[: r % len(engines)]]
        for e in order:
            kept = data / f"first-{e}.{r}.json"
            if kept.exists():
                got = json.loads(kept.read_text())
            else:
                got = worker(f"first-{e}", data, repeat, first_params(e, runs[e][r]))
                kept.write_text(json.dumps(got))
            runs[e][r].setdefault("warnings", []).extend(got.get("warnings", []))
            first[e].append(got["first_picture_s"])
    print(
        "first picture from the file (reading, tint, context, tree, one frame read back), "
        "s per round: "
        + "; ".join(f"{e} " + "/".join(f"{v:.2f}" for v in vs) for e, vs in first.items())
    )
    for e, rs in runs.items():
        said = sorted({w for got in rs for w in got.get("warnings", [])})
        where = sorted({w for got in rs for w in got.get("environment", [])})
        if said:
            print(f"{e}: FAIL: {len(said)} warning lines on stderr:")
            for w in said[:10]:
                print(f"    {w}")
        if where:
            print(f"{e}: the environment's notices on stderr: " + "; ".join(where))
    if rounds > 1 and set(engines) == set(ENGINES):
        print(
            f"per round (frame ms, median of {repeat}), ratio peer / lodscape "
            "(> 1: lodscape faster):"
        )
        for name in CAMERAS:
            cells = []
            for r in range(rounds):
                a, g, st = (runs[e][r]["cameras"][name]["frame_ms"] for e in ENGINES)
                bare = runs["lodscape"][r]["cameras"][name].get("bare_ms", float("nan"))
                cells.append(
                    f"r{r + 1} {a:.1f} ({bare:.1f})/{g:.1f}/{st:.1f} ×{g / a:.2f} ×{st / a:.2f}"
                )
            print(f"{name:>9} | lodscape (no ellipsoid)/GeoMip/STM: " + " | ".join(cells))
        for peer, title in (("geomip", "GeoMipTerrain"), ("stm", "ShaderTerrainMesh")):
            for key, how in (("frame_ms", ""), ("bare_ms", ", lodscape without the ellipsoid")):
                meds = [
                    statistics.median(
                        runs[peer][r]["cameras"][n]["frame_ms"]
                        / runs["lodscape"][r]["cameras"][n].get(key, float("nan"))
                        for n in CAMERAS
                    )
                    for r in range(rounds)
                ]
                print(
                    f"{title}{how}: median ratio per round "
                    f"{', '.join(f'×{m:.2f}' for m in meds)} "
                    f"(range ×{min(meds):.2f}–×{max(meds):.2f})"
                )
    res = {e: rs[0] for e, rs in runs.items()}
    if set(engines) != set(ENGINES):
        for e, r in res.items():
            for name, c in r["cameras"].items():
                print(f"{e:>9} {name:>9}: " + ", ".join(f"{k} {v:.2f}" for k, v in c.items()))
            print(
                f"{e:>9}: first frame {r['first_frame_s']:.2f} s, "
                f"peak RSS {r['peak_rss_mb']:.0f} MB"
            )
        return
    print(
        "per camera: frame ms (median), triangles, screen-space error in px (lodscape's bound; "
        "for all, measured per pixel: 99.9th percentile / largest), ratio = peer frame / "
        "lodscape frame (> 1: lodscape faster); bare: lodscape without the ellipsoid (the "
        "peers clear those pixels); full mesh: the measure's floor"
    )
    print(
        f"{'camera':>9} | {'lodscape':>8} {'(bare)':>7} {'tris':>8} {'bound':>4} "
        f"{'p99.9/max':>9} | "
        f"{'GeoMip':>7} {'tris':>8} {'p99.9/max':>9} {'ratio':>6} | {'STM':>6} {'width':>6} "
        f"{'p99.9/max':>9} {'ratio':>6} | full mesh"
    )
    ratios_g, ratios_s = [], []
    for name in CAMERAS:
        a, g, s = (res[e]["cameras"][name] for e in ENGINES)
        rg, rs = g["frame_ms"] / a["frame_ms"], s["frame_ms"] / a["frame_ms"]
        ratios_g.append(rg)
        ratios_s.append(rs)
        print(
            f"{name:>9} | {a['frame_ms']:8.1f} ({a.get('bare_ms', float('nan')):5.1f}) "
            f"{a['triangles']:8,d} "
            f"{a['max_sse']:4.2f} {_px(a)} | "
            f"{g['frame_ms']:7.1f} {g['triangles']:8,d} {_px(g)} ×{rg:5.2f} | "
            f"{s['frame_ms']:6.1f} {s['target_px']:6.1f} {_px(s)} ×{rs:5.2f} | "
            f"{g['floor_p999']:4.2f}/{g['floor_max']:4.2f}"
        )
    seen = [res["geomip"]["cameras"][name].get("triangles_in_view") for name in CAMERAS]
    if all(v is not None for v in seen):
        print(
            "GeoMipTerrain's triangles in its camera's frustum (what Panda3D draws; the "
            "column counts the whole terrain's): "
            + ", ".join(f"{name} {v:,d}" for name, v in zip(CAMERAS, seen, strict=True))
        )
    med = statistics.median
    print(
        "median frame ratio (peer / lodscape, >1: lodscape faster): "
        f"GeoMipTerrain ×{med(ratios_g):.2f}, ShaderTerrainMesh ×{med(ratios_s):.2f}"
    )
    print(
        "lodscape with its bound loosened per camera to the same measured error as "
        "ShaderTerrainMesh's tuning (99.9th percentile within 2 px):"
    )
    tg, ts = [], []
    for name in CAMERAS:
        a, g, s = (res[e]["cameras"][name] for e in ENGINES)
        u = a.get("tuned")
        if u is None:
            continue
        tg.append(g["frame_ms"] / u["frame_ms"])
        ts.append(s["frame_ms"] / u["frame_ms"])
        print(
            f"{name:>9} | bound {u['max_sse']:5.2f} px: {u['frame_ms']:7.1f} ms "
            f"{u['triangles']:9,d} tris, measured {_px(u)} | GeoMip ×{tg[-1]:5.2f} | "
            f"STM ×{ts[-1]:5.2f}"
        )
    if tg:
        print(
            f"median ratio, tuned: GeoMipTerrain ×{med(tg):.2f}, ShaderTerrainMesh ×{med(ts):.2f}"
        )
    for e in ENGINES:
        print(
            f"{e:>9}: first frame {res[e]['first_frame_s']:.2f} s, "
            f"peak RSS {res[e]['peak_rss_mb']:.0f} MB"
            + (f", tuning {res[e]['tuning_s']:.0f} s" if "tuning_s" in res[e] else "")
        )
    print(
        "GeoMipTerrain block size and factor per camera:",
        {n: (c["block"], round(c["factor"], 1)) for n, c in res["geomip"]["cameras"].items()},
    )
    print(
        "ShaderTerrainMesh at its default width (10 px), max SSE px per camera:",
        {n: round(c["default_sse_max"], 2) for n, c in res["stm"]["cameras"].items()},
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument(
        "--rounds", type=int, default=3,
        help="each engine this many times, alternating (A, B, C, B, C, A, …), per-round figures",
    )  # fmt: skip
    ap.add_argument("--size", type=int, default=4097)
    ap.add_argument("--dem", choices=("sample", "fbm", "both"), default="both")
    ap.add_argument("--worker", choices=(*ENGINES, *(f"first-{e}" for e in FIRST)))
    ap.add_argument("--params", default="{}", help="a first-picture worker's settings (JSON)")
    ap.add_argument("--data", type=Path)
    ap.add_argument(
        "--no-tune", action="store_true",
        help="lodscape at its default bound only (not also loosened to the peers' measured error)",
    )  # fmt: skip
    ap.add_argument(
        "--workdir", type=Path,
        help="keep the data and each engine's figures here (a run again reuses them; "
        "default: a temporary folder)",
    )  # fmt: skip
    ap.add_argument(
        "--engines", nargs="+", choices=tuple(ENGINES), default=list(ENGINES),
        help="a subset (its figures alone, no table): e.g. lodscape, with PYTHONPATH on another "
        "checkout's src to compare two versions",
    )  # fmt: skip
    ap.add_argument(
        "--resolution", default=f"{W}x{H}", help="frame size, WIDTHxHEIGHT (default 1280x720)"
    )
    args = ap.parse_args()
    if args.resolution != f"{W}x{H}":
        os.environ["BENCH_PEERS_SIZE"] = args.resolution
        os.execv(sys.executable, [sys.executable, *sys.argv])  # this process at that size too
    if args.no_tune:
        os.environ["BENCH_PEERS_TUNE"] = "0"  # the workers inherit it
    if args.worker:
        if args.worker.startswith("first-"):
            run = FIRST[args.worker.removeprefix("first-")]
            print(json.dumps(run(args.data, json.loads(args.params))))
        else:
            print(json.dumps(ENGINES[args.worker](args.data, args.repeat)))
        return
    try:
        if set(args.engines) != {"lodscape"}:
            import panda3d  # noqa: F401
    except ImportError:
        sys.exit("bench_peers needs Panda3D: pip install panda3d")
    import lodscape.data
    from bench_spine import write

    _bytecode()
    with tempfile.TemporaryDirectory() as t:
        tmp = args.workdir or Path(t)
        tmp.mkdir(parents=True, exist_ok=True)  # a --workdir not made yet
        if args.dem in ("sample", "both"):
            sample = Path(lodscape.data.__file__).parent / "jacksboro.tif"
            compare("sample", sample, args.repeat, tmp, tuple(args.engines), args.rounds)
        if args.dem in ("fbm", "both"):
            path = tmp / f"fbm{args.size}.tif"
            if not path.exists():
                write(path, args.size)
            compare(f"fbm{args.size}", path, args.repeat, tmp, tuple(args.engines), args.rounds)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()
