"""Geomorphing (issue 22): how far the ground jumps between consecutive frames of a slow
approach, with and without morphing, and what keeping each tile at its parent's resolution
costs in triangles.

Each frame's depth is reprojected into the next camera; where the surface did not move the two
agree, and the disagreement, in pixels of the surface's displacement at its distance, is what
popped (``tests/_synthetic.reprojected_jump``). Per frame the 99.9th percentile; the largest
over the approach, with and without morphing (4 px bound, where each split's step is plain;
and the default 2 px). Frames load every tile they draw (the same tiles on any machine).

    python bench/bench_morph.py [--frames 36] [--size 256x160] [--terrain-mode gpu]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

import lodscape
from lodscape import SceneOptions
from lodscape.data import sample_dem_path
from lodscape.errors import CameraError
from lodscape.geo.frames import ecef_to_geodetic
from lodscape.lod.select import SelectOptions, select

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import fbm_heights, reprojected_jump, write_dem


def approach(
    dem: str, morph: bool, sse: float, frames: int, w: int, h: int, mode: str = "cpu"
) -> tuple[list[float], list[int]]:
    """Per frame pair the 99.9th percentile jump (px), and per frame the triangles drawn."""
    # a streamed scene's meshes (regular grids, which geomorph; a still picture's TINs do not)
    opts = SceneOptions(
        select=SelectOptions(max_sse=sse),
        morph=morph,
        anisotropy=1.0,
        terrain_mode=mode,
        meshes="grid",
        ellipsoid=False,
    )
    jumps: list[float] = []
    tris: list[int] = []
    with lodscape.open(dem, opts) as scene:
        scene.view.morph = morph  # as a streaming scene's view does
        cam0 = replace(scene.overview_camera(w, h), pitch=-35.0)
        target = cam0.position + cam0.forward * 6000.0
        prev = None
        for i in range(frames):
            p = target + (cam0.position - target) * (1.0 - 0.01 * i)
            lon, lat, alt = (float(a) for a in ecef_to_geodetic(p))
            cam = cam0.moved(lon=lon, lat=lat, alt=alt)
            _, depth = scene.render(cam)
            fitted = scene.prepare(cam)
            assert scene.last is not None
            tris.append(int(scene.last.triangles))
            if prev is not None:
                jump = reprojected_jump(prev[0], prev[1], depth, fitted)
                jumps.append(float(np.nanpercentile(jump, 99.9)))
            prev = (depth, fitted)
    return jumps, tris


def hold_cost(dem: str, w: int, h: int) -> tuple[float, float]:
    """Median triangles of 20 views along the approach with and without hold_parent_grid."""
    with lodscape.open(dem, SceneOptions(meshes="grid")) as scene:
        cam0 = replace(scene.overview_camera(w, h), pitch=-35.0)
        target = cam0.position + cam0.forward * 6000.0
        got: dict[bool, list[int]] = {True: [], False: []}
        prev: dict[bool, object] = {True: None, False: None}
        for i in range(0, 60, 3):
            p = target + (cam0.position - target) * (1.0 - 0.015 * i)
            lon, lat, alt = (float(a) for a in ecef_to_geodetic(p))
            try:
                cam = scene.prepare(cam0.moved(lon=lon, lat=lat, alt=alt))
            except CameraError:
                break  # the approach reached the ground (the sample's hills rise into it)
            for hold in (True, False):
                sel = select(SelectOptions(hold_parent_grid=hold), cam, scene.tree, prev[hold])  # type: ignore[arg-type]
                prev[hold] = sel
                got[hold].append(sel.triangles)
    return statistics.median(got[True]), statistics.median(got[False])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--size", default="256x160")
    ap.add_argument("--terrain-mode", default="cpu", choices=("cpu", "gpu"))
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        fbm = write_dem(
            str(Path(tmp) / "fbm513.tif"),
            fbm_heights(513, seed=9, relief=500.0),
            crs="EPSG:32617",
            west=500_000.0,
            north=4_000_000.0,
            res=10.0,
        )
        for name, dem in (
            ("fBm 513² (10 m, 500 m relief)", fbm),
            ("the sample", sample_dem_path()),
        ):
            for sse in (4.0, 2.0):
                on, tris = approach(dem, True, sse, args.frames, w, h, args.terrain_mode)
                off, _ = approach(dem, False, sse, args.frames, w, h, args.terrain_mode)
                print(
                    f"{name}, {args.terrain_mode} terrain mode, {sse:g} px bound, {args.frames} "
                    f"frames at {w}×{h}: largest jump "
                    f"(99.9th percentile) {max(on):.2f} px with morphing, {max(off):.2f} px "
                    f"without; frames over a pixel {sum(j > 1 for j in on)} and "
                    f"{sum(j > 1 for j in off)}; the floor (median) {statistics.median(on):.2f} "
                    f"px; triangles median {statistics.median(tris):,.0f}"
                )
            held, free = hold_cost(dem, 1280, 720)
            print(
                f"{name}: triangles (1280×720, 20 views, median) keeping the parent's "
                f"resolution {held:,.0f}, without {free:,.0f} (×{held / free:.3f})"
            )


if __name__ == "__main__":
    main()
