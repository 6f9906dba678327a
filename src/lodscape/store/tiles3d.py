"""A city as 3D Tiles 1.1 (glTF 2.0 binary content): what ``lodscape serve`` gives a Cesium
client for a tileset's stored buildings.

One tile per group of the city's R-tree leaves (their parents: about a hundred buildings each),
each a .glb with one primitive per material at the full level of detail, under a root whose
transform puts the city's east-north-up frame on the globe. glTF is y-up: positions are written
as (east, up, -north), which a 3D Tiles client turns back to z-up.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape.city.materials import material
from lodscape.city.model import CityModel

__all__ = ["city_tileset", "glb"]

_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_FLOAT = 5126
_UNSIGNED_INT = 5125


def glb(
    parts: list[tuple[str, NDArray[np.float32], NDArray[np.float32], NDArray[np.uint32]]],
) -> bytes:
    """A binary glTF of one mesh: per (material, positions (N, 3), normals (N, 3), triangles
    (M, 3)) one primitive; positions already y-up."""
    buffer = bytearray()
    views: list[dict[str, Any]] = []
    accessors: list[dict[str, Any]] = []
    primitives: list[dict[str, Any]] = []
    materials: list[dict[str, Any]] = []
    names: dict[str, int] = {}

    def add(data: bytes, target: int) -> int:
        while len(buffer) % 4:
            buffer.append(0)
        views.append(
            {"buffer": 0, "byteOffset": len(buffer), "byteLength": len(data), "target": target}
        )
        buffer.extend(data)
        return len(views) - 1

    for name, pos, nrm, tri in parts:
        if not len(tri):
            continue
        pos = np.ascontiguousarray(pos, np.float32)
        nrm = np.ascontiguousarray(nrm, np.float32)
        idx = np.ascontiguousarray(tri, np.uint32).ravel()
        pv = add(pos.tobytes(), _ARRAY_BUFFER)
        accessors.append(
            {
                "bufferView": pv,
                "componentType": _FLOAT,
                "count": len(pos),
                "type": "VEC3",
                "min": pos.min(axis=0).tolist(),
                "max": pos.max(axis=0).tolist(),
            }
        )
        nv = add(nrm.tobytes(), _ARRAY_BUFFER)
        accessors.append(
            {"bufferView": nv, "componentType": _FLOAT, "count": len(nrm), "type": "VEC3"}
        )
        iv = add(idx.tobytes(), _ELEMENT_ARRAY_BUFFER)
        accessors.append(
            {"bufferView": iv, "componentType": _UNSIGNED_INT, "count": len(idx), "type": "SCALAR"}
        )
        if name not in names:
            r, g, b = material(name).colour
            names[name] = len(materials)
            materials.append(
                {
                    "name": name,
                    "pbrMetallicRoughness": {
                        "baseColorFactor": [r, g, b, 1.0],
                        "metallicFactor": 0.0,
                        "roughnessFactor": 0.9,
                    },
                }
            )
        n = len(accessors)
        primitives.append(
            {
                "attributes": {"POSITION": n - 3, "NORMAL": n - 2},
                "indices": n - 1,
                "material": names[name],
                "mode": 4,
            }
        )
    while len(buffer) % 4:
        buffer.append(0)
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "lodscape"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": primitives}],
        "materials": materials,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": len(buffer)}],
    }
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(buffer)
    return (
        struct.pack("<4sII", b"glTF", 2, total)
        + struct.pack("<I4s", len(text), b"JSON")
        + text
        + struct.pack("<I4s", len(buffer), b"BIN\x00")
        + bytes(buffer)
    )


def _box(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> list[float]:
    """A 3D Tiles box bounding volume (centre, then the three half-axes) of an ENU box."""
    c = (lo + hi) / 2.0
    h = np.maximum((hi - lo) / 2.0, 0.01)
    return [*c.tolist(), h[0], 0.0, 0.0, 0.0, h[1], 0.0, 0.0, 0.0, h[2]]


#: Cesium's default maximum screen-space error, pixels: the group tiles' geometric errors are
#: set so that a client at this default swaps boxes for full buildings where lodscape's own
#: renderer does (``CityOptions.full_px``: the largest object covers 40 px).
CLIENT_SSE = 16.0


def _extent(
    parts: list[Any], lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The east-north-up box holding ``lo``..``hi`` and every vertex of glb ``parts`` (written
    y-up: (east, up, -north))."""
    for _mat, p, _n, _t in parts:
        enu = np.column_stack([p[:, 0], -p[:, 2], p[:, 1]]).astype(np.float64)
        lo = np.minimum(lo, enu.min(axis=0))
        hi = np.maximum(hi, enu.max(axis=0))
    return lo, hi


