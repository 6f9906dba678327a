"""What a SOURCE is and how a scene is opened from it: the source string parsed once, the
provider composed (terrain, then imagery or land cover on top) before the scene is made, and the
cities draped.

    scene = lodscape.open("dem.tif", imagery="https://tile.example/{z}/{x}/{y}.png",
                          city="town.osm.pbf")
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, overload

import numpy as np
from numpy.typing import NDArray

from lodscape._cache import user_cache
from lodscape.errors import LodscapeError, SourceError
from lodscape.frame.globe import GlobeOptions
from lodscape.imagery.layers import warn_stderr
from lodscape.scene import Scene, SceneOptions

if TYPE_CHECKING:
    from lodscape.globe import Globe
from lodscape.store.provider import FractalProvider, Provider, RasterProvider
from lodscape.store.tileset import TilesetProvider, is_tileset
from lodscape.stream.streamer import Clock
from lodscape.terrain.detail import (
    DetailHeights,
    DetailTree,
    Fractal,
    ProceduralHeights,
    ProceduralTree,
    parse_procedural,
    procedural_relief,
)
from lodscape.terrain.pyramid import build_tree
from lodscape.terrain.source import (
    ArraySource,
    Fill,
    FilledSource,
    HeightSource,
    RasterSource,
    parse_fill,
    sea_note,
)

__all__ = [
    "SourceSpec",
    "flat_source",
    "fractal_provider",
    "open",
    "parse_source",
    "procedural_provider",
]

Kind = Literal["tileset", "raster", "procedural", "flat", "none", "server"]


@dataclass(frozen=True)
class SourceSpec:
    """A SOURCE argument, read once: what kind of terrain it names, and the text."""

    kind: Kind
    text: str

    @property
    def has_lattice(self) -> bool:
        """Whether heights come on a lattice fractal detail can refine (not a tileset)."""
        return self.kind in ("raster", "flat")


def parse_source(source: str | PathLike[str]) -> SourceSpec:
    """``none`` or ``-`` (no terrain: the globe alone), ``flat`` (level ground under a city),
    ``flat:W,S,E,N[,H]``, ``procedural[:seed=N,…]``, terrain on a server (a quantized-mesh
    ``layer.json`` URL, ``terrarium:URL``, ``terrain-rgb:URL``), a .lods tileset, or a raster
    path."""
    from lodscape.store.remote import is_server_spec

    text = os.fspath(source)
    if text in ("none", "-"):
        return SourceSpec("none", text)
    if is_server_spec(text):
        return SourceSpec("server", text)
    if text.lower().startswith(("http://", "https://")):
        # a terrain server's layer (or its folder) whatever its path, else a raster for GDAL
        from lodscape.store.remote import server_layer

        layer = server_layer(text)
        if layer is not None:
            return SourceSpec("server", layer)
    if text == "flat" or text.startswith("flat:"):
        return SourceSpec("flat", text)
    if text == "procedural" or text.startswith("procedural:"):
        return SourceSpec("procedural", text)
    if is_tileset(text):
        return SourceSpec("tileset", text)
    return SourceSpec("raster", text)


Opened = str | PathLike[str] | HeightSource | Provider | NDArray[np.floating]


@overload
def open(
    source: Opened, options: SceneOptions | None = None, *, globe: None = None, **kwargs: Any
) -> Scene: ...


@overload
def open(
    source: Opened, options: SceneOptions | None = None, *, globe: GlobeOptions, **kwargs: Any
) -> Globe: ...


def open(
    source: Opened,
    options: SceneOptions | None = None,
    *,
    clock: Clock | None = None,
    detail: Fractal | None = None,
    landcover: Any = None,
    imagery: str | PathLike[str] | Sequence[str | PathLike[str]] | None = None,
    imagery_cache: str | PathLike[str] | None = None,
    imagery_maxzoom: int | None = None,
    imagery_bands: str | Sequence[int] | None = None,
    city: Any = None,
    fill: str | Fill | None = None,
    sea_level: float | None = 0.0,
    band: int | None = None,
    nodata: float | None = None,
    z_units: str | None = None,
    city_options: Any = None,
    globe: GlobeOptions | None = None,
    **array_kwargs: Any,
) -> Scene | Globe:
    """A scene over a tileset built by ``lodscape build`` (.lods), a GeoTIFF (any GDAL raster), a
    numpy array (with ``transform``, ``crs``), the procedural planet (``"procedural:seed=N"``),
    level ground (``"flat:W,S,E,N"``, or ``"flat"`` under ``city``), or a ready HeightSource or
    Provider.

    - ``detail`` adds fractal detail below a raster's resolution (paper 003);
    - ``landcover`` (an ``imagery.landcover.Landcover``) colours the ground from its class masks;
    - ``imagery``: one imagery layer or a list of them, bottom to top, drawn over the terrain's
      own colours at their own resolution: XYZ URL templates (cached under ``imagery_cache``,
      levels up to ``imagery_maxzoom``, default 19), .mbtiles files, folders of z/x/y tiles, or
      georeferenced rasters (their colour bands: ``imagery_bands``, "R,G,B" or three 1-based
      numbers, else their colour interpretation, else their first three, said once), or
      georeferenced rasters (a GeoTIFF orthophoto in any CRS). Where a layer is finer than a
      raster DEM the tile tree goes on below the DEM with its surface refined, no heights made
      up. Failures are counted (``Scene.imagery_failures``) and said once on stderr;
      ``options.imagery_timeout`` bounds a render's wait and ``options.imagery_strict`` makes
      any failure an error;
    - ``city`` (an OSM file or a ``City``) is draped on it, with the cities a tileset stores,
      drawn as ``city_options`` (a ``city.model.CityOptions``: culling, levels of detail, the
      scene tree's packing) say;
    - ``fill``: what stands where a raster has no data: ``none`` (a hole, nothing drawn),
      ``nearest`` (the nearest valid height stretched), ``value:H`` or ``ellipsoid`` (height
      0); a tileset keeps the fill it was built with;
    - ``sea_level``: heights below it are tinted as water (None: no sea);
    - ``band`` picks a multi-band raster's height band; ``nodata`` declares a nodata value the
      file does not; ``z_units`` (``m``, ``ft``, ``us-ft`` or metres per unit) says what unit
      its heights are in, where the file's own unit, vertical CRS or projected CRS would not.
    - ``globe`` (``GlobeOptions``): the whole Earth on the QTM grid (paper 002) with the scene's
      own tiles (and its city) where it has data, one frame loop and one picture from orbit to
      the street (``lodscape.globe.Globe``); SOURCE ``"none"``: the globe alone, with the
      ``imagery`` layers over all of it.

    A scene opened from a path or an array closes what it opened when it closes."""
    if globe is not None:
        return _open_globe(
            source,
            options,
            globe,
            clock=clock,
            detail=detail,
            landcover=landcover,
            imagery=imagery,
            imagery_cache=imagery_cache,
            imagery_maxzoom=imagery_maxzoom,
            imagery_bands=imagery_bands,
            city=city,
            fill=fill,
            sea_level=sea_level,
            band=band,
            nodata=nodata,
            z_units=z_units,
            city_options=city_options,
            **array_kwargs,
        )
    opts = options or SceneOptions()
    if opts.ellipsoid and opts.earth:
        # the ellipsoid's Earth decodes beside the DEM's reading, not before the first picture
        from lodscape.render.passes import prefetch_blue_marble

        prefetch_blue_marble()
    provider, owns, town = _assemble(
        source,
        opts,
        detail,
        landcover,
        _imagery_specs(imagery),
        (imagery_cache, imagery_maxzoom, imagery_bands),
        city,
        (fill, sea_level, band, nodata, z_units),
        array_kwargs,
    )
    scene = Scene(provider, options, owns=owns, clock=clock)
    try:
        stored = provider.city()
        if stored is not None and town is not None:
            stored = stored.merged(town)
        if stored is not None or town is not None:
            scene.add_city(stored if stored is not None else town, city_options)
    except BaseException:
        scene.close()
        raise
    return scene


def _assemble(
    source: Any,
    opts: SceneOptions,
    detail: Fractal | None,
    landcover: Any,
    specs: list[str],
    imagery: tuple[Any, int | None, Any],
    city: Any,
    ground_args: tuple[Any, float | None, int | None, float | None, str | None],
    array_kwargs: dict[str, Any],
) -> tuple[Provider, bool, Any]:
    """``open``'s provider: SOURCE's terrain (a tileset, a raster, an array, the procedural
    planet, level ground), with its land cover or its imagery layers; whether the scene owns
    it; the city read (None: none)."""
    imagery_cache, imagery_maxzoom, imagery_bands = imagery
    fill, sea_level, band, nodata, z_units = ground_args
    if landcover is not None and specs:
        raise LodscapeError("imagery and a land cover both colour the ground: pick one")
    town = _read_city(city)
    spec = None if not isinstance(source, str | PathLike) else parse_source(source)
    if spec is not None and spec.kind == "flat" and spec.text == "flat":
        if town is None:
            raise SourceError("SOURCE flat (level ground) needs a city to know where")
        source = _ground_under(town)
        spec = parse_source(source)
    lattice = isinstance(source, np.ndarray) or (spec is not None and spec.has_lattice)
    if landcover is not None and detail is None and lattice:
        # a mask is worth metres, not the DEM's resolution: the tree goes on below the data
        # with heights interpolated (fractal detail of no amplitude), and its masks with it
        detail = Fractal(0.7, 0.0, 0)
    if (
        spec is not None
        and spec.kind != "raster"
        and (band or nodata is not None or z_units is not None)
    ):
        raise SourceError(f"{spec.text}: --band, --nodata and --z-units are for a raster DEM")
    if spec is not None and spec.kind == "tileset" and fill is not None:
        raise SourceError(f"{spec.text}: a tileset keeps the fill it was built with (--fill)")
    if fill is None:
        fill = Fill()
    ground = _Ground(
        fill if isinstance(fill, Fill) else parse_fill(fill), sea_level, band, nodata, z_units
    )
    layers = _open_layers(
        specs,
        imagery_cache,
        imagery_maxzoom,
        opts.imagery_timeout,
        opts.imagery_strict,
        _bands(imagery_bands),
    )
    try:
        provider, owns = _terrain(
            source,
            spec,
            detail,
            array_kwargs,
            ground,
            cache=_cache_dir(imagery_cache),
            timeout=opts.imagery_timeout,
        )
    except BaseException:
        for layer in layers:
            layer.close()
        raise
    try:
        if town is not None:
            _city_on(town, provider)
            if isinstance(city, str | PathLike):
                # what could not be made of the file: said once, of a city that is drawn
                note = town.skipped_note()
                if note is not None:
                    warn_stderr(note)
        if landcover is not None:
            from lodscape.store.provider import LandcoverProvider

            provider = LandcoverProvider(provider, landcover)
        elif layers:
            provider = _with_layers(provider, layers, owns)
    except BaseException:
        for layer in layers:
            layer.close()
        if owns:
            provider.close()
        raise
    return provider, owns, town


def _open_globe(
    source: Any, options: SceneOptions | None, globe: GlobeOptions, **kwargs: Any
) -> Globe:
    """The globe over SOURCE's scene, or (SOURCE "none") over the ellipsoid with the imagery
    layers alone."""
    from lodscape.globe import Globe

    options = options or SceneOptions()
    globe = replace(globe, imagery_timeout=options.imagery_timeout)
    if isinstance(source, str) and parse_source(source).kind == "none":
        if kwargs.get("city") is not None:
            raise LodscapeError("a city on the globe needs SOURCE (a DEM, a tileset, or flat)")
        if any(kwargs.get(k) is not None for k in ("landcover", "detail")):
            raise LodscapeError(
                "land cover and fractal detail colour and shape a terrain: give SOURCE (a DEM "
                "or a tileset) for the globe to draw them on"
            )
        layers = _open_layers(
            _imagery_specs(kwargs.get("imagery")),
            kwargs.get("imagery_cache"),
            kwargs.get("imagery_maxzoom"),
            options.imagery_timeout,
            options.imagery_strict,
            _bands(kwargs.get("imagery_bands")),
        )
        clock = kwargs.get("clock")
        stream = options.stream if clock is not None else None
        try:
            return Globe(None, globe, layers=layers, clock=clock, stream=stream)
        except BaseException:
            for layer in layers:
                layer.close()
            raise
    if isinstance(source, str) and parse_source(source).kind == "procedural":
        globe = replace(globe, earth="procedural")  # an invented planet, asked for
    scene = open(source, options, **kwargs)
    try:
        return Globe(scene, globe)
    except BaseException:
        scene.close()
        raise


def _city_on(town: Any, provider: Any) -> None:
    """Refuse a city that lies wholly outside the terrain's footprint (it would stand on the
    ellipsoid far from the data, as ``city add`` refuses it)."""
    box = getattr(provider, "bounds_merc", None)
    if box is None:
        return
    from lodscape.geo.tiles import merc_to_lonlat

    (w, e), (s, n) = merc_to_lonlat([box.left, box.right], [box.bottom, box.top])
    cw, cs, ce, cn = town.bounds
    if ce < w or cw > e or cn < s or cs > n:
        raise SourceError(
            f"{town.name}: lies outside the terrain ({cw:.5f}, {cs:.5f}, {ce:.5f}, {cn:.5f} "
            f"against {w:.5f}, {s:.5f}, {e:.5f}, {n:.5f}); is it the right place?"
        )


def _read_city(city: Any) -> Any:
    if city is None or not isinstance(city, str | PathLike):
        return city
    from lodscape.city.osm import read_osm

    return read_osm(Path(city))


def _ground_under(town: Any) -> str:
    """``flat:…`` level ground over a city's box and a margin around it."""
    w, s, e, n = town.bounds
    pw, ps = 0.3 * (e - w) + 0.002, 0.3 * (n - s) + 0.001
    return f"flat:{w - pw},{s - ps},{e + pw},{n + ps}"


