"""The synthetic-street cache (clsplat/data/synthetic_cache.py): a cached street equals the
generated one, the key separates configs and generator versions, a fill resumes, the models' data
source reads it, and ``clsplat data synth`` rejects bad input with exit status 2."""
import dataclasses

import numpy as np
import pytest

from clsplat.cli import main as clsplat_main
from clsplat.data import SyntheticConfig, generate_sequence
from clsplat.data import synthetic_cache as sc

CFG = SyntheticConfig(height=16, width=24, num_frames=2, seed=3, lidar=True, cameras=("CAM_FRONT", "CAM_BACK"))


def _same(a, b):
    assert a.camera_names == b.camera_names
    for ca, cb in zip(a.cameras, b.cameras):
        assert np.array_equal(ca.K, cb.K) and np.array_equal(ca.cam_to_ego, cb.cam_to_ego)
    assert len(a.frames) == len(b.frames)
    for fa, fb in zip(a.frames, b.frames):
        assert fa.timestamp == fb.timestamp and np.array_equal(fa.ego_to_world, fb.ego_to_world)
        for kind in ("images", "depths", "semantics", "instances"):
            da, db = getattr(fa, kind), getattr(fb, kind)
            assert da.keys() == db.keys(), kind
            for n in da:
                assert da[n].dtype == db[n].dtype and np.array_equal(da[n], db[n]), (kind, n)
        assert np.array_equal(fa.lidar.points, fb.lidar.points) and fa.lidar.frame == fb.lidar.frame
        assert np.array_equal(fa.lidar.intensity, fb.lidar.intensity)
        assert [(x.track_id, x.label) for x in fa.boxes] == [(x.track_id, x.label) for x in fb.boxes]
        assert all(np.array_equal(x.center, y.center) for x, y in zip(fa.boxes, fb.boxes))


def test_a_cached_street_equals_the_generated_one(tmp_path):
    cache = sc.SyntheticCache(tmp_path / "c")
    assert cache.get(CFG) is None and CFG not in cache
    first = cache.sequence(CFG)                   # miss: generated and stored
    assert CFG in cache
    _same(first, generate_sequence(CFG))
    again = cache.get(CFG)
    _same(again, generate_sequence(CFG))
    assert again.metadata["config"] == CFG


def test_a_cached_varied_street_equals_the_generated_one(tmp_path):
    cfg = dataclasses.replace(CFG, world="varied", seed=8)
    cache = sc.SyntheticCache(tmp_path)
    assert sc.config_key(cfg) != sc.config_key(dataclasses.replace(cfg, world="straight"))
    cache.sequence(cfg)
    got = cache.get(cfg)
    fresh = generate_sequence(cfg)
    _same(got, fresh)
    assert got.metadata["world"] == fresh.metadata["world"] and got.metadata["world"].world == "varied"


def test_the_key_separates_configs_and_generator_versions(tmp_path, monkeypatch):
    keys = {sc.config_key(CFG), sc.config_key(dataclasses.replace(CFG, seed=4)),
            sc.config_key(dataclasses.replace(CFG, supersample=2)), sc.config_key(dataclasses.replace(CFG, dt=0.2)),
            sc.config_key(CFG, fingerprint="0" * 16)}
    assert len(keys) == 5
    # cameras=None is the whole rig in rig order: the same street, the same key
    full = dataclasses.replace(CFG, cameras=None)
    from clsplat.data import CAMERA_NAMES
    assert sc.config_key(full) == sc.config_key(dataclasses.replace(CFG, cameras=tuple(CAMERA_NAMES)))
    cache = sc.SyntheticCache(tmp_path)
    cache.sequence(CFG)
    monkeypatch.setattr(sc, "generator_fingerprint", lambda: "f" * 16)   # the generator changed
    assert CFG not in sc.SyntheticCache(tmp_path) and sc.SyntheticCache(tmp_path).get(CFG) is None


def test_the_fingerprint_covers_every_file_of_the_generator_package(tmp_path, monkeypatch):
    """The generator is a package (clsplat/data/synthetic/): a change to any of its files, not only
    __init__.py, gives a new fingerprint."""
    import shutil
    from pathlib import Path

    from clsplat.data import synthetic

    copy = tmp_path / "synthetic"
    shutil.copytree(Path(synthetic.__file__).parent, copy,
                    ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(synthetic, "__file__", str(copy / "__init__.py"))
    before = sc.generator_fingerprint()
    assert before == sc.generator_fingerprint() and len(before) == 16
    for name in ("textures.py", "street.py", "__init__.py"):
        (copy / name).write_text((copy / name).read_text() + "\n# changed\n")
        after = sc.generator_fingerprint()
        assert after != before, name
        before = after


def test_a_damaged_file_is_a_miss_and_is_rewritten(tmp_path):
    cache = sc.SyntheticCache(tmp_path)
    cache.sequence(CFG)
    cache.path(CFG).write_bytes(b"not an npz")
    assert cache.get(CFG) is None
    _same(cache.sequence(CFG), generate_sequence(CFG))
    assert cache.get(CFG) is not None


def test_fill_resumes_and_the_command_reports_it(tmp_path, capsys):
    args = ["data", "synth", "--count", "2", "--out", str(tmp_path), "--height", "16", "--width", "24",
            "--num-frames", "2", "--no-lidar", "--cameras", "CAM_FRONT", "--quiet"]
    assert clsplat_main(args) == 0
    assert "2 streets written, 0 already cached" in capsys.readouterr().out
    files = sorted(tmp_path.glob("*.npz"))
    assert len(files) == 2
    files[0].unlink()                             # an interrupted fill: re-running completes it
    assert clsplat_main(args[:3] + ["3"] + args[4:]) == 0
    assert "2 streets written, 1 already cached" in capsys.readouterr().out
    base = SyntheticConfig(height=16, width=24, num_frames=2, lidar=False, cameras=("CAM_FRONT",))
    cache = sc.SyntheticCache(tmp_path)
    assert all(dataclasses.replace(base, seed=s) in cache for s in range(3))


@pytest.mark.parametrize("args, msg", [
    (["--count", "0"], "--count"), (["--count", "1", "--seed", "-1"], "--seed"),
    (["--count", "1", "--cameras", "CAM_TOP"], "--cameras"), (["--count", "1", "--height", "0"], "height"),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, args, msg):
    assert clsplat_main(["data", "synth", "--out", str(tmp_path / "x"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("clsplat data synth: ") and msg in err[0]
    assert clsplat_main(["data", "nothing"]) == 2


def test_the_models_read_the_cache_as_they_would_generate(tmp_path):
    from clsplat.models.common.data import parse_data
    a = parse_data(f"synthetic-cache:{tmp_path}").sequence(2, num_frames=2, height=16, width=24, split="test")
    b = parse_data("synthetic").sequence(2, num_frames=2, height=16, width=24, split="test")
    assert len(list(tmp_path.glob("*.npz"))) == 1     # written through on the miss
    c = parse_data(f"synthetic-cache:{tmp_path}").sequence(2, num_frames=2, height=16, width=24, split="test")
    for s in (a, c):
        for fa, fb in zip(s.frames, b.frames):
            assert all(np.array_equal(fa.images[n], fb.images[n]) for n in fb.images)
            assert all(np.array_equal(fa.depths[n], fb.depths[n]) for n in fb.depths)
    with pytest.raises(ValueError, match="synthetic-cache"):
        parse_data("synthetic-cache:")
