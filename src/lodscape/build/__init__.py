"""Build a tileset once (rasters or scattered points in, one SQLite file out), to stream anywhere.

    report = lodscape.build.build(["dem.tif"], "site.lods")

The coordinator plans the tree a row of blocks at a time (``build.blocks``: the tiles under one
root over four levels), finest band first, and hands each block to an executor (threads,
processes or Dask). A block's finest tiles are read from the data, every coarser tile is made
from its four children, so no task reads more than its finest tiles' pixels. Workers write
their blocks to shards; the coordinator merges each finished shard into the file in one
transaction, so a build killed at any moment, coordinator or worker, resumes where it stopped.
Which executor ran a build never changes its tiles.
"""

from __future__ import annotations

import itertools
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from lodscape.build.blocks import (
    Band,
    Block,
    bands,
    clear_shards,
    make_block,
    plan_blocks,
    shard_path,
)
from lodscape.build.executors import BuildExecutor, executor_for
from lodscape.build.tiles import Job
from lodscape.errors import SourceError
from lodscape.geo.tiles import MAX_ZOOM, ORIGIN, Bbox
from lodscape.imagery.layers import warn_stderr
from lodscape.store.tileset import (
    SCHEMA_VERSION,
    TilesetWriter,
    lonlat_bounds,
)
from lodscape.terrain.greedy import MESHERS
from lodscape.terrain.paths import absolute
from lodscape.terrain.paths import provenance as provenance_of
from lodscape.terrain.points import POINT_SUFFIXES, grid_points, read_points, write_grid
from lodscape.terrain.pyramid import LevelSpan, level_span
from lodscape.terrain.rtin import Rtin
from lodscape.terrain.source import (
    FilledSource,
    HeightSource,
    open_rasters,
    parse_fill,
    parse_z_units,
    pixel_share,
    raster_notes,
    rasters_of,
    sea_note,
)

__all__ = ["BuildOptions", "BuildReport", "build", "executor_for"]

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class BuildOptions:
    """How a tileset is built; the defaults are the documented behaviour."""

    #: Each tile's mesh keeps within this many of its level's texels (ground size) of the
    #: sampled heights; its real error against the data is measured and recorded per tile.
    error_texels: float = 1.0
    #: Texels per imagery tile side.
    tile_size: int = 256
    #: CRS of point inputs (CSV or XYZ), e.g. "EPSG:32617"; rasters carry their own.
    crs: str | None = None
    #: Grid spacing (in the points' CRS units) to resample points to; None: their own spacing.
    resolution: float | None = None
    #: Mosaic rasters in different CRSs (each reprojected) instead of refusing them.
    allow_mixed_crs: bool = False
    #: Finished tiles written per transaction.
    batch: int = 16
    #: Imagery layers baked over the terrain's tint, bottom to top: local orthophotos (any
    #: GDAL raster), MBTiles files or folders of z/x/y tiles. The tileset's imagery then goes
    #: down to the finest layer's own level, below the terrain's if it is finer.
    imagery: tuple[str, ...] = ()
    #: What stands where the data has none (kept in the tileset's metadata): ``interpolate``
    #: (voids inside the data filled smoothly from their rims; height 0 outside it, the globe
    #: a Cesium client expects around the data), ``ellipsoid`` (height 0 everywhere), ``none``
    #: (holes: no triangles there), ``nearest`` or ``value:H``.
    fill: str = "interpolate"
    #: Heights below it are tinted as water (None: no sea).
    sea_level: float | None = 0.0
    #: The rasters' height band (None: their only one) and a nodata value they do not declare.
    band: int | None = None
    nodata: float | None = None
    #: How each tile's surface is meshed within its budget: "rtin" (right-triangulated
    #: irregular networks, halves of halves of the tile) or "greedy" (Delaunay refinement,
    #: points where the error is: fewer triangles for the same measured error).
    mesher: str = "rtin"
    #: The rasters' height unit: ``m``, ``ft``, ``us-ft`` or metres per unit (None: what the
    #: files say: the band's unit, a vertical CRS, else a projected CRS's unit).
    z_units: str | None = None
    #: Who to credit, shown by clients (TileJSON, layer.json, MBTiles); None: what the inputs
    #: state (their attribution or copyright metadata), else their names. Not part of what a
    #: resumed build must match: it can be changed by building again.
    attribution: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "fill", str(parse_fill(self.fill)))
        if self.mesher not in MESHERS:
            raise ValueError(f"mesher is one of {', '.join(MESHERS)}, got {self.mesher!r}")
        if not (math.isfinite(self.error_texels) and self.error_texels >= 0.0):
            raise ValueError(f"Expected error_texels >= 0, got {self.error_texels}")
        if self.resolution is not None and not self.resolution > 0.0:
            raise ValueError(f"Expected a positive resolution, got {self.resolution}")
        if self.z_units is not None:
            parse_z_units(self.z_units)  # refused here, before anything is opened
        if self.batch < 1:
            raise ValueError(f"Expected a batch of at least 1, got {self.batch}")
        for spec in self.imagery:
            if spec.startswith(("http://", "https://")):
                raise ValueError(
                    f"--imagery {spec}: a build bakes local imagery (a raster, .mbtiles or "
                    "folder); give a tile server to render, fly or view instead"
                )


