"""Flights into an MP4 (issue 22, paper 001's triple buffering): frames per second of a flight
over the embedded sample with the pictures read through a ring of three pixel-pack buffers and
the encoder on its own thread behind a queue of three frames (the defaults), against each
picture read when drawn (and its distance with it, as before), against each frame also written
before the next renders; and without a video, what rendering alone allows. Same cameras, same
process, alternating runs, medians.

    python bench/bench_video.py [--frames 90] [--size 1280x720] [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import lodscape
from lodscape import flight
from lodscape.data import sample_dem_path
from lodscape.stream import SimClock, StreamOptions


def one(frames: int, w: int, h: int, video: Path | None, threaded: bool, ring: int) -> float:
    """Frames per second of one flight (wall time, the first frame's loading left out)."""
    flight._Video.THREADED = threaded
    flight.RING = ring
    opts = lodscape.SceneOptions(stream=StreamOptions(), anisotropy=1.0)
    route = flight.orbit_route(-84.25, 36.55, 3000.0, 2500.0, 200.0)
    cams = list(flight.cameras(route, 30.0, w, h))[:frames]
    start: list[float] = []
    with lodscape.open(sample_dem_path(), opts, clock=SimClock()) as scene:
        flight.fly(
            scene,
            iter(cams),
            30.0,
            video=video,
            on_frame=lambda i: start.append(time.perf_counter()) if i == 0 else None,
        )
        end = time.perf_counter()
    return (frames - 1) / (end - start[0])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    got: dict[str, list[float]] = {"ring": [], "threaded": [], "in turn": [], "no video": []}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "f.mp4"
        for _ in range(args.runs):
            got["in turn"].append(one(args.frames, w, h, out, False, 0))
            got["threaded"].append(one(args.frames, w, h, out, True, 0))
            got["ring"].append(one(args.frames, w, h, out, True, 3))
            got["no video"].append(one(args.frames, w, h, None, True, 3))
    med = {k: statistics.median(v) for k, v in got.items()}
    print(
        f"{args.frames} frames at {w}×{h} over the sample, medians of {args.runs}, frames/s: "
        f"read-back ring + encoder thread {med['ring']:.2f}; encoder thread, each picture read "
        f"when drawn {med['threaded']:.2f} (ring ×{med['ring'] / med['threaded']:.2f}); "
        f"each frame read and written in turn {med['in turn']:.2f} "
        f"(both ×{med['ring'] / med['in turn']:.2f}); no video {med['no video']:.2f}"
    )
    for k, v in got.items():
        print(f"    {k}: {', '.join(f'{x:.2f}' for x in v)}")


if __name__ == "__main__":
    main()