@dataclass(frozen=True)
class _Ground:
    """How a raster's heights are read and tinted: the fill, the sea, the band, nodata."""

    fill: Fill = field(default_factory=Fill)
    sea_level: float | None = 0.0
    band: int | None = None
    nodata: float | None = None
    z_units: str | None = None


def _cache_dir(cache: str | PathLike[str] | None) -> Path:
    """Where HTTP tiles are kept: the given folder, else the user's cache."""
    return Path(cache) if cache is not None else user_cache()


def _terrain(
    source: Any,
    spec: SourceSpec | None,
    detail: Fractal | None,
    array_kwargs: dict[str, Any],
    ground: _Ground | None = None,
    *,
    cache: Path | None = None,
    timeout: float = 10.0,
) -> tuple[Provider, bool]:
    """The terrain provider a source names, and whether the scene owns it."""
    ground = ground or _Ground()
    if spec is None:
        dataset = _rasterio_dataset(source)
        if dataset is not None:
            # a rasterio dataset the caller opened: read again by its name (a file, a URL,
            # /vsimem/…), with the same band, nodata and units rules as a path
            return _terrain(dataset, parse_source(dataset), detail, array_kwargs, ground)
        source = _array_of(source, array_kwargs)
        if isinstance(source, np.ndarray):
            if ground.nodata is not None:
                array_kwargs = {"nodata": ground.nodata, **array_kwargs}
            if "transform" not in array_kwargs:
                raise SourceError(
                    "array: a numpy array needs transform= (an affine: six numbers, or a "
                    "rasterio/affine Affine) and crs= (default EPSG:3857) to be placed on the "
                    "Earth; an xarray DataArray brings them through rioxarray's .rio"
                )
            array = ArraySource(source, **array_kwargs)
            return _lattice(FilledSource(array, ground.fill), detail, ground.sea_level), True
        if detail is not None:
            raise SourceError("fractal detail needs a raster source, not a ready provider")
        if hasattr(source, "sample"):  # a height source: meshed on the fly
            filled = source if ground.fill.kind == "none" else FilledSource(source, ground.fill)
            return RasterProvider(filled, sea_level=ground.sea_level), False
        return source, False
    if spec.kind == "none":
        raise SourceError(f"{spec.text}: no terrain (none is for the globe alone)")
    if spec.kind == "procedural":
        return procedural_provider(spec.text, detail, sea_level=ground.sea_level), True
    if spec.kind == "server":
        if detail is not None:
            raise SourceError(f"{spec.text}: fractal detail needs a raster source, not a server")
        if ground.fill.kind != "none":
            raise SourceError(
                f"{spec.text}: a server's terrain is drawn as it comes (--fill is for rasters)"
            )
        from lodscape.store.remote import RemoteProvider, open_server

        if cache is not None:
            cache.mkdir(parents=True, exist_ok=True)
        heights, tree = open_server(spec.text, cache_dir=cache, timeout=max(timeout, 0.5))
        return RemoteProvider(heights, tree), True
    if spec.kind == "tileset":
        if detail is not None:
            raise SourceError(
                f"{spec.text}: fractal detail needs a raster source; a tileset keeps no lattice "
                "of the data to add it to"
            )
        tileset = TilesetProvider(spec.text)
        finest = tileset.texture_levels[0]
        if finest > tileset.tree.zmax:
            # imagery baked finer than the terrain: its stored surface, cut finer to wear it
            from lodscape.store.provider import RefinedProvider

            return RefinedProvider(tileset, finest), True
        return tileset, True
    if spec.kind == "flat":
        src: HeightSource = flat_source(spec.text)
    elif spec.text.lower().endswith(".lods") and os.path.exists(spec.text):
        # named as a tileset, and not an SQLite file: say that, not that GDAL cannot read it
        size = os.path.getsize(spec.text)
        what = "an empty file" if size == 0 else f"{size:,d} bytes that are not SQLite"
        raise SourceError(f"{spec.text}: not a lodscape tileset ({what})")
    else:
        raster = RasterSource(
            spec.text, band=ground.band, nodata=ground.nodata, z_units=ground.z_units
        )
        for note in raster.notes:
            warn_stderr(note)
        said = sea_note(raster, ground.sea_level)
        if said is not None:
            warn_stderr(said)
        src = FilledSource(raster, ground.fill)
    return _lattice(src, detail, ground.sea_level), True


