"""quantized-mesh-1.0, the terrain tile format Cesium streams: encode and decode, vectorised.

Layout (little-endian), after https://github.com/CesiumGS/quantized-mesh:
- header, 88 bytes: centre (3 × f64, ECEF), min/max height (2 × f32), bounding sphere centre and
  radius (4 × f64), horizon occlusion point (3 × f64, in the ellipsoid's scaled space);
- vertex count (u32), then u, v and height (u16 each, zig-zag delta coded) in 0..32767;
  u runs west → east and v south → north, linear in longitude and latitude over the tile;
- triangle count (u32, after padding to the index width), indices coded by high-water mark,
  16-bit up to 65,536 vertices and 32-bit above;
- west, south, east and north edge vertex lists (count u32, then plain indices);
- extensions: id (u8), length (u32), bytes; id 1 is oct-encoded vertex normals (2 × u8 each).

Decoding does its index and delta arithmetic modulo 2^16 (or 2^32), as Cesium's typed arrays do,
so it also reads encoders that do not put vertices in first-use order.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lodscape.errors import LodscapeError
from lodscape.geo.frames import WGS84_A, WGS84_B, geodetic_to_ecef

__all__ = [
    "NORMALS_EXTENSION",
    "QUANTIZED_MAX",
    "QuantizedMesh",
    "QuantizedMeshError",
    "decode",
    "encode",
    "oct_decode",
    "oct_encode",
    "quantize",
    "ungzip",
]

#: Largest quantized u, v or height.
QUANTIZED_MAX = 32767
#: Extension id of oct-encoded per-vertex normals.
NORMALS_EXTENSION = 1
_HEADER = struct.Struct("<3d2f4d3d")
#: Smallest cosine term of the horizon point taken as exact: beyond it, 1/_LIMB scaled radii.
_LIMB = 1e-6
F64 = NDArray[np.float64]
U16 = NDArray[np.uint16]
U32 = NDArray[np.uint32]


class QuantizedMeshError(LodscapeError, ValueError):
    """Bytes that are not a well-formed quantized-mesh-1.0 tile."""


@dataclass(frozen=True, eq=False)
class QuantizedMesh:
    """One tile, decoded: quantized vertices, triangles, edges, header and optional normals."""

    center: F64
    min_height: float
    max_height: float
    sphere_center: F64
    sphere_radius: float
    horizon_occlusion: F64
    u: U16
    v: U16
    h: U16
    #: (M, 3) vertex indices, counter-clockwise seen from above.
    triangles: U32
    west: U32
    south: U32
    east: U32
    north: U32
    #: (N, 2) oct-encoded unit normals, or None.
    normals: NDArray[np.uint8] | None = None

    @property
    def vertex_count(self) -> int:
        return int(self.u.size)

    def positions(
        self, west: float, south: float, east: float, north: float
    ) -> tuple[F64, F64, F64]:
        """Longitude, latitude (degrees) and height (metres) of every vertex, given the tile's
        geographic rectangle."""
        s = 1.0 / QUANTIZED_MAX
        u, v, h = (a.astype(np.float64) * s for a in (self.u, self.v, self.h))
        return (
            west + (east - west) * u,
            south + (north - south) * v,
            self.min_height + (self.max_height - self.min_height) * h,
        )


def quantize(values: F64, lo: float, hi: float) -> U16:
    """Values in lo..hi to 0..32767, rounded; the ends map exactly to 0 and 32767."""
    span = hi - lo
    if span <= 0.0:
        return np.zeros(np.shape(values), dtype=np.uint16)
    q = np.rint((np.asarray(values, np.float64) - lo) / span * QUANTIZED_MAX)
    return np.clip(q, 0, QUANTIZED_MAX).astype(np.uint16)


def oct_encode(normals: F64) -> NDArray[np.uint8]:
    """Unit vectors (N, 3) to Cesium's 2-byte octahedral encoding (N, 2)."""
    n = np.asarray(normals, dtype=np.float64)
    p = n[:, :2] / np.maximum(np.abs(n).sum(axis=1, keepdims=True), 1e-300)
    neg = n[:, 2] < 0.0
    sign = np.where(p >= 0.0, 1.0, -1.0)
    folded = (1.0 - np.abs(p[:, ::-1])) * sign
    p = np.where(neg[:, None], folded, p)
    out: NDArray[np.uint8] = np.rint((np.clip(p, -1.0, 1.0) * 0.5 + 0.5) * 255.0).astype(np.uint8)
    return out