@dataclass(frozen=True)
class BuildReport:
    path: Path
    planned: int
    #: Tiles made by this run (the others were finished by an earlier, interrupted one).
    built: int
    resumed: bool
    seconds: float
    executor: str
    levels: tuple[int, int, int]
    #: The finest level of baked imagery, where imagery was baked (None: the tint alone).
    imagery_zmax: int | None = None


def build(
    inputs: Sequence[str | os.PathLike[str]],
    output: str | os.PathLike[str],
    options: BuildOptions | None = None,
    *,
    executor: BuildExecutor | None = None,
    progress: Progress | None = None,
    shards: str | os.PathLike[str] | None = None,
) -> BuildReport:
    """Build (or finish building) the tileset ``output`` from rasters and/or point files.

    The workers write each block to ``shards`` (a folder every worker and this process can
    reach; default: ``OUTPUT.shards`` beside the output), which this process merges into the
    one file and removes at the end."""
    options = options or BuildOptions()
    out = Path(output)
    t0 = time.perf_counter()
    job, manifest, span, imagery_zmax, source = _prepare(inputs, out, options)
    writer: TilesetWriter | None = None
    folder = Path(shards) if shards is not None else out.with_name(out.name + ".shards")
    own = executor is None
    ok = False
    made = 0
    label = executor.label if executor is not None else "none"
    try:
        writer = TilesetWriter(out, manifest)
        if not writer.resumed:
            clear_shards(folder)  # what another build of this name left
        folder.mkdir(parents=True, exist_ok=True)
        run = _Run(writer, job, str(folder), progress)
        # the terrain's finest level made honest (refined where a tile misses its budget)
        # where no imagery goes below it
        deepen = imagery_zmax <= span.zmax
        finer: Band | None = None
        for band in bands(max(span.zmax, imagery_zmax), span.zmin):
            todo = run.pending(source, band, finer)
            finer = band
            first = next(todo, None)
            if first is None:
                continue
            if executor is None:
                # one numba compile here, not one per worker thread racing for it
                _compile(options.mesher)
                executor = executor_for()
                label = executor.label
            tasks = itertools.chain([first], todo)
            args = ((job, b, str(folder), deepen) for b in tasks)
            for z, x, y, _ in executor.imap(make_block, args):
                run.merge((z, x, y))
        made = run.made
        zmax = max(writer.finest(), span.zmax)
        writer.finish(_mbtiles(manifest, out, _attribution(options, inputs)), zmax=zmax)
        span = replace(span, zmax=zmax)
        ok = True
        clear_shards(folder)
    finally:
        source.close()
        if own and executor is not None:
            executor.close()
        resumed = writer is not None and writer.resumed
        if writer is not None:
            writer.close()
        if not ok and not resumed and _bad_input():
            # an input that fails midway cannot be resumed from (fixing it changes it): leave
            # nothing behind; an interruption or a full disk keeps the file to resume
            for suffix in ("", "-wal", "-shm"):
                Path(str(out) + suffix).unlink(missing_ok=True)
            clear_shards(folder)
    assert writer is not None
    total = _tiles_made(out)
    return BuildReport(
        out,
        total,
        made,
        resumed,
        time.perf_counter() - t0,
        label,
        (span.zmin, span.texture_zmax, span.zmax),
        imagery_zmax if options.imagery else None,
    )


def _tiles_made(path: Path) -> int:
    import sqlite3
    from contextlib import closing

    with closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True)) as db:
        (tiles,) = db.execute("SELECT COUNT(*) FROM plan").fetchone()
    return int(tiles)


