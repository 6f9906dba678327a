"""quantized-mesh-1.0: our encoder and decoder against each other and against the PyPI package
quantized-mesh-encoder, a reference from outside the project."""

from __future__ import annotations

import io

import numpy as np
import pytest

from _synthetic import fbm_heights
from lodscape.geo.frames import geodetic_to_ecef
from lodscape.geo.tiles import Tile, bounds, merc_to_lonlat
from lodscape.store.quantized_mesh import (
    QUANTIZED_MAX,
    QuantizedMeshError,
    decode,
    encode,
    oct_decode,
    oct_encode,
)
from lodscape.terrain.mesh import grid_coordinates
from lodscape.terrain.rtin import rtin

TILE = Tile(1093, 1607, 12)


def _tile_mesh(max_error: float = 3.0) -> tuple[np.ndarray, ...]:
    """An RTIN mesh of a real-looking 65² tile grid: lon, lat, height, triangles."""
    h = fbm_heights(65, seed=4).astype(np.float64)
    v, t = rtin(h, max_error)
    xs, ys = grid_coordinates(TILE.z, TILE.x, TILE.y, 64)

    lon, lat = merc_to_lonlat(xs[v[:, 0]], ys[v[:, 1]])
    return lon, lat, h[v[:, 1], v[:, 0]], t


def _rect() -> tuple[float, float, float, float]:
    b = bounds(TILE)
    return b.left, b.bottom, b.right, b.top


