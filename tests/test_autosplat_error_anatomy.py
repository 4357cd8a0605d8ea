"""bench/experiments/autosplat_error_anatomy.py: a colour offset over a car reads as coarse error, a
pixel checkerboard as fine error, the edge's pixels as the band; bad input fails in one line."""
from __future__ import annotations

import numpy as np
import pytest


def _square():
    mask = np.zeros((40, 50), bool)
    mask[5:35, 10:40] = True
    return mask


def test_an_offset_is_coarse_and_a_checkerboard_is_fine(bench_script):
    a, mask = bench_script("autosplat_error_anatomy"), _square()
    offset = np.zeros((40, 50, 3)) + 0.1 * mask[..., None]
    o = a.split(offset, mask, 2, 5)
    assert o["coarse"][0] == pytest.approx(o["interior"][0], rel=1e-9)
    assert o["fine"][0] < 1e-20
    yy, xx = np.mgrid[:40, :50]
    checker = (0.1 * np.where((yy + xx) % 2 == 0, 1.0, -1.0) * mask)[..., None].repeat(3, -1)
    c = a.split(checker, mask, 2, 5)
    assert c["coarse"][0] < 0.05 * c["interior"][0]      # a 5x5 box averages +-0.1 to +-0.004
    assert c["fine"][0] > 0.9 * c["interior"][0]


def test_the_band_is_the_edge_and_the_parts_count_their_pixels(bench_script):
    a, mask = bench_script("autosplat_error_anatomy"), _square()
    e = np.zeros((40, 50, 3))
    e[5:7, 10:40] = 0.2                                   # the top two rows: inside the 2-pixel band
    o = a.split(e, mask, 2, 5)
    assert o["interior"][0] == 0.0 and o["band"][0] == pytest.approx(o["all"][0])
    assert o["all"][1] == 3 * 30 * 30 and o["interior"][1] == 3 * 26 * 26
    assert o["band"][1] + o["interior"][1] == o["all"][1]


@pytest.mark.parametrize("argv, needle", [
    (["/nonexistent/run"], "run: no such directory"),
    (["{d}", "--window", "4"], "--window: expected an odd integer >= 3"),
    (["{d}", "--band", "0"], "--band: expected an integer >= 1"),
    (["{d}"], "run: no checkpoint.pt"),
])
def test_bad_input_fails_in_one_line(tmp_path, argv, needle, bench_script):
    with pytest.raises(SystemExit) as e:
        bench_script("autosplat_error_anatomy").main([x.format(d=tmp_path) if "{d}" in x else x for x in argv])
    assert needle in str(e.value) and "\n" not in str(e.value)
