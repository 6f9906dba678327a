"""The greedy (Delaunay refinement) mesher of tileset builds, and the TIN error that measures it."""

from __future__ import annotations

import sqlite3
from contextlib import closing
from pathlib import Path

import numpy as np
import pytest

from _synthetic import fbm_heights, run_cli, write_dem
from lodscape.build.tiles import _sample_error
from lodscape.store.quantized_mesh import decode
from lodscape.terrain.greedy import greedy_mesh, tin_sample_error
from lodscape.terrain.rtin import Rtin, mesh_error


@pytest.mark.parametrize("bound", [0.5, 2.0, 8.0])
def test_greedy_meshes_keep_to_their_bound_with_fewer_triangles_than_rtin(bound: float) -> None:
    heights = fbm_heights(65, seed=11).astype(np.float64)
    verts, tris = greedy_mesh(heights, bound)
    # drawn back onto the grid, every height is within the bound
    assert mesh_error(heights, verts, tris) <= bound + 1e-3
    assert verts.dtype == np.int32
    assert verts.shape[1] == 2
    assert verts.min() >= 0
    assert verts.max() <= 64
    # the corners are vertices: the mesh covers the whole tile
    corners = {(0, 0), (64, 0), (0, 64), (64, 64)}
    assert corners <= {tuple(v) for v in verts.tolist()}
    # heights are read where they are: a vertex's height is the grid's at its (col, row)
    rtin_tris = Rtin(heights).mesh(bound)[1]
    assert len(tris) < len(rtin_tris)


def test_a_flat_grid_is_two_triangles_and_a_bad_one_is_refused() -> None:
    verts, tris = greedy_mesh(np.full((65, 65), 120.0), 0.1)
    assert len(tris) == 2
    assert len(verts) == 4
    with pytest.raises(ValueError, match="finite"):
        greedy_mesh(np.array([[0.0, np.nan], [0.0, 0.0]]), 1.0)
    with pytest.raises(ValueError, match="non-negative"):
        greedy_mesh(np.zeros((3, 3)), -1.0)


def test_tin_error_agrees_with_rtins_own_point_location() -> None:
    """Two ways of locating scattered samples in an RTIN mesh (descending its hierarchy, and
    searching the triangles over each cell) give the same error."""
    rng = np.random.default_rng(3)
    heights = fbm_heights(65, seed=2).astype(np.float64)
    rtin = Rtin(heights)
    verts, tris = rtin.mesh(3.0)
    # a tile's lon/lat lattice: uniform in longitude, Mercator-spaced in latitude
    lon = np.linspace(7.0, 7.1, 65)
    lat = np.degrees(np.arctan(np.sinh(np.linspace(0.82, 0.818, 65))))
    plon = rng.uniform(lon[0], lon[-1], 5000)
    plat = rng.uniform(lat[-1], lat[0], 5000)
    ph = rng.normal(500.0, 50.0, 5000)
    want = _sample_error(rtin.errors, 3.0, lon, lat, heights, plon, plat, ph)
    got = tin_sample_error(tris, verts, lon, lat, heights, plon, plat, ph)
    assert got == pytest.approx(want, rel=1e-9)
    # one sample, worked by hand: the middle of the flat tile's south-west triangle
    flat = np.full((65, 65), 10.0)
    fv, ft = greedy_mesh(flat, 0.0)
    assert tin_sample_error(ft, fv, lon, lat, flat, lon[:1] + 0.01, lat[-1:] + 0.001,
                            np.array([13.5])) == pytest.approx(3.5)  # fmt: skip
    # a sample in no triangle (a hole) is not the mesh's to match
    assert tin_sample_error(ft[:0], fv, lon, lat, flat, plon[:5], plat[:5], ph[:5]) == 0.0


def test_build_with_the_greedy_mesher_draws_fewer_triangles(tmp_path: Path, capsys: object) -> None:
    dem = write_dem(str(tmp_path / "dem.tif"), fbm_heights(257, seed=9), crs="EPSG:32617",
                    west=700000.0, north=4060000.0, res=10.0)  # fmt: skip
    counts = {}
    for mesher in ("rtin", "greedy"):
        out = tmp_path / f"{mesher}.lods"
        code, _, err = run_cli(["build", dem, "-o", str(out), "--mesher", mesher, "-q"], capsys)
        assert code == 0, err
        counts[mesher] = _triangles(out)
    assert counts["greedy"] < 0.85 * counts["rtin"], counts
    code, _, err = run_cli(["build", dem, "-o", str(tmp_path / "x.lods"), "--mesher", "tin"],
                           capsys)  # fmt: skip
    assert code == 2
    assert "mesher" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.lods").exists()
    # a build finished with one mesher is not resumed with the other
    code, _, err = run_cli(["build", dem, "-o", str(tmp_path / "rtin.lods"), "--mesher", "greedy",
                            "-q"], capsys)  # fmt: skip
    assert code != 0
    assert len(err.strip().splitlines()) == 1


def _triangles(path: Path) -> int:
    """Triangles of every stored mesh."""
    with closing(sqlite3.connect(path)) as db:
        rows = db.execute("SELECT data FROM terrain").fetchall()
    return sum(len(decode(bytes(d)).triangles) for (d,) in rows)


def test_a_build_begun_before_meshers_were_an_option_resumes_as_rtin() -> None:
    from lodscape.store.tileset import _identity

    old = {"schema": 1, "provenance": [], "options": {"error_texels": 1.0}}
    assert _identity(old) == _identity({**old, "options": {"error_texels": 1.0, "mesher": "rtin"}})
    assert _identity(old) != _identity(
        {**old, "options": {"error_texels": 1.0, "mesher": "greedy"}}
    )
