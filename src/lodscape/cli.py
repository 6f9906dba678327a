"""The ``lodscape`` command: a thin map from flags onto the Python API (mercantile ``scripts/``).

Bad input ends with one line on stderr naming the problem, exit status 2, and no output file:
outputs are written to a temporary name beside the target and renamed only when complete.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, NamedTuple

import numpy as np
import typer
from numpy.typing import NDArray

from lodscape._tmp import temp_beside
from lodscape.city.rtree import DEFAULT_PACKING
from lodscape.errors import LodscapeError
from lodscape.frame.globe import GlobeOptions
from lodscape.lod.camera import Camera
from lodscape.lod.select import SelectOptions
from lodscape.scene import Scene, SceneOptions
from lodscape.sources import open as open_scene
from lodscape.sources import parse_source
from lodscape.stream.streamer import Clock
from lodscape.terrain.detail import Fractal, parse_procedural

app = typer.Typer(
    name="lodscape",
    help="Render huge 3D landscapes with per-tile level of detail.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        from lodscape import __version__

        typer.echo(f"lodscape {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Print the version and exit."
        ),
    ] = False,
) -> None:
    """Render huge 3D landscapes with per-tile level of detail."""


def _size(value: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected WIDTHxHEIGHT such as 1280x720, got {value!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise typer.BadParameter(f"width and height must be 1..16384 pixels, got {value!r}")
    return w, h


def _finite(value: float | None) -> float | None:
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"must be a finite number, got {value}")
    return value


def _pitch(value: float | None) -> float | None:
    if value is not None and not -90.0 <= value <= 90.0:  # NaN included
        raise typer.BadParameter(f"must be within -90..90 degrees, got {value}")
    return value


def _roll(value: float | None) -> float | None:
    if value is not None and not -180.0 <= value <= 180.0:
        raise typer.BadParameter(f"must be within -180..180 degrees, got {value}")
    return value


SizeOpt = Annotated[str, typer.Option("--size", help="Viewport WIDTHxHEIGHT in pixels.")]
FovOpt = Annotated[float, typer.Option(callback=_finite, help="Vertical field of view, °.")]
HeadingOpt = Annotated[float, typer.Option(callback=_finite, help="Degrees clockwise from north.")]
OutOpt = Annotated[Path, typer.Option("-o", "--output", help="Image to write (.png, .jpg, .tif).")]
SseOpt = Annotated[float, typer.Option("--max-sse", help="Screen-space error bound, pixels.")]
CameraFileOpt = Annotated[
    Path | None,
    typer.Option(
        "--camera",
        help="A camera file (JSON: lon, lat, alt, heading, pitch, roll, fov_y), as the viewer's "
        "K key saves them.",
    ),
]
GroundOpt = Annotated[
    str,
    typer.Option(
        "--ground",
        help="tint: the terrain's own colours (or --imagery); landcover: ground materials "
        "picked by OSM land use, natural areas and roads (from --landcover, or --city).",
    ),
]
LandcoverOpt = Annotated[
    Path | None,
    typer.Option(
        help="An OpenStreetMap file whose land use colours the ground (--ground landcover)."
    ),
]
AnisotropyOpt = Annotated[
    float,
    typer.Option(
        callback=_finite, help="Anisotropic filtering cap (software rasterisers: always 1)."
    ),
]
TerrainModeOpt = Annotated[
    str,
    typer.Option(
        "--terrain-mode",
        help="cpu: tile meshes (the quadtree); gpu: height textures tessellated in hardware "
        "(falls back to cpu, with a notice, where tessellation is missing).",
    ),
]
MeshesOpt = Annotated[
    str,
    typer.Option(
        "--meshes",
        help="The cpu mode's tile meshes: tin (each tile's RTIN cut at the error its place on "
        "screen allows: fewer triangles), grid (regular grids, which geomorph), auto (tin for "
        "a picture, grid for frames that geomorph).",
    ),
]
ImageryOpt = Annotated[
    list[str] | None,
    typer.Option(
        help="An imagery layer, drawn at its own resolution over the terrain's tint: an XYZ URL "
        "template (https://{s}.host/{z}/{x}/{y}.png), an .mbtiles file, a folder of z/x/y "
        "tiles, or a georeferenced raster (a GeoTIFF orthophoto, any CRS). Repeat it for "
        "layers drawn bottom to top with their transparency."
    ),
]
MaxZoomOpt = Annotated[
    int | None,
    typer.Option(
        "--imagery-maxzoom",
        min=0,
        max=24,
        help="The finest level to ask imagery for (URL templates: default 19; files: their own).",
    ),
]
ImageryTimeoutOpt = Annotated[
    float,
    typer.Option(
        "--imagery-timeout",
        min=0.0,
        help="Seconds a render waits for imagery, all tiles together; what has not come by "
        "then is drawn without (said on stderr). Flights never wait.",
    ),
]
ImageryStrictOpt = Annotated[
    bool,
    typer.Option(
        "--imagery-strict", help="Any imagery failure (404, error, timeout…) is an error (exit 2)."
    ),
]
CacheOpt = Annotated[
    Path | None,
    typer.Option(
        help="Folder for the imagery cache (default: $LODSCAPE_CACHE, else "
        "$XDG_CACHE_HOME/lodscape)."
    ),
]


DetailOpt = Annotated[
    str,
    typer.Option(
        help="Detail below the data's resolution: none, or fractal (fBm by midpoint "
        "displacement, paper 003)."
    ),
]
HurstOpt = Annotated[
    float | None,
    typer.Option(
        callback=_finite,
        help="Roughness of the fractal detail, 0 < H < 1 (rough .. smooth). Default 0.7; a "
        "procedural source's own otherwise.",
    ),
]
SigmaOpt = Annotated[
    float | None,
    typer.Option(
        callback=_finite,
        help="Metres of the first fractal step below the data (default: from the data's own "
        "roughness).",
    ),
]
SeedOpt = Annotated[int | None, typer.Option(help="Seed of the fractal detail (default 0).")]


def _detail(
    source: str, detail: str, hurst: float | None, sigma: float | None, seed: int | None
) -> Fractal | None:
    """The fractal detail the flags ask for (None: none); one-line errors."""
    procedural = parse_source(source).kind == "procedural"
    if detail not in ("none", "fractal"):
        raise LodscapeError(f"--detail must be none or fractal, got {detail!r}")
    if detail == "none" and not procedural:
        if hurst is not None or sigma is not None or seed is not None:
            raise LodscapeError("--hurst, --sigma and --seed need --detail fractal")
        return None
    if procedural and hurst is None and sigma is None and seed is None:
        return None
    try:
        if procedural:
            spec = parse_procedural(source)
            return Fractal(
                spec.hurst if hurst is None else hurst,
                spec.sigma if sigma is None else sigma,
                spec.seed if seed is None else seed,
            )
        return Fractal(0.7 if hurst is None else hurst, sigma, 0 if seed is None else seed)
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None


FillOpt = Annotated[
    str | None,
    typer.Option(
        "--fill",
        help="What stands where the DEM has no data: none (a hole: nothing drawn; the "
        "default), nearest (the nearest height stretched), value:H (level ground at H m), "
        "ellipsoid (height 0) or interpolate (voids inside the data filled from their rims, "
        "height 0 outside it). A tileset keeps the fill it was built with.",
    ),
]
SeaLevelOpt = Annotated[
    str,
    typer.Option(
        "--sea-level",
        help="Heights below this (metres) are tinted as water, shaded by depth; none: no sea.",
    ),
]
EllipsoidOpt = Annotated[
    bool,
    typer.Option(
        "--ellipsoid/--no-ellipsoid",
        help="Draw the ellipsoid (height 0, grey) wherever there is no terrain: the world "
        "outside the data and under its holes; --no-ellipsoid shows the sky there.",
    ),
]
MorphOpt = Annotated[
    bool,
    typer.Option(
        "--morph/--no-morph",
        help="Geomorph between levels (both terrain modes, in flights and the viewer): a tile "
        "that replaces a coarser one glides from its surface to its own over 10 frames "
        "instead of jumping.",
    ),
]
CityTreeOpt = Annotated[
    str,
    typer.Option(
        "--city-tree",
        help="How the city's scene tree is packed: hilbert (the default), str, or priority "
        "(the Priority R-tree; best on long thin objects, not on a city's).",
    ),
]
CityBuffersOpt = Annotated[
    bool,
    typer.Option(
        "--city-buffers/--no-city-buffers",
        help="Draw the city with its camera in a uniform buffer and its street objects' "
        "instances in a storage buffer (OpenGL 4.3; off: plain uniforms and instanced "
        "attributes, faster on a software rasteriser).",
    ),
]
CompressOpt = Annotated[
    bool,
    typer.Option(
        "--compress-textures/--no-compress-textures",
        help="Send imagery textures to the GPU block-compressed (BC1/BC3, compressed on the "
        "worker threads): a sixth to a quarter of the texture memory, at a small loss of colour.",
    ),
]
BandOpt = Annotated[
    int | None,
    typer.Option("--band", min=1, help="The height band of a multi-band raster (1-based)."),
]
NodataOpt = Annotated[
    float | None,
    typer.Option(
        "--nodata", callback=_finite, help="A nodata value the DEM uses but does not declare."
    ),
]
ZUnitsOpt = Annotated[
    str | None,
    typer.Option(
        "--z-units",
        help="The DEM's height unit: m, ft, us-ft, or metres per unit (default: the band's "
        "unit, a vertical CRS's, else a projected CRS's own; metres where nothing says).",
    ),
]


def _sea_level(text: str) -> float | None:
    """--sea-level: metres, or none."""
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise LodscapeError(f"--sea-level must be metres or none, got {text!r}")
    return value


ImageryBandsOpt = Annotated[
    str | None,
    typer.Option(
        "--imagery-bands",
        help="R,G,B: the bands (1-based) of a raster imagery layer to draw as red, green and "
        "blue (default: its colour interpretation, else its first three, said once).",
    ),
]
#: MiB each of GPU, memory and cache a streaming command (fly, view) keeps by default.
BUDGET_MB = 256.0
BudgetOpt = Annotated[
    float, typer.Option(callback=_finite, help="MiB each of GPU, memory and cache.")
]
CityOpt = Annotated[
    Path | None,
    typer.Option(help="An OpenStreetMap file (.osm.pbf, .osm) whose city to drape on the terrain."),
]


#: The library's defaults, which the flags' are.
_SCENE, _SELECT = SceneOptions(), SelectOptions()


@dataclass(frozen=True)
class TerrainFlags:
    """The terrain flags render, fly and view share, declared once (``_terrain_flags``): their
    defaults are the library's options' (``SceneOptions``, ``SelectOptions``), written there."""

    max_sse: float = _SELECT.max_sse
    terrain_mode: str = _SCENE.terrain_mode
    meshes: str = _SCENE.meshes
    ground: str = "tint"
    landcover: Path | None = None
    anisotropy: float = _SCENE.anisotropy
    imagery: list[str] | None = None
    imagery_cache: Path | None = None
    imagery_maxzoom: int | None = None
    imagery_bands: str | None = None
    imagery_timeout: float = _SCENE.imagery_timeout
    imagery_strict: bool = _SCENE.imagery_strict
    detail: str = "none"
    hurst: float | None = None
    sigma: float | None = None
    seed: int | None = None
    city: Path | None = None
    fill: str | None = None
    sea_level: str = "0"
    band: int | None = None
    nodata: float | None = None
    z_units: str | None = None
    ellipsoid: bool = _SCENE.ellipsoid
    morph: bool = _SCENE.morph
    compress_textures: bool = _SCENE.compress_textures
    city_tree: str = DEFAULT_PACKING
    city_buffers: bool = False

    def fractal(self, source: str) -> Fractal | None:
        return _detail(source, self.detail, self.hurst, self.sigma, self.seed)

    def options(self, budget_mb: float | None = None) -> SceneOptions:
        return _scene_options(
            max_sse=self.max_sse,
            anisotropy=self.anisotropy,
            terrain_mode=self.terrain_mode,
            meshes=self.meshes,
            budget_mb=budget_mb,
            imagery_timeout=self.imagery_timeout,
            imagery_strict=self.imagery_strict,
            ellipsoid=self.ellipsoid,
            morph=self.morph,
            compress_textures=self.compress_textures,
        )

    def open(
        self,
        source: str,
        options: SceneOptions,
        *,
        clock: Clock | None = None,
        detail: Fractal | bool | None = True,
    ) -> Scene:
        """The scene the flags ask for (``detail`` True: the flags' own fractal detail)."""
        scene: Scene = open_scene(source, options, clock=clock, **self.open_kwargs(source, detail))
        return scene

    def inputs(self) -> dict[str, Any]:
        """The files the flags read (what no output may overwrite), by flag."""
        return {"--city": self.city, "--imagery": self.imagery, "--landcover": self.landcover}

    def open_kwargs(self, source: str, detail: Fractal | bool | None = True) -> dict[str, Any]:
        """``lodscape.open``'s keywords for SOURCE from the flags."""
        cover = _landcover(self.ground, self.landcover, self.city)
        if self.imagery and cover is not None:
            raise LodscapeError("--imagery and --ground landcover both colour the ground: pick one")
        if parse_source(source).text == "flat" and self.city is None:
            raise LodscapeError("SOURCE flat (level ground) needs --city to know where")
        return {
            "detail": self.fractal(source) if detail is True else detail or None,
            "landcover": cover,
            "imagery": self.imagery or None,
            "imagery_cache": self.imagery_cache,
            "imagery_maxzoom": self.imagery_maxzoom,
            "imagery_bands": self.imagery_bands,
            "city": self.city,
            "fill": self.fill,
            "sea_level": _sea_level(self.sea_level),
            "band": self.band,
            "nodata": self.nodata,
            "z_units": self.z_units,
            "city_options": self.city_options(),
        }

    def city_options(self) -> Any:
        from lodscape.city.model import CityOptions
        from lodscape.city.rtree import PACKINGS

        if self.city_tree not in PACKINGS:
            raise LodscapeError(
                f"--city-tree: expected {', '.join(PACKINGS)}, got {self.city_tree!r}"
            )
        return CityOptions(packing=self.city_tree, buffers=self.city_buffers)


def _in_panel(ann: Any, panel: str) -> Any:
    """``ann`` (an ``Annotated`` option) shown under ``panel`` in ``--help``."""
    import copy
    from typing import get_args

    kind, info = get_args(ann)
    info = copy.copy(info)
    info.rich_help_panel = panel
    return Annotated[kind, info]


#: The shared terrain flags, by help panel: (name, option, default).
_FLAG_PANELS: dict[str, tuple[tuple[str, Any], ...]] = {
    "Terrain (DEM)": (
        ("fill", FillOpt),
        ("sea_level", SeaLevelOpt),
        ("band", BandOpt),
        ("nodata", NodataOpt),
        ("z_units", ZUnitsOpt),
        ("detail", DetailOpt),
        ("hurst", HurstOpt),
        ("sigma", SigmaOpt),
        ("seed", SeedOpt),
    ),
    "Level of detail and drawing": (
        ("max_sse", SseOpt),
        ("terrain_mode", TerrainModeOpt),
        ("meshes", MeshesOpt),
        ("anisotropy", AnisotropyOpt),
        ("morph", MorphOpt),
        ("ellipsoid", EllipsoidOpt),
        ("compress_textures", CompressOpt),
    ),
    "Imagery and ground": (
        ("imagery", ImageryOpt),
        ("imagery_cache", CacheOpt),
        ("imagery_maxzoom", MaxZoomOpt),
        ("imagery_bands", ImageryBandsOpt),
        ("imagery_timeout", ImageryTimeoutOpt),
        ("imagery_strict", ImageryStrictOpt),
        ("ground", GroundOpt),
        ("landcover", LandcoverOpt),
    ),
    "City": (
        ("city", CityOpt),
        ("city_tree", CityTreeOpt),
        ("city_buffers", CityBuffersOpt),
    ),
}
_TERRAIN_FLAGS = [
    inspect.Parameter(
        name,
        inspect.Parameter.KEYWORD_ONLY,
        default=TerrainFlags.__dataclass_fields__[name].default,
        annotation=_in_panel(ann, panel),
    )
    for panel, flags in _FLAG_PANELS.items()
    for name, ann in flags
]


def _terrain_flags(command: Callable[..., None]) -> Callable[..., None]:
    """Give ``command`` the shared terrain flags: typer sees them in its signature, and the
    command gets them as one ``terrain: TerrainFlags``."""
    sig = inspect.signature(command, eval_str=True)
    own = [p for p in sig.parameters.values() if p.name != "terrain"]
    names = [p.name for p in _TERRAIN_FLAGS]

    @functools.wraps(command)
    def wrapper(**kwargs: Any) -> None:
        flags = TerrainFlags(**{n: kwargs.pop(n) for n in names if n in kwargs})
        command(terrain=flags, **kwargs)

    wrapper.__signature__ = sig.replace(parameters=[*own, *_TERRAIN_FLAGS])  # type: ignore[attr-defined]
    return wrapper


def _scene_options(
    *,
    max_sse: float,
    anisotropy: float,
    terrain_mode: str,
    meshes: str,
    budget_mb: float | None,
    imagery_timeout: float,
    imagery_strict: bool,
    ellipsoid: bool,
    morph: bool,
    compress_textures: bool,
) -> SceneOptions:
    """Scene options from flags; a value the engine refuses is a one-line usage error. With
    ``budget_mb``, a streaming scene with that many MiB each of GPU, memory and cache."""
    from lodscape.stream import StreamOptions

    streaming: dict[str, Any] = {}
    try:
        if budget_mb is not None:
            if not budget_mb > 0.0:
                raise LodscapeError(f"--budget-mb must be more than 0 MiB, got {budget_mb:g}")
            streaming = {
                "gpu_budget_mb": budget_mb,
                "stream": StreamOptions(cache_mb=budget_mb, memory_mb=budget_mb),
            }
        return SceneOptions(
            select=SelectOptions(max_sse=max_sse),
            anisotropy=anisotropy,
            terrain_mode=terrain_mode,
            meshes=meshes,
            imagery_timeout=imagery_timeout,
            imagery_strict=imagery_strict,
            ellipsoid=ellipsoid,
            morph=morph,
            compress_textures=compress_textures,
            **streaming,
        )
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None


def _landcover(ground: str, landcover: Path | None, city: Path | None) -> Any:
    """The land cover --ground asks for, read from --landcover or else --city; None for tint."""
    if ground == "tint":
        if landcover is not None:
            raise LodscapeError("--landcover needs --ground landcover")
        return None
    if ground != "landcover":
        raise LodscapeError(f"--ground is tint or landcover, got {ground!r}")
    path = landcover or city
    if path is None:
        raise LodscapeError("--ground landcover needs an OSM file: --landcover FILE or --city FILE")
    from lodscape.imagery.landcover import read_landcover

    return read_landcover(path)


def _mode_notice(scene: Scene) -> None:
    """Say on stderr when the GPU terrain mode was asked for and is not there."""
    if scene.terrain_mode_note:
        typer.echo(f"lodscape: notice: {scene.terrain_mode_note}", err=True)


def _write_atomic(path: Path, write: object) -> None:
    """Write through a temporary file in the same folder, renamed into place when complete."""
    path = path.expanduser()
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise LodscapeError(f"{path}: folder {folder} does not exist")
    tmp = temp_beside(path)
    try:
        write(tmp)  # type: ignore[operator]
        os.replace(tmp, path)
    except OSError as exc:
        raise LodscapeError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except (ValueError, KeyError) as exc:
        raise LodscapeError(f"{path}: cannot write this format ({exc})") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}


