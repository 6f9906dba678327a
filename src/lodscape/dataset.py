"""Vision datasets: many camera poses rendered in one process, each written as the picture,
metric depth, surface normals, a semantic mask and the camera in three conventions.

    lodscape render DEM.tif --poses poses.csv --dataset out/

``poses.csv`` has a header and a row per pose: ``lon, lat, alt`` (metres above the
ellipsoid) and optionally ``heading, pitch, roll`` (degrees, as everywhere in lodscape), ``fov``
(vertical, degrees) and ``name`` (the files' stem; default the row number). ``out/`` gets:

- ``images/NAME.png``: RGB.
- ``depth/NAME.npy``: float32 (H, W), metres along the optical axis (OpenCV's z); where no
  measured surface is (sky, and the no-data ellipsoid drawn where the terrain has none) the
  ``depth_invalid`` value: ``inf`` by default, ``0`` (Open3D, TUM, ScanNet; nerfstudio masks
  depth ≤ 0) or ``nan``.
- ``normals/NAME.npy``: float32 (H, W, 3), unit surface normals in the camera's OpenCV frame
  (x right, y down, z ahead), facing the camera; 0 where no measured surface is.
- ``mask/NAME.png``: uint8 (H, W), 255 where a measured surface is drawn, 0 elsewhere (sky,
  the no-data ellipsoid): nerfstudio's ``mask_path``.
- ``semantic/NAME.png``: uint8 (H, W) labels, the legend in ``frame.json``
  (``render.labels.LABELS``: sky, terrain, water, building, road, vegetation, street furniture,
  and 255 where the ground is the no-data ellipsoid).
- ``cameras/NAME.json``: OpenCV: ``K`` (pixel centres at whole numbers: cx = (W - 1) / 2),
  ``R`` and ``t`` mapping world to camera (x_cam = R·x_world + t), zero distortion.
- ``colmap/cameras.txt``, ``images.txt``, ``points3D.txt``: COLMAP's text model (PINHOLE;
  COLMAP puts pixel centres at half-integers, so cx = W / 2; quaternion w, x, y, z of R).
- ``transforms.json``: NeRF (instant-ngp / nerfstudio): per frame ``transform_matrix``, the
  camera-to-world matrix in the OpenGL convention (x right, y up, z backwards), and the
  intrinsics ``fl_x, fl_y, cx, cy, w, h`` (cx = W / 2: rays through pixel centres i + 0.5);
  instant-ngp's ``scale`` and ``offset`` (world × scale + offset puts the cameras and the
  ground they see in its unit cube) and ``aabb_scale`` (a power of two: the far ground seen).
- ``frame.json``: the world frame: local east-north-up metres from an origin (lon, lat,
  ellipsoidal height; default the data's centre at height 0, or the poses' centre where the
  data spans more than 10° or has no bounds, as a server may), the legend, the conventions.

The folder is written under a temporary name and renamed when complete: a failure leaves
nothing.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lodscape._tmp import temp_beside
from lodscape.errors import CameraError, LodscapeError
from lodscape.geo.frames import enu_basis, geodetic_to_ecef
from lodscape.lod.camera import Camera
from lodscape.render.labels import LABELS

__all__ = [
    "DEPTH_INVALID",
    "Origin",
    "Pose",
    "PoseMatrices",
    "conventions",
    "ngp_box",
    "read_poses",
    "write_dataset",
]

#: What depth holds where no measured surface is: its name in ``--depth-invalid`` and value.
DEPTH_INVALID = {"inf": np.inf, "0": 0.0, "nan": np.nan}

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
#: OpenGL's view axes (x right, y up, z backwards) to OpenCV's (x right, y down, z ahead).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Pose:
    name: str
    camera: Camera


@dataclass(frozen=True)
class Origin:
    """The dataset's world frame: east, north, up metres from (lon, lat, height)."""

    lon: float
    lat: float
    height: float = 0.0

    def to_local(self, ecef: NDArray[np.float64]) -> NDArray[np.float64]:
        """ECEF points (..., 3) to this frame's east-north-up metres."""
        o = geodetic_to_ecef(self.lon, self.lat, self.height)
        out: NDArray[np.float64] = (np.asarray(ecef, np.float64) - o) @ self.basis.T
        return out

    @property
    def basis(self) -> NDArray[np.float64]:
        """Rows east, north, up (ECEF unit vectors)."""
        b: NDArray[np.float64] = enu_basis(self.lon, self.lat)
        return b


