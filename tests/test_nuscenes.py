"""nuScenes writer / loader (built-in JSON reader and the optional devkit path)."""
import json
import sys
import types

import numpy as np
import pytest

from clsplat.data.nuscenes import TABLE_NAMES, load_nuscenes_sample, load_nuscenes_scene, load_tables, write_nuscenes
from clsplat.data.scene import CAMERA_NAMES, quat_to_rotmat
from clsplat.data.synthetic import generate_sequence

VERSION = "v1.0-synth"
# fields of each table, as in the nuScenes v1.0 schema
SCHEMA = {
    "category": {"token", "name", "description"},
    "attribute": {"token", "name", "description"},
    "visibility": {"token", "level", "description"},
    "instance": {"token", "category_token", "nbr_annotations", "first_annotation_token", "last_annotation_token"},
    "sensor": {"token", "channel", "modality"},
    "calibrated_sensor": {"token", "sensor_token", "translation", "rotation", "camera_intrinsic"},
    "ego_pose": {"token", "timestamp", "rotation", "translation"},
    "log": {"token", "logfile", "vehicle", "date_captured", "location"},
    "scene": {"token", "log_token", "nbr_samples", "first_sample_token", "last_sample_token", "name", "description"},
    "sample": {"token", "timestamp", "prev", "next", "scene_token"},
    "sample_data": {"token", "sample_token", "ego_pose_token", "calibrated_sensor_token", "timestamp", "fileformat",
                    "is_key_frame", "height", "width", "filename", "prev", "next"},
    "sample_annotation": {"token", "sample_token", "instance_token", "visibility_token", "attribute_tokens",
                          "translation", "size", "rotation", "prev", "next", "num_lidar_pts", "num_radar_pts"},
    "map": {"token", "log_tokens", "category", "filename"},
}


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    seq = generate_sequence(height=24, width=48, num_frames=5, seed=2)
    root = tmp_path_factory.mktemp("nus")
    write_nuscenes(seq, root, VERSION, keyframe_every=2, jpeg_quality=100)
    return seq, root


def test_tables_schema(written):
    _, root = written
    for name in TABLE_NAMES:
        recs = json.loads((root / VERSION / f"{name}.json").read_text())
        assert recs, name
        for r in recs:
            assert SCHEMA[name] <= set(r), (name, SCHEMA[name] - set(r))
    t = load_tables(root, VERSION)
    assert len(t.tables["sample"]) == 3  # frames 0, 2, 4 are key frames
    assert len(t.tables["sample_data"]) == 5 * 7  # 6 cameras + LIDAR_TOP, key frames and sweeps
    for sd in t.tables["sample_data"]:
        assert (root / sd["filename"]).is_file()


def _check_frame(got, k_got, seq, k_seq, img_tol=0.01):
    assert np.allclose(got.viewmats(k_got), seq.viewmats(k_seq), atol=1e-9)
    fa, fb = seq.frames[k_seq], got.frames[k_got]
    assert fb.timestamp == pytest.approx(fa.timestamp, abs=1e-6)
    for c in CAMERA_NAMES:
        assert np.abs(fb.images[c] - fa.images[c]).mean() < img_tol


def test_scene_roundtrip(written):
    seq, root = written
    got = load_nuscenes_scene(root, VERSION, scene=0)
    assert got.camera_names == list(CAMERA_NAMES) and len(got.frames) == 3
    for kg, ks in zip(range(3), (0, 2, 4)):
        _check_frame(got, kg, seq, ks)
        fa, fb = seq.frames[ks], got.frames[kg]
        lw = fa.lidar.to_world(fa.ego_to_world)
        assert np.allclose(fb.lidar.points, lw.points, atol=1e-4) and np.array_equal(fb.lidar.ring, lw.ring)
        ba = {b.track_id: b for b in fa.boxes}
        assert len(fb.boxes) == len(fa.boxes)
        for b in fb.boxes:
            a = ba[b.track_id]  # instances are written in track-id order, ids 1..n
            assert b.label == "car" and np.allclose(b.size, a.size) and np.allclose(b.center, a.center)
            assert np.allclose(quat_to_rotmat(b.quat), quat_to_rotmat(a.quat), atol=1e-9)
    for c in seq.cameras:
        assert np.allclose(got.camera(c.name).K, c.K) and np.allclose(got.camera(c.name).cam_to_ego, c.cam_to_ego)
    by_name = load_nuscenes_scene(root, VERSION, scene=seq.name, cameras=["CAM_BACK"], load_lidar=False)
    assert by_name.camera_names == ["CAM_BACK"] and by_name.frames[0].lidar is None


