"""Vision datasets: the written cameras put known points on the pixels where they are drawn, the
three conventions agree, normals and labels say what is there, and bad input leaves nothing."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import lodscape
from _synthetic import run_cli
from lodscape.data import sample_city_path, sample_dem_path
from lodscape.dataset import Origin, Pose, conventions, read_poses, write_dataset
from lodscape.errors import LodscapeError
from lodscape.geo.frames import geodetic_to_ecef
from lodscape.lod.camera import Camera
from lodscape.render import labels as L

pytestmark = pytest.mark.gl

#: Level ground 120 m above the ellipsoid, over a box around Helsinki's centre.
FLAT = "flat:24.90,60.15,24.98,60.19,120"


def _write_poses(path: Path, rows: list[dict[str, float | str]]) -> Path:
    cols = list(rows[0])
    path.write_text(
        ",".join(cols) + "\n" + "".join(",".join(str(r[c]) for c in cols) + "\n" for r in rows)
    )
    return path


def _colmap(folder: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """name → (params fx fy cx cy, qvec, tvec) read from COLMAP's text model."""
    cams = {}
    for line in (folder / "cameras.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        f = line.split()
        assert f[1] == "PINHOLE"
        cams[f[0]] = np.array([float(v) for v in f[4:8]])
    out = {}
    for line in (folder / "images.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        f = line.split()
        out[Path(f[9]).stem] = (
            cams[f[8]],
            np.array([float(v) for v in f[1:5]]),
            np.array([float(v) for v in f[5:8]]),
        )
    return out


def _quat_to_r(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _project_opencv(cam: dict, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K, R, t = np.array(cam["K"]), np.array(cam["R"]), np.array(cam["t"])
    pc = pts @ R.T + t
    uv = pc[:, :2] / pc[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return uv, pc[:, 2]


@pytest.fixture(scope="module")
def flat_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A grazing view and a steep, rolled, narrow one over level ground."""
    d = tmp_path_factory.mktemp("ds")
    poses = _write_poses(
        d / "poses.csv",
        [
            {"name": "graze", "lon": 24.93, "lat": 60.16, "alt": 420, "heading": 30,
             "pitch": -14, "roll": 0, "fov": 60},
            {"name": "steep", "lon": 24.95, "lat": 60.17, "alt": 900, "heading": 200,
             "pitch": -62, "roll": 11, "fov": 35},
        ],
    )  # fmt: skip
    out = d / "out"
    with lodscape.open(FLAT) as scene:
        write_dataset(scene, read_poses(poses, 240, 160), out, Origin(24.94, 60.17, 100.0))
    return out


def test_a_ground_point_lands_where_it_is_drawn(flat_dataset: Path) -> None:
    """Points of the level ground (geodetic, so independent of any camera), projected with
    the written OpenCV camera: the drawn depth, read at the projected spot, is the projected
    depth, within a tenth of a pixel along the depth's gradient (the half-pixel conventions
    would show as 0.5)."""
    origin = Origin(24.94, 60.17, 100.0)
    rng = np.random.default_rng(7)
    for name in ("graze", "steep"):
        cam = json.loads((flat_dataset / "cameras" / f"{name}.json").read_text())
        depth = np.load(flat_dataset / "depth" / f"{name}.npy")
        h, w = depth.shape
        lon = rng.uniform(24.91, 24.97, 20000)
        lat = rng.uniform(60.155, 60.185, 20000)
        pts = origin.to_local(geodetic_to_ecef(lon, lat, np.full_like(lon, 120.0)))
        uv, z = _project_opencv(cam, pts)
        # inside, with a pixel of margin for the bilinear read and the gradient
        ok = (z > 0) & (uv[:, 0] > 1) & (uv[:, 0] < w - 2) & (uv[:, 1] > 1) & (uv[:, 1] < h - 2)
        uv, z = uv[ok], z[ok]
        i0 = np.floor(uv).astype(int)
        f = uv - i0
        x0, y0 = i0[:, 0], i0[:, 1]
        quad = np.stack(
            [depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]]
        )
        finite = np.isfinite(quad).all(0)
        assert finite.sum() > 500, name
        quad, f, z, x0, y0 = quad[:, finite], f[finite], z[finite], x0[finite], y0[finite]
        drawn = (
            quad[0] * (1 - f[:, 0]) * (1 - f[:, 1])
            + quad[1] * f[:, 0] * (1 - f[:, 1])
            + quad[2] * (1 - f[:, 0]) * f[:, 1]
            + quad[3] * f[:, 0] * f[:, 1]
        )
        grad = np.hypot(quad[1] - quad[0], quad[2] - quad[0])
        steep = grad > 1e-3 * z  # where the depth changes enough to locate a point
        off_px = np.abs(drawn - z)[steep] / grad[steep]
        assert steep.sum() > 300, name
        assert np.median(off_px) < 0.05, (name, np.median(off_px))
        assert np.quantile(off_px, 0.99) < 0.2, (name, np.quantile(off_px, 0.99))


def test_colmap_and_nerf_agree_with_opencv(flat_dataset: Path) -> None:
    colmap = _colmap(flat_dataset / "colmap")
    nerf = json.loads((flat_dataset / "transforms.json").read_text())
    frames = {Path(fr["file_path"]).stem: fr for fr in nerf["frames"]}
    assert set(colmap) == set(frames) == {"graze", "steep"}
    rng = np.random.default_rng(3)
    for name in frames:
        cam = json.loads((flat_dataset / "cameras" / f"{name}.json").read_text())
        centre = np.array(cam["centre"])
        pts = centre + rng.normal(0, 300, (200, 3)) + 1000 * np.array(cam["R"])[2]
        uv_cv, z_cv = _project_opencv(cam, pts)
        # COLMAP: world → camera by the quaternion and t; pixel centres at half-integers
        (fx, fy, cx, cy), q, t = colmap[name]
        pc = pts @ _quat_to_r(q).T + t
        uv_colmap = pc[:, :2] / pc[:, 2:3] * [fx, fy] + [cx, cy] - 0.5
        np.testing.assert_allclose(uv_colmap, uv_cv, atol=1e-6)
        np.testing.assert_allclose(pc[:, 2], z_cv, rtol=1e-9)
        # NeRF: camera to world in OpenGL axes (looking down -z, y up); rays through i + 0.5
        fr = frames[name]
        c2w = np.array(fr["transform_matrix"])
        pg = (pts - c2w[:3, 3]) @ c2w[:3, :3]
        u = fr["fl_x"] * pg[:, 0] / -pg[:, 2] + fr["cx"]
        v = fr["fl_y"] * -pg[:, 1] / -pg[:, 2] + fr["cy"]
        uv_nerf = np.stack([u, v], axis=1) - 0.5
        np.testing.assert_allclose(uv_nerf, uv_cv, atol=1e-6)
        np.testing.assert_allclose(-pg[:, 2], z_cv, rtol=1e-9)
        assert math.isclose(
            fr["camera_angle_x"], 2 * math.atan(fr["w"] / (2 * fr["fl_x"])), rel_tol=1e-12
        )
    frame = json.loads((flat_dataset / "frame.json").read_text())
    assert frame["origin"] == {"lon": 24.94, "lat": 60.17, "height": 100.0}
    assert frame["labels"]["3"] == "building"


def test_the_normals_of_level_ground_point_up(flat_dataset: Path) -> None:
    for name in ("graze", "steep"):
        cam = json.loads((flat_dataset / "cameras" / f"{name}.json").read_text())
        n = np.load(flat_dataset / "normals" / f"{name}.npy")
        lab = np.array(Image.open(flat_dataset / "semantic" / f"{name}.png"))
        depth = np.load(flat_dataset / "depth" / f"{name}.npy")
        ground = lab == L.TERRAIN
        assert ground.mean() > 0.3
        up = np.array(cam["R"]) @ np.array([0.0, 0.0, 1.0])  # the ENU up in the camera frame
        cos = n[ground] @ up
        # the ellipsoid's normal turns 1' per 1.85 km: under a degree anywhere in the box
        assert cos.min() > math.cos(math.radians(1.0)), name
        np.testing.assert_allclose(np.linalg.norm(n[ground], axis=1), 1.0, atol=1e-5)
        # sky and the no-data ellipsoid: no depth (inf by default), normal 0, mask 0;
        # every measured surface has a depth
        unmeasured = (lab == L.SKY) | (lab == L.NO_DATA)
        assert np.array_equal(unmeasured, ~np.isfinite(depth))
        assert not n[unmeasured].any()
        mask = np.array(Image.open(flat_dataset / "mask" / f"{name}.png"))
        assert np.array_equal(mask == 255, ~unmeasured)
        assert set(np.unique(mask).tolist()) <= {0, 255}


def test_the_city_is_labelled_by_what_it_is(tmp_path: Path) -> None:
    from lodscape.imagery.landcover import read_landcover

    city = sample_city_path()
    with lodscape.open("flat", city=city, landcover=read_landcover(city)) as scene:
        cam = Camera(24.94, 60.168, 70.0, heading=0.0, pitch=-20.0, width=320, height=200)
        cap = scene.capture(cam)
        rgb, depth = scene.render(cam)
    found = set(np.unique(cap.labels).tolist())
    assert {L.TERRAIN, L.BUILDING, L.ROAD, L.VEGETATION, L.STREET_FURNITURE} <= found, found
    # the labels are of the frame drawn: the same depth, and the same picture as render's
    np.testing.assert_array_equal(cap.depth, depth)
    np.testing.assert_array_equal(cap.rgb, rgb)
    b = cap.normals[cap.labels == L.BUILDING]
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-4)
    # every normal faces the camera: against the ray through its pixel
    K = conventions(cap.camera, Origin(24.94, 60.17)).K
    v, u = np.mgrid[0:200, 0:320]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    drawn = cap.labels > 0
    assert ((cap.normals[drawn] * rays[drawn]).sum(1) <= 1e-4).all()


def test_the_command_line_writes_a_dataset(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    poses = _write_poses(
        tmp_path / "p.csv",
        [
            {"lon": -84.3, "lat": 36.45, "alt": 3000, "heading": 10, "pitch": -35},
            {"lon": -84.2, "lat": 36.5, "alt": 2500, "heading": 250, "pitch": -25},
        ],
    )
    out = tmp_path / "ds"
    code, stdout, err = run_cli(
        ["render", str(sample_dem_path()), "--poses", str(poses), "--dataset", str(out),
         "--size", "96x64", "--origin", "-84.25,36.5,300"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    assert "2 poses" in stdout
    names = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert names == sorted(
        [
            *(f"{d}/0000{i}.{e}" for i in (0, 1) for d, e in (
                ("images", "png"), ("depth", "npy"), ("normals", "npy"), ("semantic", "png"),
                ("mask", "png"), ("cameras", "json"))),
            "colmap/cameras.txt", "colmap/images.txt", "colmap/points3D.txt",
            "frame.json", "transforms.json",
        ]
    )  # fmt: skip
    assert np.load(out / "depth" / "00001.npy").shape == (64, 96)
    with Image.open(out / "images" / "00000.png") as im:
        assert im.size == (96, 64)
    # instant-ngp's box: every camera (and most of what they see) inside its unit cube
    tj = json.loads((out / "transforms.json").read_text())
    assert tj["aabb_scale"] in (1, 2, 4, 8, 16, 32, 64, 128)
    for frame in tj["frames"]:
        c = np.array(frame["transform_matrix"])[:3, 3] * tj["scale"] + np.array(tj["offset"])
        assert ((c >= 0.0) & (c <= 1.0)).all(), c
        assert frame["mask_path"].startswith("mask/")
    # and the same poses with depth 0 where no surface is measured
    zero = tmp_path / "ds0"
    code, _, err = run_cli(
        ["render", str(sample_dem_path()), "--poses", str(poses), "--dataset", str(zero),
         "--size", "96x64", "--origin", "-84.25,36.5,300", "--depth-invalid", "0"],
        capsys,
    )  # fmt: skip
    assert code == 0, err
    d_inf, d_0 = (np.load(f / "depth" / "00000.npy") for f in (out, zero))
    assert np.array_equal(np.isinf(d_inf), d_0 == 0.0)
    assert np.isinf(d_inf).any()
    assert json.loads((zero / "frame.json").read_text())["depth_invalid"] == "0"
    code, _, err = run_cli(
        ["render", str(sample_dem_path()), "--poses", str(poses), "--dataset",
         str(tmp_path / "dsx"), "--depth-invalid", "-1"],
        capsys,
    )  # fmt: skip
    assert code == 2
    assert "depth_invalid" in err
    # the same folder again: refused, and the first dataset is left as it was
    code, _, err = run_cli(
        ["render", str(sample_dem_path()), "--poses", str(poses), "--dataset", str(out)], capsys
    )
    assert code == 2
    assert "not an empty folder" in err


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ("lon,lat\n1,2\n", "missing alt"),
        ("lon,lat,alt\n-84.3,36.45,abc\n", "line 2: a value is not a number"),
        ("lon,lat,alt\n", "a header and no rows"),
        ("lon,lat,alt,name\n-84.3,36.45,3000,a\n-84.3,36.46,3000,a\n", "used twice"),
        ("lon,lat,alt,name\n-84.3,36.45,3000,../x\n", "must be letters"),
        ("lon,lat,alt,pitch\n-84.3,36.45,3000,-95\n", "line 2: camera pitch"),
        ("lon,lat,alt\n-84.3,36.45,10\n", "pose 00000: "),  # under the ground
    ],
)
def test_bad_poses_are_refused_in_one_line_and_leave_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], rows: str, message: str
) -> None:
    poses = tmp_path / "p.csv"
    poses.write_text(rows)
    out = tmp_path / "ds"
    code, _, err = run_cli(
        ["render", str(sample_dem_path()), "--poses", str(poses), "--dataset", str(out),
         "--size", "64x48"],
        capsys,
    )  # fmt: skip
    assert code == 2
    assert message in err
    assert err.strip().count("\n") == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv"]


def test_dataset_flags_go_together(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dem = str(sample_dem_path())
    for argv, message in [
        (["render", dem, "--poses", "p.csv"], "go together"),
        (["render", dem, "--poses", "p.csv", "--dataset", "d", "--lon", "1"], "drop --lon"),
        (["render", dem, "--poses", "p.csv", "--dataset", "d", "--origin", "x"], "--origin is"),
    ]:
        code, _, err = run_cli(argv, capsys)
        assert code == 2, argv
        assert message in err, (argv, err)


def test_write_dataset_refuses_what_it_cannot_write(tmp_path: Path) -> None:
    pose = Pose("a", Camera(24.94, 60.17, 500.0, width=32, height=24))
    with lodscape.open(FLAT) as scene:
        with pytest.raises(LodscapeError, match="does not exist"):
            write_dataset(scene, [pose], tmp_path / "missing" / "ds")
        with pytest.raises(LodscapeError, match="no poses"):
            write_dataset(scene, [], tmp_path / "ds")
    m = conventions(pose.camera, Origin(24.94, 60.17, 0.0))
    # right above the origin: the camera centre is 500 m up, and R is a rotation
    np.testing.assert_allclose(m.centre, [0.0, 0.0, 500.0], atol=1e-6)
    np.testing.assert_allclose(m.R @ m.R.T, np.eye(3), atol=1e-12)
    assert list(tmp_path.iterdir()) == []


def test_the_gpu_terrain_mode_labels_the_same_ground() -> None:
    """Tessellated terrain writes its normals (from the height texture) and labels too."""
    options = lodscape.SceneOptions(terrain_mode="gpu")
    cam = Camera(24.93, 60.16, 420.0, heading=30.0, pitch=-14.0, width=160, height=100)
    with lodscape.open(FLAT, options=options) as scene:
        cap = scene.capture(cam)
        _, depth = scene.render(cam)
        assert scene.terrain_mode == "gpu"
    np.testing.assert_array_equal(cap.depth, depth)
    ground = cap.labels == L.TERRAIN
    assert ground.mean() > 0.3
    up = conventions(cap.camera, Origin(24.94, 60.17)).R @ np.array([0.0, 0.0, 1.0])
    assert (cap.normals[ground] @ up).min() > math.cos(math.radians(1.0))


def test_the_default_origin_is_where_the_cameras_are_not_0_0() -> None:
    """A server's terrain has whole-world bounds (terrarium:, terrain-rgb:, a layer.json without
    bounds): the frame's origin is the poses' centre, not lon 0, lat 0 (cameras 3,600 km away,
    "up" tilted 36° at the data); a DEM's is its centre."""
    from types import SimpleNamespace

    from lodscape.dataset import default_origin
    from lodscape.geo.tiles import ORIGIN, Bbox, lonlat_to_merc

    cams = [Camera(8.0 + 0.01 * i, 46.0, 3000.0) for i in range(3)]
    world = SimpleNamespace(
        source=SimpleNamespace(bounds_merc=Bbox(-ORIGIN, -ORIGIN, ORIGIN, ORIGIN))
    )
    o = default_origin(world, cams)
    assert o.lon == pytest.approx(8.01, abs=1e-6)
    assert o.lat == pytest.approx(46.0, abs=1e-3)
    (x0, x1), (y0, y1) = lonlat_to_merc([7.9, 8.1], [45.9, 46.1])
    local = SimpleNamespace(source=SimpleNamespace(bounds_merc=Bbox(x0, y0, x1, y1)))
    o = default_origin(local, cams)
    assert (o.lon, o.lat) == pytest.approx((8.0, 46.0), abs=1e-3)