def oct_decode(encoded: NDArray[np.uint8]) -> F64:
    """Cesium's 2-byte octahedral encoding (N, 2) back to unit vectors (N, 3)."""
    p = np.asarray(encoded, dtype=np.float64) / 255.0 * 2.0 - 1.0
    z = 1.0 - np.abs(p).sum(axis=1)
    neg = z < 0.0
    sign = np.where(p >= 0.0, 1.0, -1.0)
    p = np.where(neg[:, None], (1.0 - np.abs(p[:, ::-1])) * sign, p)
    v = np.column_stack([p, z])
    out: F64 = v / np.linalg.norm(v, axis=1, keepdims=True)
    return out


def _zigzag_deltas(values: U16) -> bytes:
    d = np.diff(np.concatenate([np.zeros(1, np.int32), values.astype(np.int32)]))
    z = (np.left_shift(d, 1) ^ np.right_shift(d, 31)) & 0xFFFF
    return bytes(z.astype("<u2").tobytes())


def _unzigzag(codes: U16) -> U16:
    c = codes.astype(np.int64)
    d = (c >> 1) ^ -(c & 1)
    out: U16 = (np.cumsum(d) & 0xFFFF).astype(np.uint16)
    return out


def _horizon_occlusion(ecef: F64, sphere_center: F64, min_height: float = 0.0) -> F64:
    """Cesium's horizon-culling point (EllipsoidalOccluder): in the ellipsoid's scaled space,
    along the sphere centre's direction, far enough that every vertex is behind its horizon.
    A tile reaching below 0 m (``min_height`` < 0) is tested by Cesium against the ellipsoid
    shrunk by that much (``isScaledSpacePointVisiblePossiblyUnderEllipsoid``): its point is in
    that ellipsoid's scaled space."""
    shrink = min_height if min_height < 0.0 and -min_height < WGS84_B else 0.0
    scale = np.array([1.0 / (WGS84_A + shrink), 1.0 / (WGS84_A + shrink), 1.0 / (WGS84_B + shrink)])
    direction = sphere_center * scale
    length = float(np.linalg.norm(direction))
    if not length > 1e-9:  # a tile round the whole Earth: no direction to look from
        return np.full(3, np.nan)
    direction = direction / length
    p = ecef * scale
    mag = np.linalg.norm(p, axis=1)
    unit = p / mag[:, None]
    mag = np.maximum(mag, 1.0)
    cos_a = unit @ direction
    sin_a = np.linalg.norm(np.cross(unit, direction), axis=1)
    cos_b = 1.0 / mag
    sin_b = np.sqrt(mag * mag - 1.0) * cos_b
    denom = cos_a * cos_b - sin_a * sin_b
    if np.all(denom > _LIMB):
        magnitude = float(np.max(1.0 / denom))
    elif np.all(denom > -1e-9):
        # vertices on the limb seen from the point (a tile a hemisphere wide, lying on the
        # ellipsoid): the exact point is at infinity; far along the direction stands in
        magnitude = 1.0 / _LIMB
    else:
        # more than a hemisphere (level 0): no point is behind the horizon of every camera
        # that can see a vertex; NaN makes Cesium skip the test (its comparisons fail) rather
        # than cull the Earth from the side opposite the point
        magnitude = float("nan")
    result: F64 = direction * magnitude
    return result


