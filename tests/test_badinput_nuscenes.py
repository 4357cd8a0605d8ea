"""Bad nuScenes tables: loops, paths outside the data root, malformed records and hostile JSON
give a ValueError naming the table or the file, never a hang, a read outside the root or a
KeyError/TypeError/RecursionError."""
import json
import shutil

import pytest

from clsplat.data.nuscenes import load_nuscenes_sample, load_nuscenes_scene, write_nuscenes
from clsplat.data.synthetic import generate_sequence

VERSION = "v1.0-synth"
CAMS = ["CAM_FRONT"]


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    seq = generate_sequence(height=16, width=24, num_frames=3, seed=3)
    root = tmp_path_factory.mktemp("nus")
    write_nuscenes(seq, root, VERSION, keyframe_every=1)
    return root


@pytest.fixture
def root(pristine, tmp_path):
    dst = tmp_path / "nus"
    shutil.copytree(pristine, dst)
    return dst


def edit(root, table, fn):
    p = root / VERSION / f"{table}.json"
    recs = json.loads(p.read_text())
    fn(recs)
    p.write_text(json.dumps(recs))


def load(root):
    return load_nuscenes_scene(root, VERSION, 0, cameras=CAMS, load_lidar=True)


def test_pristine_loads(root):
    assert len(load(root).frames) == 3


# --- hang -----------------------------------------------------------------------------------
def test_sample_whose_next_points_to_itself(root):
    def loop(recs):
        recs[1]["next"] = recs[1]["token"]
    edit(root, "sample", loop)
    with pytest.raises(ValueError, match=r"'sample'.*'next' links .* loop"):
        load(root)


def test_longer_next_cycle(root):
    def loop(recs):
        recs[2]["next"] = recs[0]["token"]
    edit(root, "sample", loop)
    with pytest.raises(ValueError, match="loop"):
        load(root)


# --- unsafe ---------------------------------------------------------------------------------
@pytest.mark.parametrize("bad", ["../outside.jpg", "samples/../../outside.jpg", "/etc/passwd"])
def test_filename_outside_the_data_root_refused(root, bad):
    (root.parent / "outside.jpg").write_bytes((root / "maps").iterdir().__next__().read_bytes())

    def escape(recs):
        for r in recs:
            if "CAM_FRONT" in r["filename"]:
                r["filename"] = bad
    edit(root, "sample_data", escape)
    with pytest.raises(ValueError, match=r"sample_data .* filename: .*(outside the data root|absolute path)"):
        load(root)


def test_symlink_out_of_the_root_refused(root, tmp_path):
    secret = tmp_path / "secret"
    secret.mkdir()
    (root / "samples" / "link").symlink_to(secret)

    def escape(recs):
        for r in recs:
            if "CAM_FRONT" in r["filename"]:
                r["filename"] = "samples/link/x.jpg"
    edit(root, "sample_data", escape)
    with pytest.raises(ValueError, match="outside the data root"):
        load(root)


# --- unclear errors: malformed fields and JSON ------------------------------------------------
@pytest.mark.parametrize("table,field,value", [
    ("sample_data", "calibrated_sensor_token", None), ("sample_data", "ego_pose_token", 5),
    ("sample_data", "filename", None), ("sample_data", "filename", 7),
    ("ego_pose", "rotation", "abc"), ("ego_pose", "translation", None),
    ("calibrated_sensor", "camera_intrinsic", [[1, 2], [3]]), ("scene", "first_sample_token", 3),
    ("sample_annotation", "size", None),
])
def test_malformed_field(root, table, field, value):
    def bad(recs):
        for r in recs:
            r[field] = value
    edit(root, table, bad)
    with pytest.raises(ValueError, match=rf"(nuScenes|{table}|sample_data|calibrated_sensor|ego_pose)"):
        load(root)


@pytest.mark.parametrize("field", ["token", "channel"])
def test_missing_field(root, field):
    def drop(recs):
        for r in recs:
            r.pop(field, None)
    edit(root, "sensor", drop)
    with pytest.raises(ValueError, match="nuScenes"):
        load(root)


@pytest.mark.parametrize("text,what", [("[" * 100000 + "]" * 100000, "nested too deeply"),
                                       ("[" + "9" * 10000 + "]", "not valid JSON"),
                                       ('[{"token": 1}]', "list of records with a 'token'"),
                                       ("{}", "list of records")])
def test_hostile_json(root, text, what):
    (root / VERSION / "sample.json").write_text(text)
    with pytest.raises(ValueError, match=rf"sample\.json.*{what}"):
        load(root)


@pytest.mark.parametrize("dataroot,version", [(None, VERSION), (3, VERSION), ("x", None)])
def test_none_paths(dataroot, version):
    with pytest.raises(ValueError, match="^dataroot, version"):
        load_nuscenes_scene(dataroot, version)


def test_sample_with_prev_loop_still_bounded(root):
    """prev/next walks in load_nuscenes_sample are bounded by ``neighbors``, loops or not."""
    tok = json.loads((root / VERSION / "sample.json").read_text())[1]["token"]
    seq = load_nuscenes_sample(root, VERSION, tok, cameras=CAMS, neighbors=1)
    assert len(seq.frames) == 3


@pytest.mark.parametrize("field,value,what", [
    ("size", [1.0, 2.0], r"field 'size' must be a list of 3 numbers, got \[1.0, 2.0\]"),
    ("size", [1.0, 0.0, 2.0], r"field 'size' must be positive"),
    ("size", ["a", 1, 1], r"field 'size' must hold numbers"),
    ("rotation", [0, 0, 0, 0], r"field 'rotation' is a zero quaternion"),
    ("rotation", [1, 0, 0], r"field 'rotation' must be a list of 4 numbers"),
    ("translation", [1.0, float("nan"), 0.0], r"field 'translation' must be finite, got \[1.0, nan, 0.0\]"),
    ("translation", None, r"field 'translation' must be a list of 3 numbers, got None"),
])
def test_a_bad_annotation_names_the_table_the_token_and_the_field(root, field, value, what):
    token = []

    def bad(recs):
        recs[0][field] = value
        token.append(recs[0]["token"])
    edit(root, "sample_annotation", bad)
    # json.dumps writes NaN as a bare NaN token, which Python's JSON reader accepts, as nuScenes files might hold
    with pytest.raises(ValueError, match=rf"^sample_annotation '{token[0]}': {what}"):
        load(root)