def _rasterio_dataset(source: Any) -> str | None:
    """The name of a rasterio dataset passed as SOURCE (None: not one)."""
    try:
        import rasterio.io
    except ImportError:  # pragma: no cover - rasterio is a dependency
        return None
    if isinstance(source, rasterio.io.DatasetReaderBase):
        if source.closed:
            raise SourceError(f"{source.name}: the rasterio dataset is closed")
        return str(source.name)
    return None


def _array_of(source: Any, array_kwargs: dict[str, Any]) -> Any:
    """An xarray DataArray as its heights, with its transform, CRS and nodata (rioxarray's
    ``.rio``) put in ``array_kwargs`` where the caller did not give them; anything else as
    it is."""
    module = type(source).__module__ or ""
    if not module.startswith("xarray") or not hasattr(source, "dims"):
        return source
    name = f"xarray {getattr(source, 'name', None) or 'DataArray'}"
    try:
        rio = source.rio  # the accessor exists once rioxarray is imported
    except AttributeError:
        raise SourceError(
            f"{name}: needs rioxarray (pip install rioxarray; import rioxarray) for its "
            "transform and CRS, or pass .values with transform= and crs="
        ) from None
    data = source.squeeze()
    if data.ndim != 2:
        raise SourceError(f"{name}: expected one band of heights, got dims {source.dims}")
    crs = rio.crs
    if crs is None and "crs" not in array_kwargs:
        raise SourceError(f"{name}: has no CRS (da.rio.write_crs(...), or pass crs=)")
    array_kwargs.setdefault("transform", rio.transform())
    array_kwargs.setdefault("crs", crs.to_wkt() if crs is not None else None)
    nodata = rio.nodata if rio.nodata is not None else rio.encoded_nodata
    if nodata is not None and "nodata" not in array_kwargs:
        array_kwargs["nodata"] = float(nodata)
    return np.asarray(data.values)