def _check_outputs(image: Path, depth: Path | None) -> None:
    """Refuse an output the render could not write, before anything is rendered or written:
    a bad type or a missing folder leaves no file of any kind."""
    suffix = image.suffix.lower()
    if suffix not in _IMAGE_SUFFIXES:
        raise LodscapeError(f"{image}: unknown image type {suffix or '(none)'}; use .png or .jpg")
    if depth is not None and depth.suffix.lower() not in {".npy", ".tif", ".tiff"}:
        raise LodscapeError(
            f"{depth}: depth is written as .npy or .tif, not {depth.suffix or '(none)'}"
        )
    _folders_exist(image, depth)


def _folders_exist(*paths: Path | None) -> None:
    """Refuse an output whose folder does not exist."""
    for path in paths:
        if path is None:
            continue
        folder = path.expanduser().parent
        if str(folder) and not folder.is_dir():
            raise LodscapeError(f"{path}: folder {folder} does not exist")


def _save_image(path: Path, rgb: NDArray[np.uint8]) -> None:
    from PIL import Image

    suffix = path.suffix.lower()
    if suffix not in _IMAGE_SUFFIXES:
        raise LodscapeError(f"{path}: unknown image type {suffix or '(none)'}; use .png or .jpg")
    fmt = Image.registered_extensions()[suffix]
    _write_atomic(path, lambda tmp: Image.fromarray(rgb).save(tmp, format=fmt))