def test_sample_with_prev_next_sweeps(written):
    seq, root = written
    t = load_tables(root, VERSION)
    middle = t.tables["sample"][1]["token"]  # frame 2; neighbours are the sweeps 1 and 3
    got = load_nuscenes_sample(root, VERSION, middle, neighbors=1)
    assert len(got.frames) == 3 and got.metadata["centre_index"] == 1
    for kg, ks in zip(range(3), (1, 2, 3)):
        _check_frame(got, kg, seq, ks)
    assert got.frames[1].boxes and not got.frames[0].boxes and got.frames[1].lidar is not None
    got2 = load_nuscenes_sample(root, VERSION, middle, neighbors=2)
    assert len(got2.frames) == 5
    with pytest.raises(ValueError, match="fewer than 3 previous frames"):
        load_nuscenes_sample(root, VERSION, middle, neighbors=3)


def test_errors(written, tmp_path):
    seq, root = written
    with pytest.raises(FileNotFoundError, match="dataroot not found"):
        load_tables(tmp_path / "none", VERSION)
    with pytest.raises(FileNotFoundError, match="version folder not found"):
        load_tables(root, "v1.0-trainval")
    with pytest.raises(ValueError, match="scene 'nope' not found"):
        load_nuscenes_scene(root, VERSION, scene="nope")
    with pytest.raises(ValueError, match="sample_token 'abc' not found"):
        load_nuscenes_sample(root, VERSION, "abc")
    import shutil
    bad = tmp_path / "bad"
    shutil.copytree(root, bad)
    (bad / VERSION / "ego_pose.json").write_text("[{")
    with pytest.raises(ValueError, match="ego_pose.json' is not valid JSON"):
        load_tables(bad, VERSION)
    (bad / VERSION / "ego_pose.json").unlink()
    with pytest.raises(FileNotFoundError, match="table missing.*ego_pose.json"):
        load_tables(bad, VERSION)
    with pytest.raises(ValueError, match="keyframe_every must be a positive int"):
        write_nuscenes(seq, tmp_path / "w", keyframe_every=0)


def test_devkit_missing_message(written, monkeypatch):
    _, root = written
    monkeypatch.setitem(sys.modules, "nuscenes", None)
    monkeypatch.setitem(sys.modules, "nuscenes.nuscenes", None)
    with pytest.raises(ImportError, match="nuscenes-devkit"):
        load_nuscenes_scene(root, VERSION, use_devkit=True)


def test_devkit_path_with_stand_in(written, monkeypatch):
    """The devkit back end only needs ``NuScenes(version, dataroot).<table>`` lists; check it with a
    stand-in module (the real devkit 1.2.0 needs numpy<2 and is not installed here)."""
    seq, root = written

    class NuScenes:
        def __init__(self, version, dataroot, verbose=True):
            for name in TABLE_NAMES:
                setattr(self, name, json.loads((root / version / f"{name}.json").read_text()))

    pkg = types.ModuleType("nuscenes")
    mod = types.ModuleType("nuscenes.nuscenes")
    mod.NuScenes = NuScenes
    monkeypatch.setitem(sys.modules, "nuscenes", pkg)
    monkeypatch.setitem(sys.modules, "nuscenes.nuscenes", mod)
    got = load_nuscenes_scene(root, VERSION, use_devkit=True)
    ref = load_nuscenes_scene(root, VERSION)
    for k in range(len(ref.frames)):
        assert np.array_equal(got.viewmats(k), ref.viewmats(k))
        assert np.array_equal(got.images(k), ref.images(k))
