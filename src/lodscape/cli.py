"""The ``lodscape`` command: a thin map from flags onto the Python API (mercantile ``scripts/``).

Bad input ends with one line on stderr naming the problem, exit status 2, and no output file:
outputs are written to a temporary name beside the target and renamed only when complete.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from numpy.typing import NDArray

from lodscape.errors import LodscapeError
from lodscape.lod.camera import Camera
from lodscape.lod.select import SelectOptions
from lodscape.scene import Scene, SceneOptions
from lodscape.scene import open as open_scene

app = typer.Typer(
    name="lodscape",
    help="Render huge 3D landscapes with per-tile level of detail.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


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


SizeOpt = Annotated[str, typer.Option("--size", help="Viewport WIDTHxHEIGHT in pixels.")]
OutOpt = Annotated[Path, typer.Option("-o", "--output", help="Image to write (.png, .jpg, .tif).")]
SseOpt = Annotated[float, typer.Option("--max-sse", help="Screen-space error bound, pixels.")]


def _scene_options(*, max_sse: float, anisotropy: float) -> SceneOptions:
    """Scene options from flags; a value the engine refuses is a one-line usage error."""
    try:
        return SceneOptions(select=SelectOptions(max_sse=max_sse), anisotropy=anisotropy)
    except ValueError as exc:
        raise LodscapeError(f"bad option: {exc}") from None


def _write_atomic(path: Path, write: object) -> None:
    """Write through a temporary file in the same folder, renamed into place when complete."""
    path = path.expanduser()
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise LodscapeError(f"{path}: folder {folder} does not exist")
    tmp = folder / f".{path.name}.{os.getpid()}.tmp"
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


def _save_image(path: Path, rgb: NDArray[np.uint8]) -> None:
    from PIL import Image

    suffix = path.suffix.lower()
    if suffix not in {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp"}:
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
    rgb, depth = scene.render(camera)
    _save_image(output, rgb)
    if depth_path is not None:
        _save_depth(depth_path, depth)
    if not quiet:
        _print_stats(scene)
        typer.echo(f"{'wrote':>18}: {output}")


@app.command()
def render(
    source: Annotated[str, typer.Argument(help="A DEM: GeoTIFF or any GDAL raster, any CRS.")],
    output: OutOpt = Path("view.png"),
    lon: Annotated[
        float | None, typer.Option(callback=_finite, help="Camera longitude, °.")
    ] = None,
    lat: Annotated[float | None, typer.Option(callback=_finite, help="Camera latitude, °.")] = None,
    alt: Annotated[
        float | None,
        typer.Option(callback=_finite, help="Camera altitude, metres above sea level."),
    ] = None,
    heading: Annotated[
        float, typer.Option(callback=_finite, help="Degrees clockwise from north.")
    ] = 0.0,
    pitch: Annotated[
        float, typer.Option(callback=_finite, help="Degrees; negative looks down.")
    ] = -30.0,
    roll: Annotated[float, typer.Option(callback=_finite, help="Degrees; banks right.")] = 0.0,
    fov: Annotated[float, typer.Option(callback=_finite, help="Vertical field of view, °.")] = 60.0,
    size: SizeOpt = "1280x720",
    depth: Annotated[
        Path | None,
        typer.Option(help="Also write depth (metres along the view axis) as .npy or .tif."),
    ] = None,
    max_sse: SseOpt = 2.0,
    anisotropy: Annotated[
        float,
        typer.Option(callback=_finite, help="Anisotropic filtering cap; 1 is faster on llvmpipe."),
    ] = 16.0,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="Print nothing.")] = False,
) -> None:
    """Render one view of SOURCE. Without --lon/--lat/--alt, a view of the whole data."""
    w, h = _size(size)
    options = _scene_options(max_sse=max_sse, anisotropy=anisotropy)
    with open_scene(source, options) as scene:
        if lon is None and lat is None and alt is None:
            camera = scene.overview_camera(w, h, fov)
            camera = camera.moved(heading=camera.heading if heading == 0.0 else heading)
        else:
            if lon is None or lat is None or alt is None:
                raise LodscapeError("give all of --lon, --lat and --alt, or none of them")
            camera = Camera(
                lon, lat, alt, heading=heading, pitch=pitch, roll=roll, fov_y=fov, width=w, height=h
            )
        _render(scene, camera, output, depth, quiet)


@app.command()
def demo(
    output: OutOpt = Path("lodscape-demo.png"),
    size: SizeOpt = "1280x720",
) -> None:
    """Render the embedded sample DEM (Jacksboro Fault, Tennessee) and print the frame's stats."""
    from lodscape.data import sample_dem_path

    w, h = _size(size)
    with open_scene(sample_dem_path()) as scene:
        _render(scene, scene.overview_camera(w, h), output, None, False)


@app.command()
def info(source: Annotated[str, typer.Argument(help="A DEM: any GDAL raster.")]) -> None:
    """Print a source's footprint, resolution, height range and tile levels."""
    with open_scene(source) as scene:
        tree = scene.tree
        src = scene.source
        b = src.bounds_merc
        typer.echo(f"{'source':>14}: {src.name}")
        typer.echo(f"{'bounds 3857':>14}: {b.left:.1f} {b.bottom:.1f} {b.right:.1f} {b.top:.1f}")
        typer.echo(f"{'resolution':>14}: {src.resolution_merc:.3f} m (Web Mercator)")
        lo, hi = tree.height_range
        typer.echo(f"{'heights':>14}: {lo:.1f} .. {hi:.1f} m")
        typer.echo(
            f"{'levels':>14}: {tree.zmin} .. {tree.zmax}"
            + (f" (coarsened by {tree.coarsened})" if tree.coarsened else "")
        )
        for lv in tree.levels:
            typer.echo(
                f"{'z' + str(lv.z):>14}: {int(lv.exists.sum())} tiles, "
                f"max error {float(lv.error[0].max()):.2f} m at 16 segments"
            )


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


def main(argv: list[str] | None = None) -> None:
    """Console entry point: one-line errors, exit status 2 on bad input."""
    try:
        rv = app(args=argv, standalone_mode=False, prog_name="lodscape")
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