def _save_depth(path: Path, depth: NDArray[np.float32]) -> None:
    from PIL import Image

    suffix = path.suffix.lower()
    if suffix == ".npy":

        def write_npy(tmp: Path) -> None:
            with tmp.open("wb") as f:
                np.save(f, depth)

        _write_atomic(path, write_npy)
    elif suffix in {".tif", ".tiff"}:
        _write_atomic(path, lambda tmp: Image.fromarray(depth, mode="F").save(tmp, format="TIFF"))
    else:
        raise LodscapeError(f"{path}: depth is written as .npy or .tif, not {suffix or '(none)'}")


def _print_stats(scene: Scene) -> None:
    if scene.last is None:
        return
    for key, value in scene.last.as_dict().items():
        typer.echo(f"{key:>18}: {value}")


def _render(
    scene: Scene, camera: Camera, output: Path, depth_path: Path | None, quiet: bool
) -> None:
    # the distance is read back only when it is asked for
    rgb, depth = scene.render(camera, depth=depth_path is not None)
    _mode_notice(scene)
    _save_image(output, rgb)
    if depth_path is not None:
        _save_depth(depth_path, depth)
    if not quiet:
        _print_stats(scene)
        typer.echo(f"{'wrote':>18}: {output}")


@app.command()
@_terrain_flags
def render(
    source: Annotated[str, typer.Argument(help="A DEM: GeoTIFF or any GDAL raster, any CRS.")],
    output: OutOpt = Path("view.png"),
    lon: Annotated[
        float | None, typer.Option(callback=_finite, help="Camera longitude, °.")
    ] = None,
    lat: Annotated[float | None, typer.Option(callback=_finite, help="Camera latitude, °.")] = None,
    alt: Annotated[
        float | None,
        typer.Option(
            callback=_finite,
            help="Camera altitude, metres above sea level (the WGS84 ellipsoid: no geoid).",
        ),
    ] = None,
    heading: HeadingOpt = 0.0,
    pitch: Annotated[
        float | None,
        typer.Option(
            callback=_pitch, help="Degrees; negative looks down (default -30; with a position)."
        ),
    ] = None,
    roll: Annotated[
        float | None, typer.Option(callback=_roll, help="Degrees; banks right (with a position).")
    ] = None,
    fov: FovOpt = 60.0,
    size: SizeOpt = "1280x720",
    depth: Annotated[
        Path | None,
        typer.Option(help="Also write depth (metres along the view axis) as .npy or .tif."),
    ] = None,
    camera_file: CameraFileOpt = None,
    globe: Annotated[
        bool,
        typer.Option(
            "--globe",
            help="Render the whole Earth on the QTM grid (SOURCE: a DEM for its heights, or "
            "none); as `lodscape globe`.",
        ),
    ] = False,
    poses: Annotated[
        Path | None,
        typer.Option(
            help="A vision dataset: CSV of camera poses (lon,lat,alt[,heading,pitch,roll,fov,"
            "name]) rendered into --dataset."
        ),
    ] = None,
    dataset: Annotated[
        Path | None,
        typer.Option(
            help="Folder to write the dataset to: RGB, depth, normals, semantic masks, cameras "
            "(OpenCV, COLMAP, NeRF)."
        ),
    ] = None,
    origin: Annotated[
        str | None,
        typer.Option(
            help="LON,LAT[,HEIGHT]: the dataset's local east-north-up origin (default: the "
            "data's centre at height 0, or the poses' centre where the data spans more than "
            "10°, as a server's may)."
        ),
    ] = None,
    depth_invalid: Annotated[
        str,
        typer.Option(
            help="With --dataset: what depth holds where no measured surface is (sky, the "
            "no-data ellipsoid): inf (the default), 0 (Open3D, TUM, ScanNet; nerfstudio masks "
            "depth <= 0) or nan."
        ),
    ] = "inf",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print nothing.")] = False,
    *,
    terrain: TerrainFlags,
) -> None:
    """Render one view of SOURCE (a DEM, a .lods tileset, procedural:seed=N, or flat with
    --city). Without --lon/--lat/--alt, a view of the whole data (or of the city). With
    --poses and --dataset, a vision dataset of many views."""
    w, h = _size(size)
    if poses is not None or dataset is not None or origin is not None:
        given = {
            "--lon": lon,
            "--lat": lat,
            "--alt": alt,
            "--camera": camera_file,
            "--depth": depth,
        }
        _render_dataset(
            source,
            *_dataset_alone(poses, dataset, given, globe),
            origin,
            w,
            h,
            fov,
            quiet,
            terrain,
            depth_invalid,
        )
        return
    _check_outputs(output, depth)
    inputs = {"SOURCE": source, "--camera": camera_file, **terrain.inputs()}
    _outputs_apart({"-o": output, "--depth": depth}, inputs)
    pose = _pose(lon, lat, alt, pitch is not None or roll is not None, camera_file)
    aim = _Aim(camera_file, pose, (heading, _or(pitch, -30.0), _or(roll, 0.0)), w, h, fov)
    if globe:
        _render_globe_view(source, output, depth, quiet, terrain, aim)
        return
    with terrain.open(source, terrain.options()) as scene:
        camera = _scene_camera(scene, aim)
        _render(scene, camera, output, depth, quiet)


