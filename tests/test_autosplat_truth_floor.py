"""bench/experiments/autosplat_truth_floor.py: the street it regenerates is the one the writer drew
(the folder's JPEG and the regenerated render agree to JPEG's error), and its bad input fails in one line."""
from __future__ import annotations

import pytest


@pytest.mark.slow
def test_the_regenerated_street_is_the_written_one(tmp_path, bench_script):
    writer, floor = bench_script("autosplat_pandaset"), bench_script("autosplat_truth_floor")
    folder = writer.write(tmp_path / "busy_s3", 3, 3, 54, 96, 0.3, 2, ("CAM_FRONT", "CAM_BACK_LEFT"), "busy")
    o = floor.floors(folder, "busy", [1], 2, 4)
    assert o["pixels"]["image"] == 2 * 54 * 96
    # JPEG at quality 95 alone: far above what a different street (another seed) would read
    assert o["jpeg"]["image"] > 33.0
    # the floor holds both losses: never above either one alone
    assert o["floor"]["image"] <= min(o["jpeg"]["image"], o["alias"]["image"]) + 0.5


@pytest.mark.slow
def test_a_wrong_seed_reads_as_another_street(tmp_path, bench_script):
    writer, floor = bench_script("autosplat_pandaset"), bench_script("autosplat_truth_floor")
    folder = writer.write(tmp_path / "busy_s3", 3, 2, 54, 96, 0.3, 2, ("CAM_FRONT",), "busy")
    wrong = folder.rename(tmp_path / "busy_s4")
    assert floor.floors(wrong, "busy", [1], 2, 4)["jpeg"]["image"] < 25.0


@pytest.mark.parametrize("argv, needle", [
    (["{d}/nope_s0"], "folder: no such directory"),
    (["{d}", "--reference-supersample", "2"], "--reference-supersample: must exceed"),
    (["{d}", "--written-supersample", "0"], "--written-supersample: expected an integer >= 1"),
])
def test_bad_input_fails_in_one_line(tmp_path, capsys, argv, needle, bench_script):
    floor = bench_script("autosplat_truth_floor")
    (tmp_path / "x_s0").mkdir()
    with pytest.raises(SystemExit) as e:
        floor.main([a.format(d=tmp_path / "x_s0") if "{d}" in a else a for a in argv])
    msg = str(e.value)
    assert needle in msg and "\n" not in msg