class _Run:
    """The coordinator's side of a build: which blocks are left, merging finished shards into
    the file, and the progress it reports (tiles made of those expected: the blocks known so
    far at the tiles a block has held on average)."""

    def __init__(
        self, writer: TilesetWriter, job: Job, folder: str, progress: Progress | None
    ) -> None:
        self.writer, self.job, self.folder, self.progress = writer, job, folder, progress
        self.done, _ = writer.counts()
        self.made = 0
        self.blocks = 0
        self.known = 0

    def pending(self, source: HeightSource, band: Band, finer: Band | None) -> Iterator[Block]:
        """The band's blocks still to make, planned a row at a time (``finer``: the band whose
        roots its finest tiles are made from); a block whose shard is whole (its worker
        finished, this process did not merge it) is merged, not made, and one the coarse
        overview finds without data is recorded and skipped."""
        for row in plan_blocks(source, band):
            if not row:
                continue
            done = self.writer.blocks_done(band.root, row[0].y)
            empty = [b.key for b in row if b.empty and b.x not in done]
            if empty:
                self.writer.skip(empty)
            for b in row:
                if b.x in done or b.empty:
                    continue
                if finer is not None:
                    d = band.leaf + 1 - band.root
                    made = self.writer.blocks_made(
                        finer.root, b.x << d, (b.x + 1) << d, b.y << d, (b.y + 1) << d
                    )
                    b = replace(b, below=frozenset(made))
                self.known += 1
                self._report()
                if shard_path(self.folder, *b.key).exists():
                    self.merge(b.key)
                    continue
                yield b

    def merge(self, key: tuple[int, int, int]) -> None:
        shard = shard_path(self.folder, *key)
        n = self.writer.merge(shard, key)
        # in the file now: only its root's own file is kept (for the band above)
        shard.unlink(missing_ok=True)
        self.done += n
        self.made += n
        self.blocks += 1
        self._report()

    def _report(self) -> None:
        if self.progress is None:
            return
        mean = self.made / self.blocks if self.blocks else 1.0
        waiting = max(self.known - self.blocks, 0)
        self.progress(self.done, self.done + round(waiting * mean))


def _compile(mesher: str) -> None:
    """The numba kernels compiled once, before worker threads race for them."""
    Rtin(np.zeros((3, 3)))
    if mesher == "greedy":
        _compile_tin_error()


def _prepare(
    inputs: Sequence[str | os.PathLike[str]], out: Path, options: BuildOptions
) -> tuple[Job, dict[str, Any], LevelSpan, int, HeightSource]:
    """The inputs opened once (their notes said): the tile task's job, the manifest, the
    levels, the finest imagery level and the source (open: the blocks are planned over it)."""
    rasters = _rasters(inputs, out, options)
    raw = open_rasters(
        rasters,
        allow_mixed_crs=options.allow_mixed_crs,
        band=options.band,
        nodata=options.nodata,
        z_units=options.z_units,
    )
    for note in raster_notes(raw):
        warn_stderr(note)
    said = sea_note(raw, options.sea_level)
    if said is not None:
        warn_stderr(said)
    source = FilledSource(raw, parse_fill(options.fill))
    try:
        _check_resolution(source, options.tile_size)
        span = level_span(
            source.bounds_merc,
            source.resolution_merc,
            tile_size=options.tile_size,
            grids=(16, 32, 64),
            max_samples=None,
        )
        height_range = _height_range(source)
        imagery_zmax = _imagery_zmax(options.imagery, span.texture_zmax)
        job = Job(
            inputs=tuple(absolute(p) for p in rasters),
            allow_mixed_crs=options.allow_mixed_crs,
            tile_size=options.tile_size,
            error_texels=options.error_texels,
            texture_zmax=span.texture_zmax,
            height_range=height_range,
            resolution=source.resolution_merc,
            zmax=span.zmax,
            imagery=tuple(absolute(p) for p in options.imagery),
            imagery_zmax=imagery_zmax,
            fill=options.fill,
            sea_level=options.sea_level,
            band=options.band,
            nodata=options.nodata,
            mesher=options.mesher,
            z_units=options.z_units,
        )
        manifest = _manifest(source, options, inputs, span, height_range, imagery_zmax)
    except BaseException:
        source.close()
        raise
    return job, manifest, span, imagery_zmax, source


