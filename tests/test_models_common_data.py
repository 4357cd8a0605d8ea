"""models/common/data.py: --data specs, synthetic worlds and train/val/test streets, resampling, tensors."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from clsplat.data import write_pandaset
from clsplat.models.common.data import (TEST_SEED_OFFSET, VAL_SEED_OFFSET, parse_data, resize_sequence,
                                        to_torch_frame)


def test_synthetic_streets_differ_by_index_and_split_and_render_only_chosen_cameras():
    src = parse_data("synthetic")
    kw = dict(num_frames=1, height=24, width=40, cameras=["CAM_BACK", "CAM_FRONT"])
    a, b, t = src.sequence(0, **kw), src.sequence(1, **kw), src.sequence(0, split="test", **kw)
    assert a.camera_names == ["CAM_BACK", "CAM_FRONT"] and set(a.frames[0].images) == {"CAM_BACK", "CAM_FRONT"}
    assert not np.array_equal(a.frames[0].images["CAM_FRONT"], b.frames[0].images["CAM_FRONT"])
    assert not np.array_equal(a.frames[0].images["CAM_FRONT"], t.frames[0].images["CAM_FRONT"])
    again = src.sequence(0, **kw)
    assert np.array_equal(a.frames[0].images["CAM_FRONT"], again.frames[0].images["CAM_FRONT"])


def test_resize_scales_intrinsics_consistently():
    src = parse_data("synthetic")
    big = src.sequence(0, num_frames=1, height=48, width=80, cameras=["CAM_FRONT"])
    small = resize_sequence(big, 24, 40)
    assert small.cameras[0].K[0, 0] == pytest.approx(big.cameras[0].K[0, 0] / 2)
    assert small.frames[0].images["CAM_FRONT"].shape == (24, 40, 3)
    d = small.frames[0].depths["CAM_FRONT"]
    assert np.isinf(d).any() and np.isfinite(d).any()  # sky stays inf with nearest sampling
    # the resampled image is close to the image rendered at the small size
    direct = src.sequence(0, num_frames=1, height=24, width=40, cameras=["CAM_FRONT"]).frames[0].images["CAM_FRONT"]
    assert np.abs(small.frames[0].images["CAM_FRONT"] - direct).mean() < 0.05


def test_pandaset_windows_and_splits(tmp_path):
    seq = parse_data("synthetic").sequence(0, num_frames=5, height=24, width=40, cameras=["CAM_FRONT", "CAM_BACK"])
    write_pandaset(seq, tmp_path / "001")
    src = parse_data(f"pandaset:{tmp_path / '001'}")
    w = src.sequence(0, num_frames=3, height=12, width=20)
    assert len(w.frames) == 3 and w.cameras[0].width == 20
    assert w.frames[0].timestamp == pytest.approx(seq.frames[0].timestamp)
    test = src.sequence(0, num_frames=1, height=12, width=20, split="test")  # frames 0-3 train, 4 test
    assert test.frames[0].timestamp == pytest.approx(seq.frames[4].timestamp)
    with pytest.raises(ValueError, match="num_frames"):
        src.sequence(0, num_frames=2, height=12, width=20, split="test")
    fr = to_torch_frame(w, 1, ["CAM_BACK"])
    assert fr["images"].shape == (1, 3, 12, 20) and fr["images"].dtype == torch.float32


@pytest.mark.parametrize("spec", ["", "synthetics", "pandaset:", "kitti:/x", None])
def test_bad_specs(spec):
    with pytest.raises(ValueError, match="data"):
        parse_data(spec)


def test_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="data: pandaset folder"):
        parse_data(f"pandaset:{tmp_path / 'missing'}")
    src = parse_data("synthetic")
    with pytest.raises(ValueError, match="cameras"):
        src.sequence(0, num_frames=1, height=8, width=8, cameras=["CAM_SIDEWAYS"])
    with pytest.raises(ValueError, match="num_frames"):
        src.sequence(0, num_frames=0, height=8, width=8)
    with pytest.raises(ValueError, match="split"):
        src.sequence(0, num_frames=1, height=8, width=8, split="valid")
    with pytest.raises(ValueError, match="synthetic world 'hilly'"):
        parse_data("synthetic:hilly")
    with pytest.raises(ValueError, match="default_world"):
        parse_data("synthetic", default_world="moon")


def test_train_val_and_test_streets_have_disjoint_seeds():
    """Every preset field is chosen on validation streets and reported on test streets: the three
    synthetic splits are disjoint seed ranges, whatever the base seed and index a run reaches."""
    src = parse_data("synthetic:classic", seed=5)
    kw = dict(num_frames=1, height=8, width=8, cameras=["CAM_FRONT"])
    seeds = {split: src.sequence(3, split=split, **kw).metadata["config"].seed for split in ("train", "val", "test")}
    assert seeds == {"train": 8, "val": VAL_SEED_OFFSET + 8, "test": TEST_SEED_OFFSET + 8}
    assert VAL_SEED_OFFSET - TEST_SEED_OFFSET >= TEST_SEED_OFFSET   # a test index never reaches a val seed


def test_a_plain_synthetic_is_the_familys_default_world_and_a_named_one_is_kept():
    assert parse_data("synthetic").name == "synthetic:classic"
    assert parse_data("synthetic", default_world="varied").name == "synthetic:varied"
    assert parse_data("synthetic:classic", default_world="varied").name == "synthetic:classic"


def test_real_data_splits_are_consecutive_and_disjoint(tmp_path):
    """A recorded sequence: the first 70 % of its frames train, the next 10 % validate, the last 20 %
    test; no window of one split holds a frame of another."""
    seq = parse_data("synthetic").sequence(0, num_frames=20, height=12, width=20, cameras=["CAM_FRONT"])
    write_pandaset(seq, tmp_path / "001")
    src = parse_data(f"pandaset:{tmp_path / '001'}")
    stamps = {}
    for split in ("train", "val", "test"):
        starts = src._window_starts(20, 1, split)
        stamps[split] = {round(src.sequence(i, num_frames=1, height=12, width=20, split=split).frames[0].timestamp, 6)
                         for i in range(len(starts))}
    assert [len(stamps[k]) for k in ("train", "val", "test")] == [14, 2, 4]
    assert not (stamps["train"] & stamps["val"] or stamps["val"] & stamps["test"] or stamps["train"] & stamps["test"])
    assert max(stamps["train"]) < min(stamps["val"]) and max(stamps["val"]) < min(stamps["test"])


def test_pandaset_pickles_are_allow_listed_unless_the_caller_trusts_them(tmp_path):
    """What --data pandaset:PATH does for drivingforward and pgt (their --trust-pickle sets safe_pickle=False)."""
    import gzip
    import os
    import pickle

    from clsplat.data.synthetic import generate_sequence

    class Payload:
        def __reduce__(self):
            return os.system, (f"touch {tmp_path / 'ran'}",)
    root = write_pandaset(generate_sequence(height=16, width=24, num_frames=2, seed=1), tmp_path / "001")
    with gzip.open(root / "lidar" / "01.pkl.gz", "wb") as fh:
        pickle.dump(Payload(), fh)
    with pytest.raises(ValueError, match=r"lidar/01\.pkl\.gz.*safe mode refuses"):
        parse_data(f"pandaset:{root}").full_sequence()
    assert not (tmp_path / "ran").exists()
    with pytest.raises(ValueError, match="not a pandas DataFrame"):
        parse_data(f"pandaset:{root}", safe_pickle=False).full_sequence()
    assert (tmp_path / "ran").exists()
