"""The terrain drawn without ``discard`` where a tile's texture has nothing to cut (issue 24).

A 2049² spectral fBm DEM (5 m, UTM 17N, no nodata: every texture whole), three views at
1280×720 (the overview, a lower oblique, a grazing one), every tile resident, no distance read
back; per view the median of 11 frames with the variant without a discard
(``Renderer.no_discard``, the default) and with every tile drawn by the cutting program, in the
same process, alternating, three rounds.

    python bench/bench_discard.py
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import lodscape
from _synthetic import periodic_fbm, write_dem


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        dem = write_dem(str(Path(tmp) / "dem.tif"), periodic_fbm(2048), crs="EPSG:32617",
                        west=500000.0, north=4000000.0, res=5.0)  # fmt: skip
        with lodscape.open(dem, lodscape.SceneOptions(anisotropy=1.0)) as scene:
            ov = scene.overview_camera(1280, 720)
            views = {
                "overview": ov,
                "oblique": ov.moved(alt=ov.alt * 0.4, pitch=-25.0),
                "grazing": ov.moved(alt=ov.alt * 0.15, pitch=-12.0),
            }
            for cam in views.values():
                scene.render(cam, depth=False)
            rend = scene.renderer
            assert rend is not None
            times: dict[tuple[str, bool], list[float]] = {}
            for _ in range(3):
                for on in (True, False):
                    rend.no_discard = on
                    for name, cam in views.items():
                        ts = []
                        for _ in range(11):
                            t = time.perf_counter()
                            scene.render(cam, depth=False)
                            ts.append(time.perf_counter() - t)
                        times.setdefault((name, on), []).append(statistics.median(ts))
            rend.no_discard = True
    for name in views:
        a = statistics.median(times[(name, True)]) * 1e3
        b = statistics.median(times[(name, False)]) * 1e3
        print(f"{name:>9}: {a:.1f} ms without the discard, {b:.1f} ms with it (×{b / a:.3f})")


if __name__ == "__main__":
    main()