def encode(
    lon: F64,
    lat: F64,
    height: F64,
    triangles: NDArray[np.integer],
    rect: tuple[float, float, float, float],
    *,
    normals: F64 | None = None,
) -> bytes:
    """One tile's bytes. ``rect`` is the tile's (west, south, east, north) in degrees; vertices
    on its sides must lie exactly on them (they become the edge lists). ``normals`` (N, 3, ECEF
    unit vectors) adds the oct-encoded normals extension. Vertices are written in the order
    triangles first use them, which the high-water-mark index code needs."""
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = int(np.asarray(lon).size)
    if tri.size == 0 or n < 3:
        raise ValueError("Expected at least one triangle")
    if tri.min() < 0 or tri.max() >= n:
        raise ValueError(f"Expected triangle indices in 0..{n - 1}")
    lon = np.asarray(lon, np.float64).ravel()
    lat = np.asarray(lat, np.float64).ravel()
    height = np.asarray(height, np.float64).ravel()
    # counter-clockwise seen from above (east right, north up), whatever the caller's winding
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    cw = (lon[b] - lon[a]) * (lat[c] - lat[a]) - (lat[b] - lat[a]) * (lon[c] - lon[a]) < 0.0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    # first-use order: old index of the k-th vertex first met in the triangle list
    flat = tri.ravel()
    _, first = np.unique(flat, return_index=True)
    order = flat[np.sort(first)]
    if order.size != n:
        raise ValueError("Expected every vertex to be used by a triangle")
    new = np.empty(n, dtype=np.int64)
    new[order] = np.arange(n)
    tri = new[tri]
    lon, lat, height = lon[order], lat[order], height[order]

    west, south, east, north = rect
    hmin, hmax = float(height.min()), float(height.max())
    u = quantize(lon, west, east)
    v = quantize(lat, south, north)
    h = quantize(height, hmin, hmax)
    # the header from the positions the decoder will see, so bounds hold for what is drawn
    s = 1.0 / QUANTIZED_MAX
    ecef = geodetic_to_ecef(
        west + (east - west) * u * s,
        south + (north - south) * v * s,
        hmin + (hmax - hmin) * h * s,
    ).reshape(-1, 3)
    lo, hi = ecef.min(axis=0), ecef.max(axis=0)
    center = (lo + hi) / 2.0
    radius = float(np.linalg.norm(ecef - center, axis=1).max())
    # the minimum height as the header stores it (float32): what Cesium shrinks by
    occlusion = _horizon_occlusion(ecef, center, float(np.float32(hmin)))

    out = [
        _HEADER.pack(*center, hmin, hmax, *center, radius, *occlusion),
        struct.pack("<I", n),
        _zigzag_deltas(u),
        _zigzag_deltas(v),
        _zigzag_deltas(h),
    ]
    wide = n > 65536
    itype = "<u4" if wide else "<u2"
    offset = _HEADER.size + 4 + 6 * n
    if wide and offset % 4:
        out.append(b"\0" * (4 - offset % 4))
    flat = tri.ravel()
    # high-water mark: each index is coded as (highest so far + 1) − index, 0 for a new one
    highest = np.concatenate([[0], np.maximum.accumulate(flat)[:-1] + 1])
    out.append(struct.pack("<I", tri.shape[0]))
    out.append((highest - flat).astype(itype).tobytes())
    for side in (u == 0, v == 0, u == QUANTIZED_MAX, v == QUANTIZED_MAX):
        idx = np.flatnonzero(side)
        out.append(struct.pack("<I", idx.size))
        out.append(idx.astype(itype).tobytes())
    if normals is not None:
        enc = oct_encode(np.asarray(normals, np.float64).reshape(-1, 3)[order])
        out.append(struct.pack("<BI", NORMALS_EXTENSION, enc.nbytes))
        out.append(enc.tobytes())
    return b"".join(out)


def ungzip(data: bytes) -> bytes:
    """The tile's bytes without their gzip wrapping, if they have one."""
    if data[:2] != b"\x1f\x8b":
        return data
    try:
        return gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as exc:
        raise QuantizedMeshError(f"gzipped tile does not inflate ({exc})") from None


