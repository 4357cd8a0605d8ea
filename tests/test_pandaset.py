"""PandaSet writer/loader round trip and error messages."""
import gzip
import json

import numpy as np
import pytest

from clsplat.data.pandaset import load_pandaset, write_pandaset
from clsplat.data.scene import quat_to_rotmat
from clsplat.data.synthetic import generate_sequence


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    seq = generate_sequence(height=24, width=48, num_frames=3, seed=1)
    root = write_pandaset(seq, tmp_path_factory.mktemp("pandaset") / "001", jpeg_quality=100)
    return seq, root


def test_layout(written):
    _, root = written
    for sub in ["camera/front_camera/00.jpg", "camera/back_camera/02.jpg", "camera/left_camera/intrinsics.json",
                "camera/front_camera/poses.json", "camera/front_camera/timestamps.json", "lidar/00.pkl.gz",
                "lidar/poses.json", "annotations/cuboids/01.pkl.gz"]:
        assert (root / sub).is_file(), sub
    intr = json.loads((root / "camera/front_camera/intrinsics.json").read_text())
    assert set(intr) == {"fx", "fy", "cx", "cy"}
    pose = json.loads((root / "camera/front_camera/poses.json").read_text())[0]
    assert set(pose) == {"position", "heading"} and set(pose["heading"]) == {"w", "x", "y", "z"}
    import pandas as pd
    df = pd.read_pickle(root / "lidar/00.pkl.gz", compression="gzip")
    assert list(df.columns) == ["x", "y", "z", "i", "t", "d"]


def test_roundtrip(written):
    seq, root = written
    got = load_pandaset(root)
    assert got.camera_names == seq.camera_names and len(got.frames) == 3
    for k in range(3):
        assert np.allclose(got.viewmats(k), seq.viewmats(k), atol=1e-9)
        fa, fb = seq.frames[k], got.frames[k]
        assert fb.timestamp == pytest.approx(fa.timestamp)
        assert np.allclose(fb.ego_to_world, fa.ego_to_world, atol=1e-12)
        for c in seq.camera_names:
            assert np.abs(fb.images[c] - fa.images[c]).mean() < 0.01  # JPEG q=100
        lw = fa.lidar.to_world(fa.ego_to_world)
        assert fb.lidar.frame == "world" and np.allclose(fb.lidar.points, lw.points, atol=1e-4)
        assert np.allclose(fb.lidar.intensity, lw.intensity, atol=1e-5)
        ba = {b.uuid: b for b in fa.boxes}
        for b in fb.boxes:
            a = ba[b.uuid]
            assert np.allclose(b.size, a.size) and np.allclose(b.center, a.center)
            assert np.allclose(quat_to_rotmat(b.quat), quat_to_rotmat(a.quat), atol=1e-9)
    assert np.allclose(got.Ks(), seq.Ks())
    for c in seq.cameras:
        assert np.allclose(got.camera(c.name).cam_to_ego, c.cam_to_ego, atol=1e-9)
    # track ids stable across frames
    ids = [{b.uuid: b.track_id for b in f.boxes} for f in got.frames]
    assert ids[0] == ids[1] == ids[2]
    sub = load_pandaset(root, cameras=["CAM_BACK", "front_camera"], frames=[2], load_lidar=False)
    assert sub.camera_names == ["CAM_BACK", "CAM_FRONT"] and len(sub.frames) == 1 and sub.frames[0].lidar is None