def _parts(model: CityModel, leaves: NDArray[np.int64], lod: int) -> list[Any]:
    """The glb parts (material, positions, normals, triangles) of some leaves at one level of
    detail, in glTF's y-up frame."""
    parts = []
    for (lv, mat), geo in model.geometry.items():
        if lv != lod or not len(geo.triangles) or not len(leaves):
            continue
        first, count = model.runs[(lv, mat)]
        flat = np.concatenate(
            [
                geo.triangles.ravel()[f : f + c]
                for f, c in zip(first[leaves], count[leaves], strict=True)
            ]
        )
        if not len(flat):
            continue
        used, local = np.unique(flat, return_inverse=True)
        p = geo.positions[used].astype(np.float32)
        n = geo.normals[used].astype(np.float32)
        # east-north-up to glTF's y-up: (e, n, u) -> (e, u, -n)
        parts.append(
            (
                mat,
                np.column_stack([p[:, 0], p[:, 2], -p[:, 1]]),
                np.column_stack([n[:, 0], n[:, 2], -n[:, 1]]),
                local.reshape(-1, 3).astype(np.uint32),
            )
        )
    return parts


def city_tileset(model: CityModel) -> tuple[dict[str, Any], list[bytes]]:
    """The city's buildings as a 3D Tiles tileset (``tileset.json`` content, referring to
    ``{i}.glb``) and the glb of each tile. Each group of R-tree leaves is a tile of box models
    that a client replaces by the full buildings (``REPLACE``) when their largest building
    would cover ``CityOptions().full_px`` pixels at its default screen-space error."""
    from lodscape.city.model import CityOptions

    tree = model.tree
    fanout = tree.fanout
    groups = max(1, -(-tree.leaves // fanout))
    contents: list[bytes] = []
    children: list[dict[str, Any]] = []
    per_px = CLIENT_SSE / CityOptions().full_px
    every = (np.full(3, np.inf), np.full(3, -np.inf))
    for g in range(groups):
        leaves = np.arange(g * fanout, min((g + 1) * fanout, tree.leaves))
        full = _parts(model, leaves, 0)
        if not full:
            continue
        coarse = _parts(model, leaves, 1)
        # the boxes hold what is drawn: the leaves' boxes and every vertex of both levels
        # (roofs and box models may reach past the footprints' boxes)
        boxes = tree.levels[0][leaves]
        lo, hi = _extent(full + coarse, boxes[:, :3].min(axis=0), boxes[:, 3:].max(axis=0))
        fine = {
            "boundingVolume": {"box": _box(lo, hi)},
            "geometricError": 0.0,
            "content": {"uri": f"{len(contents)}.glb"},
        }
        contents.append(glb(full))
        every = (np.minimum(every[0], lo), np.maximum(every[1], hi))
        if not coarse:
            children.append(fine)
            continue
        children.append(
            {
                "boundingVolume": {"box": _box(lo, hi)},
                "geometricError": float(model.leaf_size[leaves].max() * per_px),
                "refine": "REPLACE",
                "content": {"uri": f"{len(contents)}.glb"},
                "children": [fine],
            }
        )
        contents.append(glb(coarse))
    all_boxes = tree.levels[0]
    lo = np.minimum(all_boxes[:, :3].min(axis=0), every[0])
    hi = np.maximum(all_boxes[:, 3:].max(axis=0), every[1])
    to_ecef = np.eye(4)
    to_ecef[:3, :3] = model.frame.basis.T
    to_ecef[:3, 3] = model.frame.origin
    tileset = {
        "asset": {"version": "1.1", "generator": "lodscape"},
        "geometricError": float(np.linalg.norm(hi - lo)),
        "root": {
            # column-major, as 3D Tiles stores matrices
            "transform": to_ecef.T.ravel().tolist(),
            "boundingVolume": {"box": _box(lo, hi)},
            "geometricError": max(
                [float(np.linalg.norm(hi - lo)) / 8.0] + [c["geometricError"] for c in children]
            ),
            "refine": "ADD",
            "children": children,
        },
    }
    return tileset, contents