def _pose(
    lon: float | None,
    lat: float | None,
    alt: float | None,
    turned: bool,
    camera_file: Path | None,
) -> tuple[float, float, float] | None:
    """--lon/--lat/--alt, all or none (None), apart from --camera; --pitch and --roll
    (``turned``) only with them."""
    if lon is None and lat is None and alt is None and turned:
        raise LodscapeError(
            "--pitch and --roll need --lon/--lat/--alt: without a position the camera is "
            "fitted to the view (or read from --camera)"
        )
    if camera_file is not None and (lon is not None or lat is not None or alt is not None):
        raise LodscapeError("give --camera or --lon/--lat/--alt, not both")
    if lon is None or lat is None or alt is None:
        if lon is not None or lat is not None or alt is not None:
            raise LodscapeError("give all of --lon, --lat and --alt, or none of them")
        return None
    return (lon, lat, alt)


def _dataset_alone(
    poses: Path | None, dataset: Path | None, given: dict[str, Any], globe: bool
) -> tuple[Path, Path]:
    """--poses and --dataset: a dataset's cameras come from --poses alone."""
    if poses is None or dataset is None:
        raise LodscapeError("--poses and --dataset go together (--origin needs both)")
    flags = [flag for flag, v in given.items() if v is not None]
    if flags or globe:
        raise LodscapeError(
            f"a dataset's cameras come from --poses: drop {', '.join(flags) or '--globe'}"
        )
    return poses, dataset


class _Aim(NamedTuple):
    """Where ``render`` looks from: a camera file, or POSE (lon, lat, alt) looking as LOOK
    (heading, pitch, roll) says, or neither (the view is fitted); the picture's size and field
    of view."""

    camera_file: Path | None
    pose: tuple[float, float, float] | None
    look: tuple[float, float, float]
    w: int
    h: int
    fov: float


def _scene_camera(scene: Scene, aim: _Aim) -> Camera:
    """``render``'s camera: from the camera file, at the pose, or the city's or the overview
    (its heading, if given)."""
    camera_file, pose, look, w, h, fov = aim
    if camera_file is not None:
        from lodscape.view import load_camera

        return load_camera(camera_file, w, h)
    if pose is None and scene.city is not None:
        return scene.city_camera(w, h, fov)
    if pose is None:
        camera = scene.overview_camera(w, h, fov)
        return camera.moved(heading=camera.heading if look[0] == 0.0 else look[0])
    heading, pitch, roll = look
    return Camera(*pose, heading=heading, pitch=pitch, roll=roll, fov_y=fov, width=w, height=h)


def _render_globe_view(
    source: str, output: Path, depth: Path | None, quiet: bool, terrain: TerrainFlags, aim: _Aim
) -> None:
    """``render --globe``: the globe over SOURCE from the camera file, the pose or the
    default."""
    camera_file, pose, look, w, h, fov = aim
    from lodscape.globe import GlobeOptions

    try:
        globe_options = GlobeOptions(max_sse=terrain.max_sse)
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None
    full = None if pose is None else (*pose, *look)
    _render_globe(
        source,
        globe_options,
        output,
        depth,
        quiet,
        lambda scene: _globe_camera(scene, camera_file, full, w, h, fov),
        terrain,
    )


def _outputs_apart(outputs: dict[str, Any], inputs: dict[str, Any]) -> None:
    """Refuse an output that is one of the inputs (a route overwritten by its flight's
    statistics), or two outputs that are one file."""

    def same(a: Any, b: Any) -> bool:
        try:
            return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()
        except (OSError, RuntimeError):
            return False

    named = [(flag, p) for flag, p in outputs.items() if p is not None]
    for flag, out in named:
        for what, given in inputs.items():
            for p in given if isinstance(given, list | tuple) else [given]:
                if p is not None and same(out, p):
                    raise LodscapeError(f"{out}: {flag} would overwrite {what}; name another file")
    for i, (flag, out) in enumerate(named):
        for other, out2 in named[i + 1 :]:
            if same(out, out2):
                raise LodscapeError(f"{out}: given to both {flag} and {other}; name two files")


def _or(value: float | None, default: float) -> float:
    return default if value is None else value