def test_errors(written, tmp_path):
    seq, root = written
    with pytest.raises(FileNotFoundError, match="sequence folder not found"):
        load_pandaset(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no 'camera' folder"):
        load_pandaset(tmp_path / "empty")
    with pytest.raises(ValueError, match="cameras: 'CAM_X' not found"):
        load_pandaset(root, cameras=["CAM_X"])
    with pytest.raises(ValueError, match="frames: index 7 out of range"):
        load_pandaset(root, frames=[7])
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    (bad / "camera/front_camera/intrinsics.json").write_text("{fx: 1")
    with pytest.raises(ValueError, match="intrinsics.json' is not valid JSON"):
        load_pandaset(bad)
    (bad / "camera/front_camera/intrinsics.json").write_text(json.dumps({"fx": 1}))
    with pytest.raises(ValueError, match="must hold numbers fx, fy, cx, cy"):
        load_pandaset(bad)
    shutil.copy(root / "camera/front_camera/intrinsics.json", bad / "camera/front_camera/intrinsics.json")
    (bad / "lidar/01.pkl.gz").write_bytes(gzip.compress(b"not a pickle"))
    with pytest.raises(ValueError, match=r"cannot read pickled DataFrame .*01\.pkl\.gz"):
        load_pandaset(bad)
    (bad / "lidar/poses.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"poses\.json"):
        load_pandaset(bad)
    poses = json.loads((root / "lidar/poses.json").read_text())
    poses[0]["heading"] = {"w": 1}
    (bad / "lidar/poses.json").write_text(json.dumps(poses))
    with pytest.raises(ValueError, match="pose must be"):
        load_pandaset(bad)
    with pytest.raises(ValueError, match="seq must be a DrivingSequence"):
        write_pandaset("seq", tmp_path / "x")


def test_semseg_labels_follow_the_points(tmp_path):
    """Per-point labels round-trip through annotations/semseg, are mapped from PandaSet's 42
    classes by name, and stay aligned with the points when another device's rows are dropped."""
    import pandas as pd

    from clsplat.data.pandaset import PANDASET_CLASSES, pandaset_class_to_clsplat
    from clsplat.data.scene import SEMANTIC_CLASSES

    seq = generate_sequence(height=16, width=32, num_frames=2, seed=3)
    road, other = SEMANTIC_CLASSES.index("road"), SEMANTIC_CLASSES.index("other")
    labels = []
    for f in seq.frames:
        p = f.lidar.to_world(f.ego_to_world).points
        labels.append(np.where((np.abs(p[:, 2]) < 0.05) & (np.abs(p[:, 1]) < 7), road, other).astype(np.uint8))
    seq.metadata["lidar_semantics"] = labels
    root = write_pandaset(seq, tmp_path / "002", jpeg_quality=90)
    # a second device (d = 1) with its own labels, interleaved: the loader must drop both together
    lid = pd.read_pickle(root / "lidar/00.pkl.gz", compression="gzip")
    sem = pd.read_pickle(root / "annotations/semseg/00.pkl.gz", compression="gzip")
    extra = lid.iloc[:50].copy()
    extra["d"] = 1
    pd.concat([extra, lid]).to_pickle(root / "lidar/00.pkl.gz", compression="gzip")
    pd.concat([pd.DataFrame({"class": np.full(50, 41)}), sem]).to_pickle(root / "annotations/semseg/00.pkl.gz",
                                                                          compression="gzip")
    got = load_pandaset(root)
    for k in range(2):
        assert got.frames[k].lidar.points.shape[0] == labels[k].shape[0]
        assert np.array_equal(got.metadata["lidar_semantics"][k], labels[k])
    assert len(PANDASET_CLASSES) == 42
    names = {v: pandaset_class_to_clsplat(v) for v in PANDASET_CLASSES.values()}
    assert names["Lane Line Marking"] == road and names["Road Barriers"] == other
    assert names["Other Vehicle - Pedicab"] == SEMANTIC_CLASSES.index("vehicle")
    assert names["Building"] == SEMANTIC_CLASSES.index("building")
    pd.DataFrame({"class": np.zeros(3, np.int64)}).to_pickle(root / "annotations/semseg/01.pkl.gz", compression="gzip")
    with pytest.raises(ValueError, match="one row per LiDAR point"):
        load_pandaset(root)


def test_tracker_noise_boxes_are_the_written_cuboids(tmp_path):
    """Issue 36's noisy PandaSet-format streets: after ``add_tracker_noise`` the cuboids written and
    read back are the tracker's boxes (yaw-only, so PandaSet can hold them), not the exact ones kept
    in ``metadata["exact_boxes"]``; uuids, sizes and track ids are unchanged."""
    from clsplat.data.synthetic.views import TrackerNoise, add_tracker_noise
    seq = generate_sequence(height=16, width=32, num_frames=3, seed=2, lidar=False)
    add_tracker_noise(seq, TrackerNoise(), seed=2)
    got = load_pandaset(write_pandaset(seq, tmp_path / "001"), load_lidar=False)
    moved = 0.0
    for k, (fa, fb) in enumerate(zip(seq.frames, got.frames)):
        noisy = {b.uuid: b for b in fa.boxes}
        exact = {b.uuid: b for b in seq.metadata["exact_boxes"][k].values()}
        assert {b.uuid for b in fb.boxes} == set(noisy) == set(exact)
        for b in fb.boxes:
            a = noisy[b.uuid]
            assert np.allclose(b.center, a.center, atol=1e-9) and np.allclose(b.size, exact[b.uuid].size)
            assert np.allclose(quat_to_rotmat(b.quat), quat_to_rotmat(a.quat), atol=1e-9)
            moved = max(moved, float(np.linalg.norm(b.center - exact[b.uuid].center)))
    assert moved > 0.01