@dataclass(frozen=True)
class PoseMatrices:
    """One camera in the dataset's frame, in every convention written."""

    #: OpenCV intrinsics (pixel centres at whole numbers).
    K: NDArray[np.float64]
    #: World (local ENU) to OpenCV camera: x_cam = R @ x_world + t.
    R: NDArray[np.float64]
    t: NDArray[np.float64]
    #: The camera's centre in the world frame.
    centre: NDArray[np.float64]
    #: NeRF's camera-to-world (OpenGL camera axes), 4×4.
    c2w_gl: NDArray[np.float64]
    #: COLMAP: quaternion (w, x, y, z) of R, and its intrinsics (pixel centres at +0.5).
    qvec: NDArray[np.float64]
    colmap_params: tuple[float, float, float, float]


def conventions(camera: Camera, origin: Origin) -> PoseMatrices:
    """``camera`` in the dataset's conventions (see the module)."""
    w, h = camera.width, camera.height
    f = camera.scale  # pixels: square pixels, so fx = fy
    K = np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
    r_gl = camera.rotation @ origin.basis.T  # world (ENU) → GL view
    R = _GL_TO_CV @ r_gl
    centre = origin.to_local(camera.position)
    t = -R @ centre
    c2w = np.eye(4)
    c2w[:3, :3] = r_gl.T
    c2w[:3, 3] = centre
    return PoseMatrices(K, R, t, centre, c2w, _quaternion(R), (f, f, w / 2.0, h / 2.0))


def _quaternion(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method)."""
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    out = np.array(q, np.float64)
    out /= np.linalg.norm(out)
    return out if out[0] >= 0.0 else -out


def read_poses(
    path: str | os.PathLike[str], width: int, height: int, fov: float = 60.0
) -> list[Pose]:
    """The poses of a CSV file (see the module); a one-line error names a bad file or row."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise LodscapeError(f"{p}: no such poses file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LodscapeError(f"{p}: cannot read the poses ({exc})") from None
    rows = list(csv.reader(line for line in text.splitlines() if line.strip()))
    if not rows:
        raise LodscapeError(f"{p}: no poses (an empty file)")
    head = [c.strip().lower() for c in rows[0]]
    missing = [c for c in ("lon", "lat", "alt") if c not in head]
    if missing:
        raise LodscapeError(
            f"{p}: the header needs lon, lat and alt (and may have heading, pitch, roll, fov, "
            f"name); missing {', '.join(missing)}"
        )
    known = {"lon", "lat", "alt", "heading", "pitch", "roll", "fov", "name"}
    unknown = [c for c in head if c not in known]
    if unknown:
        raise LodscapeError(f"{p}: unknown column {unknown[0]!r}")
    if len(set(head)) != len(head):
        raise LodscapeError(f"{p}: a column is named twice")
    defaults = {"heading": 0.0, "pitch": -30.0, "roll": 0.0, "fov": fov}
    poses: list[Pose] = []
    names: set[str] = set()
    for n, row in enumerate(rows[1:], start=2):
        if len(row) != len(head):
            raise LodscapeError(f"{p}: line {n} has {len(row)} values for {len(head)} columns")
        cell = dict(zip(head, (c.strip() for c in row), strict=True))
        try:
            v = {k: float(cell[k]) for k in cell if k != "name"}
        except ValueError:
            raise LodscapeError(f"{p}: line {n}: a value is not a number") from None
        v = {**defaults, **v}
        name = cell.get("name") or f"{len(poses):05d}"
        if not _NAME.match(name):
            raise LodscapeError(
                f"{p}: line {n}: name {name!r} must be letters, digits, '.', '_' or '-'"
            )
        if name in names:
            raise LodscapeError(f"{p}: line {n}: the name {name!r} is used twice")
        names.add(name)
        try:
            cam = Camera(
                v["lon"],
                v["lat"],
                v["alt"],
                heading=v["heading"],
                pitch=v["pitch"],
                roll=v["roll"],
                fov_y=v["fov"],
                width=width,
                height=height,
            )
        except CameraError as exc:
            raise LodscapeError(f"{p}: line {n}: {exc}") from None
        poses.append(Pose(name, cam))
    if not poses:
        raise LodscapeError(f"{p}: no poses (a header and no rows)")
    return poses