def _lattice(src: HeightSource, detail: Fractal | None, sea_level: float | None) -> Provider:
    if detail is None:
        return RasterProvider(src, sea_level=sea_level)
    try:
        return fractal_provider(src, detail, sea_level=sea_level)
    except BaseException:
        src.close()
        raise


def _imagery_specs(imagery: Any) -> list[str]:
    if imagery is None:
        return []
    if isinstance(imagery, str | PathLike):
        return [os.fspath(imagery)]
    return [os.fspath(i) for i in imagery]


def _bands(bands: str | Sequence[int] | None) -> tuple[int, ...] | None:
    if bands is None:
        return None
    from lodscape.imagery.raster import parse_bands

    return parse_bands(bands if isinstance(bands, str) else ",".join(map(str, bands)))


def _silent(message: str) -> None:
    """A warning not said (what an error says instead)."""


def _open_layers(
    specs: list[str],
    cache: str | PathLike[str] | None,
    max_zoom: int | None,
    timeout: float,
    strict: bool = False,
    bands: tuple[int, ...] | None = None,
) -> list[Any]:
    """The imagery layers, bottom to top; none half-opened on an error. ``strict``: a failure
    ends the frame with its own error line, so the layers say nothing before it."""
    if not specs:
        return []
    from lodscape.imagery.layers import MAX_OVERLAYS, open_layer

    if len(specs) > MAX_OVERLAYS:
        raise LodscapeError(f"at most {MAX_OVERLAYS} imagery layers, got {len(specs)}")
    cache = _cache_dir(cache)
    layers: list[Any] = []
    try:
        for i, text in enumerate(specs):
            layers.append(
                open_layer(
                    text,
                    i + 1,
                    cache_dir=Path(cache),
                    max_zoom=max_zoom,
                    timeout=max(timeout, 0.5),
                    bands=bands,
                    **({"warn": _silent} if strict else {}),
                )
            )
    except BaseException:
        for layer in layers:
            layer.close()
        raise
    return layers


