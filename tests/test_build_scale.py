"""Builds whose cost per task is bounded: coarse tiles from their children (no pixel of the
data read), blocks without data skipped, shards merged into one file (real GeoTIFFs, real
SQLite, threads and a Dask cluster)."""

from __future__ import annotations

import sqlite3
import threading
from collections import defaultdict
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import lodscape
from _synthetic import fbm_heights, write_dem
from lodscape import Camera, SceneOptions
from lodscape.build import blocks, build, tiles
from lodscape.build.executors import PoolExecutor
from lodscape.geo.tiles import ORIGIN, merc_to_lonlat
from lodscape.terrain import source


def _counting(monkeypatch: pytest.MonkeyPatch) -> dict[int, list[int]]:
    """Pixels of the data read while each tile is made, by the tile's level."""
    local = threading.local()
    pixels: dict[int, list[int]] = defaultdict(list)
    read = source.RasterSource._read_raw

    def counted(self: Any, overview: Any, r0: int, r1: int, c0: int, c1: int) -> Any:
        if getattr(local, "count", None) is not None:
            local.count += max(r1 - r0, 0) * max(c1 - c0, 0)
        return read(self, overview, r0, r1, c0, c1)

    def per_tile(fn: Any) -> Any:
        def wrapped(job: Any, z: int, x: int, y: int, *a: Any) -> Any:
            outer = getattr(local, "count", None)
            local.count = 0
            try:
                return fn(job, z, x, y, *a)
            finally:
                pixels[z].append(local.count)
                local.count = outer

        return wrapped

    monkeypatch.setattr(source.RasterSource, "_read_raw", counted)
    for name in ("made_from_data", "made_from_children", "made_without_data"):
        monkeypatch.setattr(blocks, name, per_tile(getattr(tiles, name)))
    return pixels


@pytest.mark.parametrize("size", [513, 1025])
def test_no_tile_reads_more_pixels_than_its_finest_level_does(
    size: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever the DEM's size, the most pixels a tile reads is about its own grid's (the
    finest levels' tiles are as fine as the data), and a tile below the finest imagery level
    reads none: it is made from its four children."""
    dem = write_dem(
        str(tmp_path / "dem.tif"),
        fbm_heights(size, seed=3),
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=10.0,
    )
    pixels = _counting(monkeypatch)
    report = build([dem], tmp_path / "out.lods", executor=PoolExecutor(2, processes=False))
    zmin, texture_zmax, _ = report.levels
    assert zmin < texture_zmax
    worst = max(max(v) for v in pixels.values())
    # the tint of the finest imagery level samples a (256 + 2)² grid of texels as fine as the
    # data's pixels, at most twice as coarse: its 2×2 blocks of pixels
    assert worst <= 4 * 258 * 258, dict(pixels)
    for z, counts in pixels.items():
        if z < texture_zmax:
            assert max(counts) == 0, (z, max(counts))
    assert sum(len(v) for z, v in pixels.items() if z < texture_zmax) > 0


def test_blocks_without_data_are_skipped_and_the_picture_keeps_no_hole(tmp_path: Path) -> None:
    """A DEM whose western half is nodata: the blocks there are not made (the coarser tiles
    over them stand on the fill), and a view over the whole of it shows the fill there, not a
    hole."""
    h = fbm_heights(1025, seed=9).astype(np.float32)
    h[:, :512] = -9999.0
    dem = write_dem(
        str(tmp_path / "half.tif"),
        h,
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=10.0,
        nodata=-9999.0,
    )
    out = tmp_path / "half.lods"
    report = build([dem], out, executor=PoolExecutor(2, processes=False))
    full = tmp_path / "full.tif"
    write_dem(
        str(full),
        np.where(h == -9999.0, 100.0, h).astype(np.float32),
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=10.0,
    )
    whole = build([full], tmp_path / "full.lods", executor=PoolExecutor(2, processes=False))
    _, texture_zmax, _ = report.levels

    def levels(p: Path) -> dict[int, list[tuple[int, int]]]:
        out: dict[int, list[tuple[int, int]]] = defaultdict(list)
        with closing(sqlite3.connect(p)) as db:
            for z, x, y in db.execute("SELECT z, x, y FROM plan"):
                out[z].append((x, y))
        return out

    half, entire = levels(out), levels(tmp_path / "full.lods")
    with closing(sqlite3.connect(out)) as db:
        empty = db.execute("SELECT COUNT(*) FROM blocks WHERE tiles = 0").fetchone()[0]
    assert empty > 0
    fine = texture_zmax + 2  # the finest level planned before the refinement
    assert len(half[fine]) < 0.65 * len(entire[fine]), (len(half[fine]), len(entire[fine]))
    assert report.planned < whole.planned
    # no tile of the fine levels lies wholly over the nodata half
    with lodscape.open(dem) as raw:
        b = raw.source.bounds_merc
    middle = (b.left + b.right) / 2.0
    for z in range(texture_zmax + 1, fine + 1):
        east = np.array([-ORIGIN + (x + 1) * 2.0 * ORIGIN / (1 << z) for x, _ in half[z]])
        assert (east > middle - 2.0 * ORIGIN / (1 << z)).all(), z
    with lodscape.open(out, SceneOptions(ellipsoid=False)) as scene:
        lon_c, lat_c = merc_to_lonlat((b.left + b.right) / 2.0, (b.top + b.bottom) / 2.0)
        cam = Camera(float(lon_c), float(lat_c), 4000.0, pitch=-90.0, width=160, height=120)
        _, dist = scene.render(cam)
    # every pixel is the terrain's or its fill's: none is the sky
    assert np.isfinite(dist).all()


def test_a_build_keeps_its_shards_apart_and_merges_them(tmp_path: Path) -> None:
    """The shards go where asked (a folder the workers share), and are gone when the file is
    whole; a build's tiles are the same wherever its shards were."""
    dem = write_dem(
        str(tmp_path / "dem.tif"),
        fbm_heights(257, seed=5),
        crs="EPSG:32617",
        west=700000.0,
        north=4060000.0,
        res=10.0,
    )
    seen: list[list[str]] = []
    shards = tmp_path / "shared" / "shards"

    def progress(done: int, total: int) -> None:
        if shards.exists():
            seen.append(sorted(p.name for p in shards.iterdir()))

    a = build([dem], tmp_path / "a.lods", shards=shards, progress=progress)
    b = build([dem], tmp_path / "b.lods")
    assert any(names for names in seen)

    # shards, and the temporaries they are written to (renamed into place when whole), with
    # SQLite's rollback journal of a temporary while it is written; never a shard's own
    def temporary(n: str) -> bool:
        return n.removesuffix("-journal").endswith(".tmp")

    assert all(n.endswith(".sqlite") or temporary(n) for names in seen for n in names), seen
    assert not shards.exists()
    assert not (tmp_path / "b.lods.shards").exists()
    assert a.planned == b.planned

    def rows(p: Path) -> list[tuple[Any, ...]]:
        with closing(sqlite3.connect(p)) as db:
            return db.execute("SELECT * FROM terrain ORDER BY z, x, y").fetchall()

    assert rows(tmp_path / "a.lods") == rows(tmp_path / "b.lods")
