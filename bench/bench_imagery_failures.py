"""How long `lodscape render` takes, and what it says, when its imagery server fails in each way
(issue 18): 404, 500, HTML, a truncated PNG, a body cut short, a server that never answers,
nothing listening; with and without --imagery-strict, against the same render with no imagery.

A real loopback tile server (tests/_tileserver.py) answers every tile with the fault. The DEM is
a 129² fBm made here. Each run is a fresh `lodscape render` process (its start-up included).

    python bench/bench_imagery_failures.py [--timeout 10]
"""

from __future__ import annotations

import argparse
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from _synthetic import fbm_heights, write_dem
from _tileserver import TileServer

FAULTS = {
    "404": "404",
    "500": "500",
    "HTML": "garbage",
    "truncated PNG": "truncated-png",
    "body cut short": "truncated",
    "never answers": "slow",
    "nothing listening": None,
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def render(dem: Path, work: Path, extra: list[str]) -> tuple[int, float, str, str]:
    t = time.perf_counter()
    r = subprocess.run(
        ["lodscape", "render", str(dem), "--size", "320x200", "-o", str(work / "v.png"), *extra],
        capture_output=True,
        text=True,
    )
    return r.returncode, time.perf_counter() - t, r.stdout, r.stderr


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--timeout", type=float, default=10.0, help="--imagery-timeout")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        dem = work / "dem.tif"
        write_dem(str(dem), fbm_heights(129, seed=2), crs="EPSG:32616", west=500000.0,
                  north=4000000.0, res=30.0)  # fmt: skip
        _, base, _, _ = render(dem, work, ["-q"])
        print(f"no imagery: {base:.1f} s")
        for name, fault in FAULTS.items():
            server = TileServer()
            server.default_fault = fault
            server.delay = 600.0
            template = server.template
            if fault is None:
                template = f"http://127.0.0.1:{_free_port()}/{{z}}/{{x}}/{{y}}.png"
            flags = ["--imagery", template, "--imagery-cache", str(work / name.replace(" ", "_"))]
            flags += ["--imagery-timeout", str(args.timeout)]
            for strict in ([], ["--imagery-strict"]):
                code, took, out, err = render(dem, work, flags + strict)
                said = [line for line in err.splitlines() if line.startswith("lodscape")]
                counts = " ".join(
                    line.strip() for line in out.splitlines() if "imagery_failed" in line
                )
                label = "strict" if strict else "default"
                print(f"{name:>18} {label:>7}: exit {code}, {took:5.1f} s, {counts or '-'}")
                for line in said:
                    print(f"{'':>28}{line[:150]}")
            server.close()


if __name__ == "__main__":
    main()