def _with_layers(provider: Provider, layers: list[Any], owns: bool) -> Provider:
    """The layers over the terrain. Where one is finer than a raster DEM's tree goes, the tree
    goes on below it with the DEM's surface refined (fractal detail of no amplitude: heights
    interpolated, none made up), and the terrain's own texture stops at the DEM's level."""
    from lodscape.store.provider import LayeredProvider, RefinedProvider

    finest = max(int(layer.max_zoom) for layer in layers)
    own = provider.texture_levels[0]
    deepen = getattr(provider.tree, "deepen", None)
    if deepen is not None and finest > provider.tree.zmax:
        deepen(finest)  # a server's tree: its finest surface interpolated below its data
    if finest > provider.tree.zmax:
        if type(provider) is RasterProvider and owns:
            base = provider.tree
            if getattr(base, "twist", None) is None:
                # a tree made on demand has no twist per finest tile, which the refinement
                # below the data bounds its error by: the raster is walked whole here
                base = build_tree(provider.source)
                closing = getattr(provider.tree, "close", None)
                if closing is not None:
                    closing()
            tree = DetailTree.over(base, Fractal(0.7, 0.0, 0))
            provider = FractalProvider(
                DetailHeights(provider.source, tree), tree, sea_level=provider.imagery.sea_level
            )
        elif not isinstance(provider, FractalProvider):
            # no lattice to refine (a tileset): its finest stored surface, sampled finer
            provider = RefinedProvider(provider, finest)
    return LayeredProvider(provider, layers, own_zmax=own)


