"""Midpoint-displacement fBm: its increments follow the fBm law, and it is seamless and
deterministic whatever window, order or process computes it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lodscape.terrain.fractal import fbm_window, gaussian_hash

LAGS = np.array([1, 2, 4, 8, 16, 32, 64])


@pytest.mark.parametrize("hurst", [0.3, 0.5, 0.8])
def test_increments_follow_the_fbm_law(hurst: float) -> None:
    """log-log slope of the mean squared increment against distance is 2H (±0.1)."""
    slopes = []
    for seed in (101, 202):  # seeds the calibration never saw
        z = fbm_window(seed, hurst, 1.0, 12, 512, 1024, 1024, 1024)
        msq = [
            np.mean(
                np.concatenate(
                    [(z[:, k:] - z[:, :-k]).ravel() ** 2, (z[k:, :] - z[:-k, :]).ravel() ** 2]
                )
            )
            for k in LAGS
        ]
        slopes.append(np.polyfit(np.log(LAGS), np.log(msq), 1)[0])
    assert abs(np.mean(slopes) - 2 * hurst) <= 0.1, slopes


def test_windows_agree_to_the_bit_wherever_they_overlap() -> None:
    big = fbm_window(5, 0.7, 300.0, 14, 1000, 2000, 400, 300)
    for i0, j0, ni, nj in [
        (1000, 2000, 1, 1),
        (1123, 2047, 17, 65),
        (1399, 2299, 1, 1),
        (1200, 2100, 200, 200),
    ]:
        part = fbm_window(5, 0.7, 300.0, 14, i0, j0, ni, nj)
        assert (
            part.tobytes() == big[j0 - 2000 : j0 - 2000 + nj, i0 - 1000 : i0 - 1000 + ni].tobytes()
        )
    # the same points, asked in any order of windows, come out the same
    a = [fbm_window(5, 0.7, 300.0, 14, 1000 + 50 * k, 2000, 50, 50) for k in range(4)]
    b = [fbm_window(5, 0.7, 300.0, 14, 1000 + 50 * k, 2000, 50, 50) for k in reversed(range(4))]
    assert np.concatenate(a, axis=1).tobytes() == np.concatenate(b[::-1], axis=1).tobytes()


def test_the_lattice_wraps_at_the_antimeridian() -> None:
    n = 1 << 10
    across = fbm_window(9, 0.5, 1.0, 10, n - 4, 100, 8, 4)
    east = fbm_window(9, 0.5, 1.0, 10, 0, 100, 4, 4)
    assert across[:, 4:].tobytes() == east.tobytes()


def test_the_same_in_another_process() -> None:
    code = (
        "from lodscape.terrain.fractal import fbm_window; import sys; "
        "sys.stdout.buffer.write(fbm_window(3, 0.8, 500.0, 16, 7000, 9000, 64, 64).tobytes())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, check=True).stdout
    assert out == fbm_window(3, 0.8, 500.0, 16, 7000, 9000, 64, 64).tobytes()


def test_seeds_differ_and_the_hash_is_normal() -> None:
    i, j = np.meshgrid(np.arange(300), np.arange(300))
    g = gaussian_hash(1, 3, i, j)
    assert abs(g.mean()) < 0.02
    assert abs(g.std() - 1.0) < 0.02
    assert not np.array_equal(g, gaussian_hash(2, 3, i, j))
    assert not np.array_equal(g, gaussian_hash(1, 4, i, j))


@pytest.mark.parametrize(("args", "message"), [((1.2, 5), "Hurst"), ((0.5, 99), "level")])
def test_bad_parameters(args: tuple[float, int], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        fbm_window(0, args[0], 1.0, args[1], 0, 0, 4, 4)