def _same_triangles(dlon, dlat, dtri, lon, lat, tri) -> bool:
    """The decoded triangles are the original ones: vertices matched to their nearest original."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(np.column_stack([lon, lat])).query(np.column_stack([dlon, dlat]))
    assert dist.max() < 1e-5
    mapped = idx[np.asarray(dtri, dtype=np.int64)]
    return {frozenset(t) for t in mapped.tolist()} == {frozenset(t) for t in tri.tolist()}


def test_round_trip_keeps_vertices_within_quantisation_and_the_triangles() -> None:
    lon, lat, h, tri = _tile_mesh()
    west, south, east, north = _rect()
    qm = decode(encode(lon, lat, h, tri, _rect()))
    assert qm.vertex_count == lon.size
    dlon, dlat, dh = qm.positions(west, south, east, north)
    step = np.array([east - west, north - south, h.max() - h.min()]) / QUANTIZED_MAX
    order = np.lexsort((lat, lon))
    back = np.lexsort((dlat, dlon))
    got = np.column_stack([dlon[back], dlat[back], dh[back]])
    want = np.column_stack([lon[order], lat[order], h[order]])
    assert np.all(np.abs(got - want) <= step / 2 + 1e-9)
    assert _same_triangles(dlon, dlat, qm.triangles, lon, lat, tri)
    # counter-clockwise seen from above, as the format requires
    p = np.column_stack([dlon, dlat])[qm.triangles.astype(np.int64)]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    assert np.all(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0)


def test_edges_header_and_normals() -> None:
    lon, lat, h, tri = _tile_mesh()
    west, south, east, north = _rect()
    normals = np.tile(np.array([[0.0, 0.6, 0.8]]), (lon.size, 1))
    qm = decode(encode(lon, lat, h, tri, _rect(), normals=normals))
    assert np.all(qm.u[qm.west] == 0)
    assert np.all(qm.v[qm.south] == 0)
    assert np.all(qm.u[qm.east] == QUANTIZED_MAX)
    assert np.all(qm.v[qm.north] == QUANTIZED_MAX)
    assert qm.west.size + qm.east.size + qm.south.size + qm.north.size >= 8
    dlon, dlat, dh = qm.positions(west, south, east, north)
    ecef = geodetic_to_ecef(dlon, dlat, dh)
    assert np.linalg.norm(ecef - qm.sphere_center, axis=1).max() <= qm.sphere_radius + 1e-6
    assert qm.min_height == pytest.approx(h.min(), abs=1e-3)
    assert qm.max_height == pytest.approx(h.max(), abs=1e-3)
    assert np.isfinite(qm.horizon_occlusion).all()
    assert qm.normals is not None
    np.testing.assert_allclose(oct_decode(qm.normals), normals, atol=0.01)


def test_oct_encoding_round_trips_every_direction() -> None:
    rng = np.random.default_rng(0)
    n = rng.normal(size=(2000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # 8 bits a component: within about a degree everywhere on the sphere
    back = oct_decode(oct_encode(n))
    assert np.degrees(np.arccos(np.clip((back * n).sum(axis=1), -1, 1))).max() < 1.5


def test_we_decode_what_the_reference_encoder_writes() -> None:
    qme = pytest.importorskip("quantized_mesh_encoder")
    lon, lat, h, tri = _tile_mesh()
    positions = np.column_stack([lon, lat, h]).astype(np.float32)
    buf = io.BytesIO()
    ext = qme.VertexNormalsExtension(positions=positions, indices=tri.astype(np.uint32))
    qme.encode(buf, positions, tri.astype(np.uint32), bounds=_rect(), extensions=[ext])
    qm = decode(buf.getvalue())
    west, south, east, north = _rect()
    dlon, dlat, dh = qm.positions(west, south, east, north)
    # the reference truncates where we round: within one quantisation step (and float32 input)
    step = np.array([east - west, north - south, h.max() - h.min()]) / QUANTIZED_MAX
    got = np.column_stack([dlon, dlat, dh])
    want = np.column_stack([lon, lat, h])  # the reference keeps the caller's vertex order
    assert np.all(np.abs(got - want) <= step * 1.01 + np.array([1e-5, 1e-5, 1e-3]))
    assert _same_triangles(dlon, dlat, qm.triangles, lon, lat, tri)
    assert qm.normals is not None
    assert qm.normals.shape == (lon.size, 2)
    up = geodetic_to_ecef(lon, lat, 1.0) - geodetic_to_ecef(lon, lat, 0.0)
    # fairly flat terrain: the reference's normals point roughly up
    assert np.median((oct_decode(qm.normals) * up).sum(axis=1)) > 0.8


def test_our_bytes_decode_with_the_reference_header_layout() -> None:
    """The first 88 bytes are the header in the reference's layout: its own tile and ours agree
    on the centre of the same mesh."""
    qme = pytest.importorskip("quantized_mesh_encoder")
    lon, lat, h, tri = _tile_mesh()
    ours = decode(encode(lon, lat, h, tri, _rect()))
    buf = io.BytesIO()
    qme.encode(
        buf,
        np.column_stack([lon, lat, h]).astype(np.float32),
        tri.astype(np.uint32),
        bounds=_rect(),
    )
    theirs = decode(buf.getvalue())
    np.testing.assert_allclose(ours.center, theirs.center, atol=2.0)
    assert abs(ours.sphere_radius - theirs.sphere_radius) < 0.05 * theirs.sphere_radius


@pytest.mark.parametrize("cut", [0, 10, 88, 95, 200, -40, -3])
def test_truncated_tiles_fail_in_one_line(cut: int) -> None:
    lon, lat, h, tri = _tile_mesh()
    data = encode(lon, lat, h, tri, _rect(), normals=np.tile([0.0, 0.0, 1.0], (lon.size, 1)))
    with pytest.raises(QuantizedMeshError):
        decode(data[:cut])


def test_garbage_fails_cleanly() -> None:
    rng = np.random.default_rng(1)
    failures = 0
    for size in (0, 50, 100, 1000, 5000):
        try:
            decode(rng.bytes(size))
        except QuantizedMeshError:
            failures += 1
    assert failures == 5


def test_thirty_two_bit_indices_above_65536_vertices() -> None:
    n = 257
    h = fbm_heights(n, seed=9).astype(np.float64)
    v, t = rtin(h, 0.0)
    assert len(v) > 65536
    west, south, east, north = _rect()
    lon = west + (east - west) * v[:, 0] / (n - 1)
    lat = north - (north - south) * v[:, 1] / (n - 1)
    qm = decode(encode(lon, lat, h[v[:, 1], v[:, 0]], t, _rect()))
    assert qm.vertex_count == len(v)
    assert len(qm.triangles) == len(t)


def test_gzipped_tiles_decode_and_broken_gzip_fails_cleanly() -> None:
    import gzip

    lon, lat, h, tri = _tile_mesh()
    data = encode(lon, lat, h, tri, _rect())
    plain, zipped = decode(data), decode(gzip.compress(data))
    assert np.array_equal(plain.triangles, zipped.triangles)
    assert np.array_equal(plain.h, zipped.h)
    with pytest.raises(QuantizedMeshError, match="gzip"):
        decode(gzip.compress(data)[:40])


def test_a_plain_tile_that_starts_like_gzip_still_decodes() -> None:
    """The header's first bytes are the centre's lowest: one plain tile in 65,536 starts with
    gzip's magic (1f 8b). It decodes as the plain tile it is; a broken gzipped tile still
    raises in one line."""
    import gzip

    from lodscape.store.quantized_mesh import QuantizedMeshError, decode, encode

    lon, lat, h = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 2.0])
    data = bytearray(encode(lon, lat, h, np.array([[0, 1, 2]], np.int32), (0.0, 0.0, 1.0, 1.0)))
    data[0:2] = b"\x1f\x8b"
    assert decode(bytes(data)).vertex_count == 3
    broken = gzip.compress(bytes(data))[:40]
    with pytest.raises(QuantizedMeshError, match="does not inflate"):
        decode(broken)


def _cesium_visible(point: np.ndarray, camera: np.ndarray, min_height: float) -> np.ndarray:
    """CesiumJS's EllipsoidalOccluder.isScaledSpacePointVisiblePossiblyUnderEllipsoid, for
    cameras (N, 3) and one scaled-space point, written here from its published algorithm."""
    from lodscape.geo.frames import WGS84_A, WGS84_B

    s = min_height if min_height < 0.0 and -min_height < WGS84_B else 0.0
    cv = camera / np.array([WGS84_A + s, WGS84_A + s, WGS84_B + s])
    vh2 = (cv * cv).sum(axis=1) - 1.0
    vt = point[None, :] - cv
    vt_dot_vc = -(vt * cv).sum(axis=1)
    occluded = np.where(
        vh2 < 0.0, vt_dot_vc > 0.0, (vt_dot_vc > vh2) & (vt_dot_vc**2 / (vt * vt).sum(axis=1) > vh2)
    )
    return np.asarray(~occluded)


@pytest.mark.parametrize("depth", [0.0, 40.0, 400.0])
def test_cesium_sees_a_tile_below_sea_level_wherever_a_vertex_shows(depth: float) -> None:
    """A tile whose vertices lie ``depth`` metres below the ellipsoid (a sea floor, the Dead
    Sea): from cameras all around, wherever Cesium's own test (the ellipsoid shrunk by the tile's
    minimum height) sees one of its vertices, it sees the tile's horizon-occlusion point too."""
    from lodscape.store.quantized_mesh import decode, encode

    lon, lat, h, tri = _tile_mesh()
    h = h - h.max() - depth if depth else h
    west, south, east, north = _rect()
    qm = decode(encode(lon, lat, h, tri, _rect()))
    dlon, dlat, dh = qm.positions(west, south, east, north)
    vertices = geodetic_to_ecef(dlon, dlat, dh).reshape(-1, 3)
    rng = np.random.default_rng(3)
    # cameras from 10 m to 2,000 km over points within 30° of the tile
    clon = (west + east) / 2 + rng.uniform(-30, 30, 4000)
    clat = np.clip((south + north) / 2 + rng.uniform(-30, 30, 4000), -89, 89)
    cams = geodetic_to_ecef(clon, clat, 10.0 ** rng.uniform(1, 6.3, 4000)).reshape(-1, 3)
    from lodscape.geo.frames import WGS84_A, WGS84_B

    s = qm.min_height if qm.min_height < 0 else 0.0
    scale = np.array([WGS84_A + s, WGS84_A + s, WGS84_B + s])
    seen = np.zeros(len(cams), bool)
    for v in vertices[:: max(1, len(vertices) // 200)]:
        seen |= _cesium_visible(v / scale, cams, qm.min_height)
    point = _cesium_visible(qm.horizon_occlusion, cams, qm.min_height)
    assert seen.any()
    assert not (seen & ~point).any(), int((seen & ~point).sum())