def _imagery_zmax(imagery: Sequence[str], texture_zmax: int) -> int:
    """The finest level the tileset's imagery goes to: the tint's, or the finest layer's."""
    if not imagery:
        return texture_zmax
    from lodscape.imagery.layers import open_layer

    finest = texture_zmax
    for i, spec in enumerate(imagery):
        layer = open_layer(spec, i + 1)
        try:
            finest = max(finest, int(layer.max_zoom))
        finally:
            layer.close()
    return finest


def _bad_input() -> bool:
    """Whether the exception being handled is about the inputs."""
    import sys

    from lodscape.imagery.sources import ImageryError

    return isinstance(sys.exc_info()[1], SourceError | ImageryError)


def _rasters(
    inputs: Sequence[str | os.PathLike[str]], out: Path, options: BuildOptions
) -> list[str]:
    """The raster inputs, with point files gridded into one GeoTIFF beside the output."""
    if not inputs:
        raise SourceError("no inputs given")
    rasters = [os.fspath(p) for p in inputs if not _is_points(p)]
    points = [os.fspath(p) for p in inputs if _is_points(p)]
    if points:
        read = [read_points(p) for p in points]
        named = {p: r[3] for p, r in zip(points, read, strict=True) if r[3] is not None}
        if options.crs is not None:
            try:
                crs = CRS.from_user_input(options.crs)
            except Exception as exc:  # pyproj's CRSError on anything it cannot parse
                raise SourceError(f"--crs {options.crs!r} is not a CRS ({exc})") from None
        elif named:
            crs = next(iter(named.values()))
        else:
            raise SourceError(
                f"{points[0]}: point files need their CRS: give --crs (e.g. EPSG:4326)"
            )
        for p, own in named.items():
            if own != crs:
                raise SourceError(
                    f"{p}: its CRS ({own.to_string()}) differs from {crs.to_string()}; "
                    "reproject the points, or give the one --crs they are all in"
                )
        xs, ys, zs = ([r[0] for r in read], [r[1] for r in read], [r[2] for r in read])
        name = points[0] if len(points) == 1 else f"{points[0]} (+{len(points) - 1} more)"
        heights, transform = grid_points(
            np.concatenate(xs),
            np.concatenate(ys),
            np.concatenate(zs),
            name=name,
            resolution=options.resolution,
        )
        grid = out.with_name(out.name + ".points.tif")
        write_grid(grid, heights, transform, crs)
        rasters.append(str(grid))
    return rasters


def _is_points(path: str | os.PathLike[str]) -> bool:
    return os.fspath(path).lower().endswith(POINT_SUFFIXES)


def _height_range(source: HeightSource) -> tuple[float, float]:
    """The data's lowest and highest height (for the imagery's colours): what its source
    knows (a raster's overview, a mosaic's members'), else over a 513² sample of it."""
    known = getattr(source, "data_range", None)
    if known is not None:
        return float(known[0]), float(known[1])
    b = source.bounds_merc
    xs = np.linspace(b.left, b.right, 513)
    ys = np.linspace(b.top, b.bottom, 513)
    h, valid = source.sample_grid(xs, ys, max(b.right - b.left, b.top - b.bottom) / 512)
    if not valid.any():
        raise SourceError(f"{source.name}: no valid heights inside the data's footprint")
    return float(h[valid].min()), float(h[valid].max())


def _check_resolution(source: HeightSource, tile_size: int) -> None:
    """Refuse data finer than the deepest level a tileset holds, before anything is written."""
    wanted = math.ceil(math.log2(2.0 * ORIGIN / (tile_size * source.resolution_merc)))
    limit = MAX_ZOOM - round(math.log2(tile_size / 64))
    if wanted > limit:
        finest = 2.0 * ORIGIN / (tile_size * (1 << limit))
        raise SourceError(
            f"{source.name}: pixels of {source.resolution_merc:.3g} m ask for level {wanted}; "
            f"a tileset of {tile_size}-texel tiles ends at level {limit} ({finest:.3g} m): "
            f"resample the DEM to {finest:.3g} m or coarser (e.g. gdalwarp -tr)"
        )


def _compile_tin_error() -> None:
    """``tin_sample_error`` compiled once, before worker threads race for it."""
    from lodscape.terrain.greedy import tin_sample_error

    grid = np.array([0.0, 1.0])
    tin_sample_error(
        np.array([[0, 1, 2]], np.int32),
        np.array([[0, 0], [1, 0], [0, 1]], np.int32),
        grid,
        grid[::-1].copy(),
        np.zeros((2, 2)),
        np.array([0.2]),
        np.array([0.8]),
        np.array([0.0]),
    )