def write_dataset(
    scene: Any,
    poses: Sequence[Pose],
    out: str | os.PathLike[str],
    origin: Origin | None = None,
    progress: Callable[[int, int], None] | None = None,
    *,
    depth_invalid: str = "inf",
) -> Origin:
    """Render every pose of ``scene`` (``Scene.capture``) into the folder ``out`` (see the
    module; written under a temporary name, renamed when complete). Returns the origin used.
    Every pose is checked (under the ground, outside the Earth) before anything is drawn.
    ``depth_invalid``: "inf", "0" or "nan", what depth holds where no surface is measured."""
    if depth_invalid not in DEPTH_INVALID:
        raise LodscapeError(
            f"depth_invalid must be one of {', '.join(DEPTH_INVALID)}, got {depth_invalid!r}"
        )

    target = Path(out).expanduser()
    if target.exists() and (not target.is_dir() or any(target.iterdir())):
        raise LodscapeError(f"{target}: exists and is not an empty folder")
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise LodscapeError(f"{target}: folder {parent} does not exist")
    if not poses:
        raise LodscapeError("no poses to render")
    for pose in poses:
        try:
            scene.prepare(pose.camera)
        except CameraError as exc:
            raise LodscapeError(f"pose {pose.name}: {exc}") from None
    if origin is None:
        origin = default_origin(scene, [p.camera for p in poses])
    tmp = temp_beside(parent / target.name, kind="partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for sub in ("images", "depth", "normals", "semantic", "mask", "cameras", "colmap"):
            (tmp / sub).mkdir(parents=True)
        frames: list[dict[str, Any]] = []
        cameras_txt, images_txt = [], []
        seen: list[NDArray[np.float64]] = []
        for i, pose in enumerate(poses):
            camera_line, image_line, frame, points = _write_pose(
                tmp, i, pose, scene, origin, DEPTH_INVALID[depth_invalid]
            )
            cameras_txt.append(camera_line)
            images_txt.append(image_line)
            frames.append(frame)
            seen.append(points)
            if progress is not None:
                progress(i + 1, len(poses))
        _write_indexes(tmp, frames, cameras_txt, images_txt, origin, seen, depth_invalid)
        if target.exists():
            target.rmdir()  # empty, checked above
        os.replace(tmp, target)
    except OSError as exc:
        raise LodscapeError(f"{target}: cannot write ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return origin


#: Points of each view's measured surface kept to size instant-ngp's box (a sample).
_SEEN_POINTS = 4096


def _write_pose(
    tmp: Path, i: int, pose: Pose, scene: Any, origin: Origin, invalid: float
) -> tuple[str, str, dict[str, Any], NDArray[np.float64]]:
    """Pose ``i`` captured and written (image, depth, normals, labels, mask, its camera's
    JSON); its lines of COLMAP's cameras.txt and images.txt, its NeRF frame, and a sample of
    the world points it sees (with its centre)."""
    from PIL import Image

    from lodscape.render.labels import NO_DATA, SKY

    cap = scene.capture(pose.camera)
    m = conventions(cap.camera, origin)
    measured = (cap.labels != SKY) & (cap.labels != NO_DATA) & np.isfinite(cap.depth)
    depth = np.where(measured, cap.depth, np.float32(invalid)).astype(np.float32)
    normals = np.where(measured[..., None], cap.normals, 0.0).astype(np.float32)
    Image.fromarray(cap.rgb, "RGB").save(tmp / "images" / f"{pose.name}.png")
    np.save(tmp / "depth" / f"{pose.name}.npy", depth)
    np.save(tmp / "normals" / f"{pose.name}.npy", normals)
    Image.fromarray(cap.labels, "L").save(tmp / "semantic" / f"{pose.name}.png")
    mask = np.where(measured, 255, 0).astype(np.uint8)
    Image.fromarray(mask, "L").save(tmp / "mask" / f"{pose.name}.png")
    # what it sees, in the world frame: x_world = R^T (z K^-1 [u, v, 1] - t)
    rows, cols = np.nonzero(measured)
    pick = np.random.default_rng(i).permutation(rows.size)[:_SEEN_POINTS]
    z = cap.depth[rows[pick], cols[pick]].astype(np.float64)
    uv1 = np.stack([cols[pick], rows[pick], np.ones(pick.size)]).astype(np.float64)
    cam = np.linalg.solve(m.K, uv1) * z
    points = np.vstack([(m.R.T @ (cam - m.t[:, None])).T, m.centre[None, :]])
    c = cap.camera
    (tmp / "cameras" / f"{pose.name}.json").write_text(
        json.dumps(
            {
                "width": c.width,
                "height": c.height,
                "K": m.K.tolist(),
                "R": m.R.tolist(),
                "t": m.t.tolist(),
                "dist": [0.0, 0.0, 0.0, 0.0, 0.0],
                "centre": m.centre.tolist(),
                "geodetic": {
                    k: float(getattr(c, k))
                    for k in ("lon", "lat", "alt", "heading", "pitch", "roll", "fov_y")
                },
                "near": c.near,
                "far": c.far,
            },
            indent=1,
        )
        + "\n"
    )
    fx, fy, cx, cy = m.colmap_params
    camera_line = f"{i + 1} PINHOLE {c.width} {c.height} {_num(fx, fy, cx, cy)}"
    image_line = f"{i + 1} {_num(*m.qvec, *m.t)} {i + 1} {pose.name}.png\n"
    frame = {
        "file_path": f"images/{pose.name}.png",
        "depth_file_path": f"depth/{pose.name}.npy",
        "mask_path": f"mask/{pose.name}.png",
        "semantic_file_path": f"semantic/{pose.name}.png",
        "transform_matrix": m.c2w_gl.tolist(),
        "fl_x": float(fx),
        "fl_y": float(fy),
        "cx": float(cx),
        "cy": float(cy),
        "w": c.width,
        "h": c.height,
        "camera_angle_x": 2.0 * math.atan(c.width / (2.0 * float(fx))),
    }
    return camera_line, image_line, frame, points


def _write_indexes(
    tmp: Path,
    frames: list[dict[str, Any]],
    cameras_txt: list[str],
    images_txt: list[str],
    origin: Origin,
    seen: list[NDArray[np.float64]],
    depth_invalid: str,
) -> None:
    """The dataset's indexes: NeRF's transforms.json, COLMAP's text model, and frame.json (the
    world frame, the units and the conventions)."""
    first = frames[0]
    transforms = {
        "camera_model": "OPENCV",
        **{k: first[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x")},
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        **ngp_box(np.vstack(seen)),
        "frames": frames,
    }
    (tmp / "transforms.json").write_text(json.dumps(transforms, indent=1) + "\n")
    (tmp / "colmap" / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cameras_txt) + "\n"
    )
    (tmp / "colmap" / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n" + "\n".join(images_txt) + "\n"
    )
    (tmp / "colmap" / "points3D.txt").write_text(
        "# 3D point list (none: the scene's geometry is in depth/)\n"
    )
    (tmp / "frame.json").write_text(
        json.dumps(
            {
                "world": "local east-north-up metres",
                "origin": {"lon": origin.lon, "lat": origin.lat, "height": origin.height},
                "height": "ellipsoidal (WGS84), metres",
                "labels": {str(k): v for k, v in LABELS.items()},
                "depth": "float32 metres along the optical axis; "
                f"{depth_invalid} where no measured surface is (sky, the no-data ellipsoid)",
                "depth_invalid": depth_invalid,
                "normals": "float32 unit vectors in the OpenCV camera frame "
                "(x right, y down, z ahead), facing the camera; 0 where no measured surface is",
                "mask": "uint8: 255 where a measured surface is drawn, 0 elsewhere",
                "instant_ngp": "world * scale + offset in its unit cube (before its axis cycle)",
                "opencv": "x_cam = R @ x_world + t; pixel centres at whole numbers",
                "colmap": "PINHOLE; pixel centres at half-integers",
                "nerf": "transform_matrix: camera to world, OpenGL camera axes",
                "poses": len(frames),
            },
            indent=1,
        )
        + "\n"
    )


def _num(*values: float) -> str:
    """Numbers for a text file: shortest round-trip decimal of each float64."""
    return " ".join(repr(float(v)) for v in values)


def ngp_box(points: NDArray[np.float64]) -> dict[str, Any]:
    """instant-ngp's ``scale``, ``offset`` and ``aabb_scale`` for world points (the cameras'
    centres and samples of what they see): the middle 96 % of them fill its unit cube, world ×
    scale + offset (before its axis cycle, which keeps the cube); ``aabb_scale``, the power of
    two (1..128) whose box reaches the farthest of them."""
    p = np.asarray(points, np.float64)
    lo, hi = np.percentile(p, 2, axis=0), np.percentile(p, 98, axis=0)
    centre = (lo + hi) / 2.0
    scale = 1.0 / max(float((hi - lo).max()) * 1.1, 1e-6)
    reach = float(np.abs(p - centre).max()) * scale * 2.0  # the box side that holds them all
    aabb = int(np.clip(2 ** math.ceil(math.log2(max(reach, 1.0))), 1, 128))
    return {
        "aabb_scale": aabb,
        "scale": scale,
        "offset": (0.5 - centre * scale).tolist(),
    }


def default_origin(scene: Any, cameras: Sequence[Camera] = ()) -> Origin:
    """The data's centre at height 0 (a city without terrain: the city's own origin); where the
    data spans more than 10° (a server's whole-world bounds, say) the cameras' centre, so the
    frame's "up" is up where they look."""
    from lodscape.geo.frames import ecef_to_geodetic
    from lodscape.geo.tiles import merc_to_lonlat

    b = scene.source.bounds_merc
    (w, e), (s, n) = merc_to_lonlat([b.left, b.right], [b.bottom, b.top])
    if (e - w > 10.0 or n - s > 10.0) and len(cameras):
        mean = np.mean([c.position for c in cameras], axis=0)
        lon, lat, _h = ecef_to_geodetic(mean)
        return Origin(round(float(lon), 7), round(float(lat), 7), 0.0)
    lon, lat = merc_to_lonlat((b.left + b.right) / 2.0, (b.bottom + b.top) / 2.0)
    return Origin(round(float(lon), 7), round(float(lat), 7), 0.0)