def _render_dataset(
    source: str,
    poses_csv: Path,
    out: Path,
    origin_text: str | None,
    w: int,
    h: int,
    fov: float,
    quiet: bool,
    terrain: TerrainFlags,
    depth_invalid: str = "inf",
) -> None:
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from lodscape.dataset import Origin, read_poses, write_dataset

    origin = None
    if origin_text is not None:
        try:
            parts = [float(v) for v in origin_text.split(",")]
        except ValueError:
            parts = []
        if len(parts) not in (2, 3) or not all(math.isfinite(v) for v in parts):
            raise LodscapeError(f"--origin is LON,LAT[,HEIGHT], got {origin_text!r}")
        if not (-180.0 <= parts[0] <= 180.0 and -90.0 <= parts[1] <= 90.0):
            raise LodscapeError(f"--origin {origin_text!r} is not on the Earth")
        origin = Origin(*parts)
    cameras = read_poses(poses_csv, w, h, fov)
    columns = (
        TextColumn("[bold]rendering"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
    )
    with terrain.open(source, terrain.options()) as scene:
        with Progress(*columns, disable=quiet) as bar:
            task = bar.add_task("poses", total=len(cameras))
            used = write_dataset(
                scene,
                cameras,
                out,
                origin,
                progress=lambda done, _total: bar.update(task, completed=done),
                depth_invalid=depth_invalid,
            )
        _mode_notice(scene)
    if not quiet:
        typer.echo(
            f"wrote {out}: {len(cameras)} poses (images, depth, normals, semantic, cameras; "
            f"COLMAP and NeRF) in east-north-up metres from lon {used.lon}, lat {used.lat}, "
            f"height {used.height} m"
        )


@app.command()
@_terrain_flags
def fly(
    source: Annotated[str, typer.Argument(help="A DEM (any GDAL raster) or a .lods tileset.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="The video to write (.mp4).")],
    path: Annotated[
        Path | None,
        typer.Option(help="Route: CSV with lon,lat,alt[,time] columns, or a GeoJSON line."),
    ] = None,
    orbit: Annotated[
        str | None, typer.Option(help="LON,LAT,RADIUS_M,ALT: circle a point, looking at it.")
    ] = None,
    line: Annotated[
        str | None, typer.Option(help="LON1,LAT1,LON2,LAT2,ALT: fly a straight line.")
    ] = None,
    speed: Annotated[float, typer.Option(callback=_finite, help="Metres per second.")] = 100.0,
    fps: Annotated[float, typer.Option(callback=_finite, help="Frames per second.")] = 30.0,
    pitch: Annotated[
        float, typer.Option(callback=_pitch, help="Degrees; negative looks down.")
    ] = -15.0,
    fov: FovOpt = 60.0,
    size: SizeOpt = "1280x720",
    duration: Annotated[
        float | None, typer.Option(callback=_finite, help="Stop after this many seconds.")
    ] = None,
    stats: Annotated[
        Path | None, typer.Option(help="Per-frame statistics to write (.csv).")
    ] = None,
    budget_mb: BudgetOpt = BUDGET_MB,
    globe: Annotated[
        bool,
        typer.Option(
            "--globe",
            help="Fly over the whole Earth on the QTM grid (SOURCE: a DEM for its heights, or "
            "none).",
        ),
    ] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    *,
    terrain: TerrainFlags,
) -> None:
    """Fly a camera over SOURCE along a route, an orbit or a line into an MP4, streaming tiles
    on a simulated clock: the statistics say what a real-time viewer at --fps would have seen."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    from lodscape import flight
    from lodscape.stream import SimClock

    w, h = _size(size)
    if output.suffix.lower() != ".mp4":
        raise LodscapeError(f"{output}: the video is written as .mp4")
    if not 0.0 < fps <= 240.0:
        raise LodscapeError(f"--fps must be within 0..240, got {fps}")
    if duration is not None and not duration > 0.0:
        raise LodscapeError(f"--duration must be a positive number of seconds, got {duration}")
    if not speed > 0.0:
        raise LodscapeError(f"--speed must be a positive number of metres per second, got {speed}")
    _folders_exist(output, stats)
    inputs = {"SOURCE": source, "--path": path, **terrain.inputs()}
    _outputs_apart({"-o": output, "--stats": stats}, inputs)
    route = _route(path, orbit, line, speed)
    options = terrain.options(budget_mb)
    cams = list(flight.cameras(route, fps, w, h, pitch=pitch, fov=fov, duration=duration))
    if globe:
        space = GlobeOptions(max_sse=terrain.max_sse, background=(0.0, 0.0, 0.0))
        subject: Any = _globe(source, space, terrain, options, clock=SimClock())
    else:
        subject = terrain.open(source, options, clock=SimClock())
    columns = (TextColumn("[bold]flying"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with subject, Progress(*columns, disable=quiet) as bar:
        task = bar.add_task("frames", total=len(cams))
        flown = flight.fly(
            subject,
            iter(cams),
            fps,
            video=output,
            stats=stats,
            on_frame=lambda i: bar.update(task, completed=i + 1),
        )
        if not globe:
            _mode_notice(subject)
    if not quiet:
        line = _flight_summary(output, flown, fps)
        if globe:
            line += (
                f"; globe facets per frame up to {max(r['facets'] for r in flown):,}, levels "
                f"to {max(r['max_level'] for r in flown)}"
            )
        typer.echo(line)


def _route(path: Path | None, orbit: str | None, line: str | None, speed: float) -> Any:
    """The flight's route: a file (GeoJSON, CSV, KML, GPX), an orbit or a line."""
    from lodscape import flight

    given = [p for p in (path, orbit, line) if p is not None]
    if len(given) != 1:
        raise LodscapeError("give one of --path, --orbit or --line")
    if path is not None:
        return flight.read_route(path, speed)
    if orbit is not None:
        lon, lat, radius, alt = _numbers(orbit, 4, "--orbit LON,LAT,RADIUS,ALT")
        return flight.orbit_route(lon, lat, radius, alt, speed)
    assert line is not None
    lon1, lat1, lon2, lat2, alt = _numbers(line, 5, "--line LON1,LAT1,LON2,LAT2,ALT")
    return flight.line_route(lon1, lat1, lon2, lat2, alt, speed)


def _flight_summary(output: Path, rows: Sequence[dict[str, float]], fps: float) -> str:
    """One line on a flight: every frame counted, frame 0 (the one that waits for the first
    tiles) named, and the same counts after the first second."""
    after = [r for r in rows if r["time_s"] >= 1.0]

    def counts(rs: Sequence[dict[str, float]]) -> str:
        # a terrain tile drawn from a coarser one, or (the globe) an imagery tile from an
        # ancestor more than one level up
        fell = sum(r["fallback_max"] > 1 or r.get("imagery_fallbacks", 0) > 0 for r in rs)
        over = sum(r["over_budget"] for r in rs)
        return f"{fell} fell back more than one level, {over} went over {1000 / fps:.1f} ms"

    first = rows[0]
    line = (
        f"wrote {output}: {len(rows)} frames; frame 0 took {first['frame_cpu_ms']:.0f} ms "
        f"(stalled {first['stall_ms']:.0f} ms); of all frames {counts(rows)}"
    )
    if after:
        line += f"; after the first second {counts(after)}"
    retries = max(r.get("http_retries", 0) for r in rows)
    if retries:
        line += f"; the imagery server needed {int(retries)} retries"
    return line


def _numbers(text: str, count: int, usage: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise typer.BadParameter(f"expected {usage}, got {text!r}") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise typer.BadParameter(f"expected {usage}, got {text!r}")
    return values


#: ``demo --procedural``'s camera: metres south of the rugged place, above the ground there,
#: and its pitch.
VISTA_BACK = 40_000.0
VISTA_UP = 3_000.0
VISTA_PITCH = -10.0


@app.command()
def demo(
    output: OutOpt = Path("lodscape-demo.png"),
    size: SizeOpt = "1280x720",
    procedural: Annotated[
        bool,
        typer.Option(
            "--procedural", help="The procedural planet (no data at all) instead of the sample."
        ),
    ] = False,
    seed: Annotated[int, typer.Option(help="The procedural planet's seed.")] = 0,
) -> None:
    """Render the embedded sample DEM (Jacksboro Fault, Tennessee) and print the frame's stats;
    with --procedural, a low view over the procedural planet."""
    from lodscape.data import sample_dem_path

    w, h = _size(size)
    if procedural:
        from lodscape.terrain.detail import ProceduralTree, vista

        with open_scene(f"procedural:seed={seed}") as scene:
            tree = scene.provider.tree
            assert isinstance(tree, ProceduralTree)
            # its most rugged land, seen from VISTA_BACK south of it, VISTA_UP above the ground
            lon, peak_lat = vista(tree)
            lat = peak_lat - VISTA_BACK / 111_320.0
            ground = scene.ground_height(lon, lat) or 0.0
            camera = Camera(
                lon, lat, ground + VISTA_UP, heading=0.0, pitch=VISTA_PITCH, width=w, height=h
            )
            _render(scene, camera, output, None, False)
        return
    with open_scene(sample_dem_path()) as scene:
        _render(scene, scene.overview_camera(w, h), output, None, False)


@app.command()
def info(
    source: Annotated[str, typer.Argument(help="A DEM (any GDAL raster) or a .lods tileset.")],
    z_units: ZUnitsOpt = None,
) -> None:
    """Print a source's footprint, resolution, heights and tile levels (and for a tileset, its
    size and provenance)."""
    from lodscape.build.describe import describe

    with open_scene(source, z_units=z_units) as scene:
        for label, text in describe(scene.provider):
            typer.echo(f"{label:>14}: {text}" if label else f"{'':>14}  {text}")


class _TileRate:
    """A build's progress bar: tiles done of planned, the rate since the first report, ETA."""

    def __init__(self, quiet: bool) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.bar = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[rate]} tiles/s"),
            TimeElapsedColumn(),
            TextColumn("ETA"),
            TimeRemainingColumn(),
            disable=quiet,
            transient=False,
        )
        self.start: tuple[float, int] | None = None

    def __enter__(self) -> _TileRate:
        self.bar.__enter__()
        self.task = self.bar.add_task("building", total=None, rate="-")
        return self

    def __call__(self, done: int, total: int) -> None:
        import time

        now = time.monotonic()
        if self.start is None:
            self.start = (now, done)
        rate = (done - self.start[1]) / max(now - self.start[0], 1e-9)
        self.bar.update(self.task, completed=done, total=total, rate=f"{rate:.1f}")

    def __exit__(self, *exc: object) -> None:
        self.bar.__exit__(None, None, None)


@app.command()
def build(
    inputs: Annotated[
        list[str],
        typer.Argument(help="Rasters (any GDAL format, any CRS) and/or point files (.csv .xyz)."),
    ],
    output: Annotated[Path, typer.Option("-o", "--output", help="The tileset to write (.lods).")],
    crs: Annotated[
        str | None, typer.Option(help="CRS of point files, e.g. EPSG:32617 or EPSG:4326.")
    ] = None,
    resolution: Annotated[
        float | None,
        typer.Option(callback=_finite, help="Grid spacing for points, in their CRS's units."),
    ] = None,
    error_texels: Annotated[
        float,
        typer.Option(callback=_finite, help="Mesh error budget per level, in its texels."),
    ] = 1.0,
    workers: Annotated[
        int | None, typer.Option(help="Build in this many processes (default: threads).")
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(help="Dask scheduler address (tcp://host:8786), or 'local' for a cluster."),
    ] = None,
    allow_mixed_crs: Annotated[
        bool, typer.Option(help="Mosaic rasters in different CRSs, reprojecting each.")
    ] = False,
    imagery: Annotated[
        list[str] | None,
        typer.Option(
            help="Imagery to bake over the terrain's tint at its own levels (repeatable, bottom "
            "to top): a georeferenced raster (an orthophoto), an .mbtiles file or a folder."
        ),
    ] = None,
    fill: Annotated[
        str,
        typer.Option(
            "--fill",
            help="What the tiles hold where the data has none: interpolate (the default: voids "
            "inside the data filled smoothly from their rims, as gdal_fillnodata does; height 0 "
            "outside it, the globe a Cesium client expects), ellipsoid (height 0 everywhere), "
            "none (holes: no triangles), nearest or value:H. Kept in the tileset's metadata.",
        ),
    ] = "interpolate",
    sea_level: SeaLevelOpt = "0",
    band: BandOpt = None,
    nodata: NodataOpt = None,
    z_units: ZUnitsOpt = None,
    mesher: Annotated[
        str,
        typer.Option(
            help="How tiles are meshed: rtin (halves of halves) or greedy (Delaunay "
            "refinement: fewer triangles for the same error, slower to build)."
        ),
    ] = "rtin",
    attribution: Annotated[
        str | None,
        typer.Option(
            help="Who to credit (e.g. '© State Survey 2024'), written into the tileset's "
            "TileJSON, layer.json and MBTiles metadata; default: what the inputs' metadata "
            "states, else their names."
        ),
    ] = None,
    shards: Annotated[
        str | None,
        typer.Option(
            help="The folder the workers write their blocks to before they are merged into "
            "OUTPUT (default: OUTPUT.shards beside it). On a cluster, a folder every worker and "
            "this machine reach (a shared disk). Removed when the build has finished.",
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Build a tileset from INPUTS once, to render, fly or serve it anywhere. Run it again after
    an interruption: it finishes without redoing what is done."""
    from lodscape.build import BuildOptions, executor_for
    from lodscape.build import build as build_tileset

    try:
        options = BuildOptions(
            error_texels=error_texels,
            crs=crs,
            resolution=resolution,
            allow_mixed_crs=allow_mixed_crs,
            imagery=tuple(imagery or ()),
            fill=fill,
            sea_level=_sea_level(sea_level),
            band=band,
            nodata=nodata,
            mesher=mesher,
            z_units=z_units,
            attribution=attribution,
        )
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None
    executor = executor_for(workers, scheduler)
    try:
        with _TileRate(quiet) as progress:
            report = build_tileset(
                inputs, output, options, executor=executor, progress=progress, shards=shards
            )
    finally:
        executor.close()
    if not quiet:
        what = "finished" if report.resumed else "built"
        typer.echo(
            f"{what} {output}: {report.planned} tiles ({report.built} made now) in "
            f"{report.seconds:.1f} s on {report.executor}; levels {report.levels[0]}.."
            f"{report.levels[2]}, textures to {report.levels[1]}"
            + (f", imagery to {report.imagery_zmax}" if report.imagery_zmax else "")
        )


TilingOpt = Annotated[
    str,
    typer.Option(
        help="The Cesium terrain's tiling: geographic (EPSG:4326, two level-0 tiles, to the "
        "poles) or mercator (EPSG:3857, the stored tiles, which stop at ±85.05°).",
    ),
]


@app.command()
def export(
    tileset: Annotated[str, typer.Argument(help="A .lods tileset.")],
    cesium: Annotated[
        Path | None, typer.Option("--cesium", help="Folder to write a Cesium terrain layer into.")
    ] = None,
    pmtiles: Annotated[
        Path | None,
        typer.Option("--pmtiles", help="PMTiles v3 archive to write the imagery into."),
    ] = None,
    terrarium: Annotated[
        Path | None,
        typer.Option(
            "--terrarium",
            help="PMTiles v3 archive to write the terrain into, as Terrarium PNG tiles.",
        ),
    ] = None,
    base_url: Annotated[
        str | None,
        typer.Option(
            help="The URL the --cesium folder will be served from (https://host/path), so its "
            "imagery.json names its tiles absolutely (MapLibre resolves a relative one against "
            "the page, not the TileJSON)."
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(help="Write the --cesium folder's tiles in this many processes."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Write the --cesium folder's tiles on a Dask cluster (tcp://host:8786, or "
            "'local'): its workers must reach the folder."
        ),
    ] = None,
    tiling: TilingOpt = "geographic",
) -> None:
    """Write a tileset as files clients stream: with --cesium a folder (layer.json,
    {z}/{x}/{y}.terrain, the imagery as imagery/{z}/{x}/{y}.png with its TileJSON, a stored
    city's buildings as 3D Tiles); with --pmtiles its imagery, with --terrarium its terrain
    (Terrarium-encoded), each one PMTiles v3 archive."""
    if cesium is None and pmtiles is None and terrarium is None:
        raise LodscapeError("export: give --cesium FOLDER, --pmtiles FILE or --terrarium FILE")
    if cesium is not None:
        from lodscape.store.export import export_cesium

        executor = None
        if workers is not None or scheduler is not None:
            from lodscape.build import executor_for

            executor = executor_for(workers, scheduler)
        try:
            n = export_cesium(
                tileset,
                cesium,
                executor,
                base_url=_absolute_url(base_url, "--base-url"),
                tiling=tiling,
            )
        finally:
            if executor is not None:
                executor.close()
        city = " and 3dtiles/" if (cesium / "3dtiles").exists() else ""
        typer.echo(f"wrote {n} terrain tiles, layer.json, imagery.json{city} to {cesium}")
    if pmtiles is not None or terrarium is not None:
        from lodscape.store.pmtiles import export_pmtiles

        got = export_pmtiles(tileset, pmtiles, terrarium)
        for what, path in (("imagery", pmtiles), ("terrain", terrarium)):
            if path is not None:
                typer.echo(f"wrote {got[what]} {what} tiles to {path}")


@app.command()
@_terrain_flags
def view(
    source: Annotated[
        str, typer.Argument(help="A DEM, a .lods tileset, procedural:seed=N, or flat with --city.")
    ],
    camera_file: CameraFileOpt = None,
    save_camera: Annotated[
        Path | None,
        typer.Option("--camera-file", help="Where the K key saves the camera (JSON)."),
    ] = None,
    screenshots: Annotated[
        Path, typer.Option(help="Folder the P key writes screenshots into.")
    ] = Path("."),
    size: SizeOpt = "1280x720",
    fov: FovOpt = 60.0,
    budget_mb: BudgetOpt = BUDGET_MB,
    exit_after: Annotated[
        float | None,
        typer.Option(callback=_finite, help="Close the window after this many seconds."),
    ] = None,
    globe: Annotated[
        bool,
        typer.Option(
            "--globe",
            help="The whole Earth on the QTM grid, with SOURCE's heights where it covers.",
        ),
    ] = False,
    *,
    terrain: TerrainFlags,
) -> None:
    """Fly over SOURCE in a window: W/S/A/D/Q/E move, arrows and mouse drag look, the wheel
    sets the speed; T wireframe, L level colours, C back-face culling, G fractal detail, P
    screenshot, K save the camera (--camera-file), Esc quits. Tiles stream as you fly."""
    from lodscape.view import view as run_view

    w, h = _size(size)
    if globe:
        _view_globe(
            source, camera_file, save_camera, screenshots, w, h, fov, terrain, budget_mb, exit_after
        )
        return
    fractal = terrain.fractal(source)
    options = terrain.options(budget_mb)
    opened = terrain.open(source, options)
    try:
        if camera_file is not None:
            from lodscape.view import load_camera

            camera = load_camera(camera_file, w, h)
        else:
            camera = opened.default_camera(w, h, fov)
        lattice = parse_source(source).has_lattice

        def other(with_detail: bool) -> Scene:
            return terrain.open(
                source, options, detail=(fractal or Fractal()) if with_detail else None
            )

        # the G key's other scene, made when first asked for
        scenes: dict[str, Any] = {"detail" if fractal is not None else "plain": opened}
        if fractal is not None:
            scenes["plain"] = lambda: other(False)
        elif lattice and terrain.ground == "tint":
            scenes["detail"] = lambda: other(True)
    except BaseException:
        opened.close()
        raise
    done = run_view(
        scenes,
        camera,
        start="detail" if fractal is not None else "plain",
        screenshot_dir=screenshots,
        camera_file=save_camera,
        exit_after=exit_after,
        title=f"lodscape: {source}",
    )
    c = done["camera"]
    typer.echo(
        f"{done['frames']} frames, {done['screenshots']} screenshots; camera "
        f"{c.lon:.6f} {c.lat:.6f} {c.alt:.1f} heading {c.heading:.1f} pitch {c.pitch:.1f}"
    )


@app.command()
def serve(
    tileset: Annotated[Path, typer.Argument(help="A .lods tileset (built by lodscape build).")],
    port: Annotated[int, typer.Option(help="TCP port.")] = 8000,
    host: Annotated[
        str, typer.Option(help="Address to listen on (0.0.0.0: every interface).")
    ] = "127.0.0.1",
    public_url: Annotated[
        str | None,
        typer.Option(
            help="The URL clients reach this server by (https://tiles.example.org), for the "
            "URLs it writes into its TileJSON; without it, a reverse proxy's "
            "X-Forwarded-Proto and X-Forwarded-Host, else the request's own."
        ),
    ] = None,
    viewer_js: Annotated[
        str | None,
        typer.Option(
            help="Where the page at / loads CesiumJS from: a URL ending in Build/Cesium/, or a "
            "local folder of it (node_modules/cesium/Build/Cesium), served under /viewer-js/ "
            "(default: the npm package on jsDelivr)."
        ),
    ] = None,
    tiling: TilingOpt = "geographic",
    maplibre_js: Annotated[
        str | None,
        typer.Option(
            help="Where the page at /maplibre loads MapLibre GL JS from: a URL ending in dist/, "
            "or a local folder of it (node_modules/maplibre-gl/dist), served under "
            "/maplibre-js/ (default: the npm package on jsDelivr)."
        ),
    ] = None,
) -> None:
    """Serve a tileset over HTTP: a viewer page at / (CesiumJS) and at /maplibre (MapLibre),
    /layer.json and /{z}/{x}/{y}.terrain (quantized-mesh, for Cesium), /imagery/{z}/{x}/{y}.png
    with /imagery.json, /terrarium/{z}/{x}/{y}.png with /terrarium.json (Terrarium heights, for
    MapLibre and deck.gl), and the stored cities as 3D Tiles under /3dtiles/tileset.json;
    /index.json lists them. CORS, ETag, gzip. Ctrl-C stops it."""
    from lodscape.serve import run

    if not 0 < port < 65536:
        raise LodscapeError(f"--port must be within 1..65535, got {port}")
    run(
        tileset,
        host,
        port,
        ready=lambda url: typer.echo(f"serving {tileset} on {url} (Ctrl-C stops)"),
        public_url=_absolute_url(public_url, "--public-url"),
        viewer_js=viewer_js,
        tiling=tiling,
        maplibre_js=maplibre_js,
    )


def _absolute_url(url: str | None, flag: str) -> str | None:
    """An http(s) URL with a host, without its trailing slash; a one-line error otherwise."""
    if url is None:
        return None
    from urllib.parse import urlsplit

    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        raise LodscapeError(f"{flag} {url!r}: give an absolute http(s) URL, e.g. https://host/path")
    return url.rstrip("/")


@app.command()
def globe(
    source: Annotated[
        str | None,
        typer.Argument(help="A DEM whose heights the globe takes where it covers (optional)."),
    ] = None,
    lon: Annotated[float, typer.Option(callback=_finite, help="Camera longitude, °.")] = 0.0,
    lat: Annotated[float, typer.Option(callback=_finite, help="Camera latitude, °.")] = 20.0,
    alt: Annotated[
        float,
        typer.Option(
            callback=_finite,
            help="Camera altitude, metres above sea level (the WGS84 ellipsoid: no geoid).",
        ),
    ] = 2.0e7,
    heading: HeadingOpt = 0.0,
    pitch: Annotated[
        float, typer.Option(callback=_pitch, help="Degrees; negative looks down.")
    ] = -90.0,
    fov: FovOpt = 45.0,
    size: SizeOpt = "1024x768",
    output: OutOpt = Path("globe.png"),
    mode: Annotated[
        str,
        typer.Option(
            help="sse: refined by screen-space error; thinning: the paper's base level with a "
            "thinning area around the viewpoint."
        ),
    ] = "sse",
    max_sse: SseOpt = 2.0,
    base: Annotated[int, typer.Option(help="thinning: the base level.")] = 7,
    extra: Annotated[int, typer.Option(help="thinning: levels added in the thinning area.")] = 2,
    blocks: Annotated[int, typer.Option(help="thinning: blocks in the thinning area.")] = 4,
    block_level: Annotated[int, typer.Option(help="thinning: the blocks' QTM level.")] = 4,
    terrain_tiles: Annotated[
        bool,
        typer.Option(
            help="Draw SOURCE's own terrain tiles where it has data (its meshes and imagery "
            "at their own resolution); --no-terrain-tiles: the globe's facets take its "
            "heights and drape its imagery instead."
        ),
    ] = True,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print nothing.")] = False,
) -> None:
    """Render the whole Earth on the octahedral QTM grid (paper 002), from orbit down to a few
    hundred metres: SOURCE's own terrain tiles where it covers, the Earth elsewhere."""
    from lodscape.globe import GlobeOptions

    w, h = _size(size)
    _check_outputs(output, None)
    try:
        options = GlobeOptions(
            mode=mode,
            max_sse=max_sse,
            base=base,
            extra=extra,
            blocks=blocks,
            block_level=block_level,
            terrain_tiles=terrain_tiles,
        )
        camera = Camera(lon, lat, alt, heading=heading, pitch=pitch, fov_y=fov, width=w, height=h)
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None
    if not 1 <= block_level <= base <= 12 or not 0 <= extra <= 6:
        raise LodscapeError("thinning needs 1 <= --block-level <= --base <= 12, 0 <= --extra <= 6")
    _render_globe(source, options, output, None, quiet, lambda _: camera)


def _globe(
    source: str | None,
    options: Any,
    flags: TerrainFlags | None = None,
    scene_options: SceneOptions | None = None,
    *,
    clock: Clock | None = None,
) -> Any:
    """The QTM globe over SOURCE (None, "-" or "none": the ellipsoid alone), for ``globe`` and
    every command's --globe: ``lodscape.open`` with the terrain FLAGS and ``globe=``. With
    ``clock``, frames stream on it (flights, the viewer)."""
    flags = flags or TerrainFlags()
    none = source is None or parse_source(source).kind == "none"
    if none:
        if flags.city is not None:
            raise LodscapeError("--city on the globe needs SOURCE (a DEM, a tileset, or flat)")
        if flags.ground != "tint" or flags.landcover is not None or flags.detail != "none":
            raise LodscapeError(
                "--ground, --landcover and --detail colour a terrain: give SOURCE (a DEM or a "
                "tileset) for the globe to draw them on"
            )
    opts = scene_options or flags.options(256.0 if none else None)
    text = "none" if none or source is None else source
    kwargs = flags.open_kwargs(text, None if none else True)
    return open_scene(text, opts, clock=clock, globe=options, **kwargs)


def _globe_camera(
    terrain: Scene | None,
    camera_file: Path | None,
    pose: tuple[float, ...] | None,
    w: int,
    h: int,
    fov: float,
) -> Camera:
    """The camera of ``render --globe`` and ``view --globe``: from the camera file, from
    --lon/--lat/--alt (POSE: lon, lat, alt, heading, pitch, roll), over the DEM, or the Earth
    from orbit."""
    if camera_file is not None:
        from lodscape.view import load_camera

        return load_camera(camera_file, w, h)
    if pose is not None:
        lon, lat, alt, heading, pitch, roll = pose
        try:
            return Camera(
                lon, lat, alt, heading=heading, pitch=pitch, roll=roll, fov_y=fov, width=w, height=h
            )
        except ValueError as exc:
            raise LodscapeError(f"bad camera: {exc}") from None
    if terrain is not None:
        c = terrain.overview_camera(w, h, fov)
        return c.moved(alt=max(c.alt, 5.0e4))
    return Camera(10.0, 30.0, 2.0e7, pitch=-90.0, fov_y=fov, width=w, height=h)


def _render_globe(
    source: str | None,
    options: Any,
    output: Path,
    depth_path: Path | None,
    quiet: bool,
    camera: Callable[[Scene | None], Camera],
    flags: TerrainFlags | None = None,
) -> None:
    """One view of the QTM globe (``globe``, ``render --globe``): heights from SOURCE (None,
    "-" or "none": the ellipsoid), the camera made from the terrain opened."""

    g = _globe(source, options, flags)
    terrain = g.terrain
    try:
        rgb, dist = g.render(camera(terrain))
        _save_image(output, rgb)
        if depth_path is not None:
            _save_depth(depth_path, dist)
    finally:
        g.close()
    if not quiet:
        for key, value in g.last.items():
            typer.echo(f"{key:>18}: {value}")
        typer.echo(f"{'wrote':>18}: {output}")


def _view_globe(
    source: str,
    camera_file: Path | None,
    save_camera: Path | None,
    screenshots: Path,
    w: int,
    h: int,
    fov: float,
    flags: TerrainFlags,
    budget_mb: float,
    exit_after: float | None,
) -> None:
    """``view --globe``: the QTM globe in the window (SOURCE "-" or "none": no heights), its
    tiles and imagery streaming as you fly."""
    from lodscape.globe import GlobeOptions
    from lodscape.stream import RealClock
    from lodscape.view import view as run_view

    try:
        options = GlobeOptions(max_sse=flags.max_sse, background=(0.0, 0.0, 0.0))
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None
    g = _globe(source, options, flags, flags.options(budget_mb), clock=RealClock())
    camera = _globe_camera(g.terrain, camera_file, None, w, h, fov)
    done = run_view(
        {"plain": g},
        camera,
        screenshot_dir=screenshots,
        camera_file=save_camera,
        exit_after=exit_after,
        title="lodscape: globe",
    )
    c = done["camera"]
    typer.echo(
        f"{done['frames']} frames, {done['screenshots']} screenshots; camera "
        f"{c.lon:.6f} {c.lat:.6f} {c.alt:.1f} heading {c.heading:.1f} pitch {c.pitch:.1f}"
    )


city_app = typer.Typer(
    help="Cities stored in a tileset: add an OpenStreetMap file, list, remove.",
    no_args_is_help=True,
)
app.add_typer(city_app, name="city")


@city_app.command("add")
def city_add(
    tileset: Annotated[Path, typer.Argument(help="A .lods tileset (built by lodscape build).")],
    osm: Annotated[Path, typer.Argument(help="An OpenStreetMap file (.osm.pbf, .osm).")],
    name: Annotated[
        str | None, typer.Option(help="The city's name in the tileset (default: the file's).")
    ] = None,
    replace: Annotated[
        bool, typer.Option("--replace", help="Replace a stored city of the same name.")
    ] = False,
) -> None:
    """Store the buildings, trees, lamps and benches of an OSM file in a tileset (one
    transaction); render, fly and view then drape them on its terrain."""
    from lodscape.city.osm import read_osm
    from lodscape.store.city import add_city
    from lodscape.store.city_tiles import store_city_tiles
    from lodscape.store.tileset import TilesetProvider, lonlat_bounds

    provider = TilesetProvider(tileset)
    made: list[int] = []
    try:
        box = lonlat_bounds(provider.bounds_merc)
        town = read_osm(osm)
        got = add_city(
            tileset,
            town,
            name=name,
            replace=replace,
            bounds=box,
            # its 3D Tiles (for serve and export) made and stored in the same transaction
            then=lambda db: made.append(store_city_tiles(db, provider)),
        )
    finally:
        provider.close()
    rep = town.report()
    typer.echo(
        f"stored {name or osm.name} in {tileset}: {got['buildings']:,} buildings, "
        f"{got['features']:,} street objects ({got['outside']:,} outside the tileset left out; "
        f"{rep['repaired']} footprints repaired, {sum(town.skipped.values())} skipped); "
        f"3D Tiles: {made[0] if made else 0} contents"
    )


@city_app.command("list")
def city_list(
    tileset: Annotated[Path, typer.Argument(help="A .lods tileset.")],
) -> None:
    """The cities a tileset stores."""
    from lodscape.store.tileset import TilesetProvider

    provider = TilesetProvider(tileset)
    try:
        rows = provider.cities()
    finally:
        provider.close()
    if not rows:
        typer.echo(f"{tileset}: no city stored")
    for r in rows:
        typer.echo(
            f"{r['name']}: {r['buildings']:,} buildings, {r['features']:,} street objects "
            f"(from {r['source']})"
        )


@city_app.command("remove")
def city_remove(
    tileset: Annotated[Path, typer.Argument(help="A .lods tileset.")],
    name: Annotated[str, typer.Argument(help="The stored city's name (see lodscape city list).")],
) -> None:
    """Remove a stored city (one transaction)."""
    from lodscape.store.city import remove_city
    from lodscape.store.city_tiles import store_city_tiles
    from lodscape.store.tileset import TilesetProvider

    provider = TilesetProvider(tileset)
    try:
        remove_city(tileset, name, then=lambda db: store_city_tiles(db, provider))
    finally:
        provider.close()
    typer.echo(f"removed {name} from {tileset}")


def _usage_errors() -> tuple[type[Exception], ...]:
    """Click's usage errors: typer ≥ 0.29 vendors click as ``typer._click``, older typer uses it."""
    found: list[type[Exception]] = []
    with contextlib.suppress(ImportError):
        from typer._click.exceptions import ClickException as Vendored

        found.append(Vendored)
    with contextlib.suppress(ImportError):
        from click.exceptions import ClickException

        found.append(ClickException)
    return tuple(found)


_USAGE_ERRORS = _usage_errors()


def _quiet_gdal() -> None:
    """GDAL's own messages (rasterio hands them to Python's logging, whose last-resort handler
    prints them as "ERROR 4: …" lines) stay out of the terminal: lodscape turns the failures
    that matter into its own one-line errors, naming the input."""
    import logging

    # GDAL's default handler prints what reaches it outside rasterio's own (a VRT's missing
    # source, read on a worker thread: "ERROR 4: …" twice); CPL_LOG sends those to nothing
    os.environ.setdefault("CPL_LOG", os.devnull)
    for name in ("rasterio", "fiona", "pyogrio"):
        log = logging.getLogger(name)
        if not log.handlers:
            log.addHandler(logging.NullHandler())
        log.propagate = False


def _command() -> Any:
    """The click command of ``app``, its help's type column written for people: nothing for a
    flag (typer writes ``<bool>``), ``<text>`` for an option given several times (typer writes
    ``<list[str]>``; each option's help says it repeats)."""
    root = typer.main.get_command(app)
    commands = getattr(root, "commands", {})
    for cmd in [
        root,
        *commands.values(),
        *(sub for c in commands.values() for sub in getattr(c, "commands", {}).values()),
    ]:
        helper = cmd.get_help_option(typer.Context(cmd))  # made once, kept by the command
        for p in [*cmd.params, *([helper] if helper is not None else [])]:
            if getattr(p, "param_type_name", "") == "option" and p.metavar is None:
                if getattr(p, "is_flag", False):
                    p.metavar = ""
                elif getattr(p, "multiple", False):
                    p.metavar = "<text>"
    return root


def main(argv: list[str] | None = None) -> None:
    """Console entry point: one-line errors, exit status 2 on bad input."""
    _quiet_gdal()
    try:
        rv = _command()(args=argv, standalone_mode=False, prog_name="lodscape")
    except (typer.Abort, KeyboardInterrupt):
        print("lodscape: aborted", file=sys.stderr)
        sys.exit(130)
    except _USAGE_ERRORS as exc:
        print(f"lodscape: error: {exc.format_message()}", file=sys.stderr)  # type: ignore[attr-defined]
        sys.exit(2)
    except LodscapeError as exc:
        print(f"lodscape: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except OSError as exc:
        name = f"{exc.filename}: " if exc.filename else ""
        print(f"lodscape: error: {name}{exc.strerror or exc}", file=sys.stderr)
        sys.exit(2)
    if isinstance(rv, int) and rv:
        sys.exit(rv)


if __name__ == "__main__":
    main()