def flat_source(spec: str) -> ArraySource:
    """``flat:WEST,SOUTH,EAST,NORTH[,HEIGHT]``: level ground (the ellipsoid, or HEIGHT metres
    above it) over a box in degrees, for cities and tests with no DEM."""
    try:
        vals = [float(v) for v in spec.split(":", 1)[1].split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (4, 5) or not all(math.isfinite(v) for v in vals):
        raise SourceError(f"{spec}: expected flat:WEST,SOUTH,EAST,NORTH[,HEIGHT] in degrees")
    w, s, e, n = vals[:4]
    h = vals[4] if len(vals) == 5 else 0.0
    if not (-180.0 <= w < e <= 180.0 and -85.0 <= s < n <= 85.0):
        raise SourceError(f"{spec}: the box must have west < east and south < north, in degrees")
    size = 65
    from affine import Affine

    transform = Affine(
        (e - w) / (size - 1),
        0.0,
        w - 0.5 * (e - w) / (size - 1),
        0.0,
        -(n - s) / (size - 1),
        n + 0.5 * (n - s) / (size - 1),
    )
    src = ArraySource(np.full((size, size), h), transform, crs="EPSG:4326")
    src.name = spec
    return src


def fractal_provider(
    source: HeightSource, fractal: Fractal, *, sea_level: float | None = 0.0
) -> FractalProvider:
    """A raster with fractal detail below its resolution."""
    tree = DetailTree.over(build_tree(source), fractal)
    return FractalProvider(DetailHeights(source, tree), tree, sea_level=sea_level)


def procedural_provider(
    spec: str, override: Fractal | None = None, *, sea_level: float | None = 0.0
) -> FractalProvider:
    """The procedural planet of ``procedural:seed=N[,hurst=H][,sigma=S][,relief=R]``;
    ``override``'s fields, where given, win over the spec's (its hurst and sigma are the
    continents')."""
    try:
        f = parse_procedural(spec)
        relief = procedural_relief(spec)
    except ValueError as exc:
        raise SourceError(str(exc)) from None
    if override is not None:
        f = Fractal(
            override.hurst,
            override.sigma if override.sigma is not None else f.sigma,
            override.seed,
        )
    sigma = float(f.sigma if f.sigma is not None else 0.0)
    tree = ProceduralTree(f, sigma, relief)
    return FractalProvider(ProceduralHeights(tree), tree, sea_level=sea_level)