def decode(data: bytes) -> QuantizedMesh:
    """Read one tile's bytes, gzipped or not; anything malformed raises QuantizedMeshError in
    one line."""
    try:
        plain = ungzip(data)
    except QuantizedMeshError as gzipped:
        # a plain tile whose header starts with gzip's two magic bytes (its centre's lowest
        # bytes: one tile in 65,536) is read as it is
        try:
            return _decode_plain(data)
        except QuantizedMeshError:
            raise gzipped from None
    return _decode_plain(plain)


def _decode_plain(data: bytes) -> QuantizedMesh:
    buf = memoryview(data)
    try:
        head = _HEADER.unpack_from(buf, 0)
        pos = _HEADER.size
        (n,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        if n < 3 or pos + 6 * n > len(buf):
            raise QuantizedMeshError(f"vertex count {n} does not fit {len(buf)} bytes")
        codes = np.frombuffer(buf, dtype="<u2", count=3 * n, offset=pos).reshape(3, n)
        u, v, h = (_unzigzag(c) for c in codes)
        pos += 6 * n
        wide = n > 65536
        size = 4 if wide else 2
        if pos % size:
            pos += size - pos % size
        (m,) = struct.unpack_from("<I", buf, pos)
        pos += 4
        if pos + 3 * m * size > len(buf):
            raise QuantizedMeshError(f"triangle count {m} does not fit {len(buf)} bytes")
        code = np.frombuffer(buf, dtype="<u4" if wide else "<u2", count=3 * m, offset=pos)
        pos += 3 * m * size
        code64 = code.astype(np.int64)
        highest = np.cumsum(code64 == 0) - (code64 == 0)
        mask = 0xFFFFFFFF if wide else 0xFFFF
        tri = ((highest - code64) & mask).astype(np.uint32).reshape(-1, 3)
        edges = []
        for _ in range(4):
            (k,) = struct.unpack_from("<I", buf, pos)
            pos += 4
            if pos + k * size > len(buf):
                raise QuantizedMeshError(f"edge list of {k} does not fit {len(buf)} bytes")
            e = np.frombuffer(buf, dtype="<u4" if wide else "<u2", count=k, offset=pos)
            edges.append(e.astype(np.uint32))
            pos += k * size
        normals = None
        while pos + 5 <= len(buf):
            ext, length = struct.unpack_from("<BI", buf, pos)
            pos += 5
            if pos + length > len(buf):
                raise QuantizedMeshError(f"extension {ext} of {length} bytes is cut short")
            if ext == NORMALS_EXTENSION:
                if length != 2 * n:
                    raise QuantizedMeshError(f"normals extension of {length} bytes for {n}")
                normals = np.frombuffer(buf, np.uint8, count=2 * n, offset=pos).reshape(n, 2)
            pos += length
    except struct.error:
        raise QuantizedMeshError(f"quantized-mesh tile cut short ({len(data)} bytes)") from None
    if tri.size and int(tri.max()) >= n:
        raise QuantizedMeshError(f"triangle index {int(tri.max())} beyond {n} vertices")
    if any(e.size and int(e.max()) >= n for e in edges):
        raise QuantizedMeshError(f"edge vertex beyond {n} vertices")
    if max(int(u.max()), int(v.max()), int(h.max())) > QUANTIZED_MAX:
        raise QuantizedMeshError("quantized coordinate above 32767")
    return QuantizedMesh(
        center=np.array(head[0:3]),
        min_height=float(head[3]),
        max_height=float(head[4]),
        sphere_center=np.array(head[5:8]),
        sphere_radius=float(head[8]),
        horizon_occlusion=np.array(head[9:12]),
        u=u,
        v=v,
        h=h,
        triangles=tri,
        west=edges[0],
        south=edges[1],
        east=edges[2],
        north=edges[3],
        normals=None if normals is None else normals.copy(),
    )