def _manifest(
    source: HeightSource,
    options: BuildOptions,
    inputs: Sequence[str | os.PathLike[str]],
    span: LevelSpan,
    height_range: tuple[float, float],
    imagery_zmax: int,
) -> dict[str, object]:
    provenance = [provenance_of(os.fspath(p)) for p in inputs]
    remote = [p["path"] for p in provenance if p.get("remote")]
    if remote:
        # a URL's size and time would cost a request each (and a server may not say them)
        warn_stderr(
            f"{remote[0]}{f' (+{len(remote) - 1} more)' if len(remote) > 1 else ''}: a remote "
            "input: its size and time are not recorded, so a resumed build cannot tell whether "
            "it changed"
        )
    opts = asdict(options)
    opts.pop("batch")
    opts.pop("attribution")
    opts["imagery"] = [absolute(p) for p in options.imagery]
    return {
        "schema": SCHEMA_VERSION,
        "tile_size": options.tile_size,
        "levels": {
            "zmin": span.zmin,
            "texture_zmax": span.texture_zmax,
            "zmax": span.zmax,
            # the stored imagery's finest level: the tint's, or a baked layer's own
            "imagery_zmax": imagery_zmax,
        },
        "crs": source.crs_wkt,
        "bounds_merc": list(source.bounds_merc),
        "height_range": list(height_range),
        "resolution_merc": source.resolution_merc,
        "terrain": {
            "format": "quantized-mesh-1.0",
            "extensions": ["octvertexnormals"],
            "scheme": "xyz",
            "projection": "EPSG:3857",
        },
        "provenance": provenance,
        "options": opts,
        # metres per height unit of the rasters not in metres (converted when read)
        "z_factors": {
            absolute(r.path): r.z_factor for r in rasters_of(source) if r.z_factor != 1.0
        },
        # the share of the rasters' pixels in voids inside the data (what interpolate fills)
        "void_share": round(pixel_share(source, lambda r: r.void_share), 6),
    }


#: The metadata keys GDAL reports a raster's credit under (GeoTIFF's copyright tag among them).
_CREDIT_KEYS = ("attribution", "ATTRIBUTION", "TIFFTAG_COPYRIGHT", "COPYRIGHT", "copyright")


def _attribution(options: BuildOptions, inputs: Sequence[str | os.PathLike[str]]) -> str:
    """``options.attribution``, else what the rasters state (each once, in input order), else
    their names and this tool: never a sentence that credits no one."""
    if options.attribution:
        return options.attribution
    import rasterio

    stated: list[str] = []
    for path in inputs:
        if _is_points(path):
            continue
        try:
            with rasterio.open(os.fspath(path)) as ds:
                tags = ds.tags()
        except Exception:  # opened once already: a failure here only loses the credit
            continue
        for key in _CREDIT_KEYS:
            text = str(tags.get(key, "")).strip()
            if text and text not in stated:
                stated.append(text)
                break
    if stated:
        return "; ".join(stated)
    names = ", ".join(os.path.basename(os.fspath(p)) for p in inputs)
    return f"{names}; tiles made with lodscape"


def _mbtiles(manifest: dict[str, object], out: Path, attribution: str) -> dict[str, str]:
    b = manifest["bounds_merc"]
    w, s, e, n = lonlat_bounds(Bbox(*b))  # type: ignore[misc]
    levels = manifest["levels"]
    lo, hi = levels["zmin"], levels["imagery_zmax"]  # type: ignore[index]
    layers = manifest["options"]["imagery"]  # type: ignore[index]
    described = "hypsometric tint with hillshade, made by lodscape"
    if layers:
        names = ", ".join(os.path.basename(str(p)) for p in layers)
        described = f"{names} over the terrain's {described}"
    return {
        "name": out.stem,
        "format": "png",
        "type": "baselayer",
        "version": "1",
        "description": described,
        "attribution": attribution,
        "bounds": f"{w:.7f},{s:.7f},{e:.7f},{n:.7f}",
        "center": f"{(w + e) / 2:.7f},{(s + n) / 2:.7f},{lo}",
        "minzoom": str(lo),
        "maxzoom": str(hi),
    }
