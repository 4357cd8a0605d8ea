"""clsplat/viewer/cameras.py: the three camera-file layouts give the same cameras, and a bad file
is a one-line ValueError naming --cameras and the camera."""
import json

import numpy as np
import pytest

from clsplat.viewer.cameras import cameras_to_json, read_cameras
from clsplat.viewer.scene import look_at_viewmat

K = [[50.0, 0, 32.0], [0, 60.0, 24.0], [0, 0, 1]]


def _views():
    return [look_at_viewmat([0, -4, 0.5], [0, 0, 0]), look_at_viewmat([3, 1, 2], [0, 0, 0.2])]


def test_clsplat_layout_round_trips(tmp_path):
    V = _views()
    f = tmp_path / "c.json"
    f.write_text(json.dumps([{"name": "a", "width": 64, "height": 48, "K": K, "world_to_camera": V[0].tolist()},
                             {"width": 64, "height": 48, "fx": 50, "fy": 60, "cx": 32, "cy": 24,
                              "camera_to_world": np.linalg.inv(V[1]).tolist()}]))
    cams = read_cameras(f)
    assert [c.name for c in cams] == ["a", "view_0001"]
    for c, v in zip(cams, V):
        np.testing.assert_allclose(c.viewmat, v, atol=1e-12)
        np.testing.assert_allclose(c.K, K)
    g = tmp_path / "g.json"
    g.write_text(cameras_to_json(cams))
    again = read_cameras(g)
    np.testing.assert_allclose(again[1].viewmat, cams[1].viewmat)


def test_inria_and_nerfstudio_layouts_give_the_same_cameras(tmp_path):
    V = _views()
    inria = [{"id": i, "img_name": f"im{i}", "width": 64, "height": 48, "position": np.linalg.inv(v)[:3, 3].tolist(),
              "rotation": np.linalg.inv(v)[:3, :3].tolist(), "fx": 50.0, "fy": 60.0} for i, v in enumerate(V)]
    (tmp_path / "cameras.json").write_text(json.dumps(inria))
    frames = []
    for i, v in enumerate(V):
        c2w = np.linalg.inv(v)
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL, as nerfstudio stores it
        frames.append({"file_path": f"images/frame_{i}.png", "transform_matrix": c2w.tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps({"fl_x": 50, "fl_y": 60, "cx": 32, "cy": 24, "w": 64,
                                                          "h": 48, "frames": frames}))
    for name, names in (("cameras.json", ["im0", "im1"]), ("transforms.json", ["frame_0", "frame_1"])):
        cams = read_cameras(tmp_path / name)
        assert [c.name for c in cams] == names
        for c, v in zip(cams, V):
            np.testing.assert_allclose(c.viewmat, v, atol=1e-9)
            np.testing.assert_allclose(c.K, K)
            assert (c.width, c.height) == (64, 48)


@pytest.mark.parametrize("doc, match", [
    ("not json", "not JSON"),
    ("[]", "non-empty list"),
    ('[{"width": 64, "height": 48, "K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]', "camera 0: needs 'world_to_camera'"),
    ('[{"width": 64, "height": 48, "fx": 50, "fy": 50, "cx": 1, "world_to_camera": '
     '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]', "camera 0: missing 'cy'"),
    ('[{"width": 0, "height": 48, "fx": 5, "fy": 5, "cx": 1, "cy": 1, "world_to_camera": '
     '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]', "width and height"),
    ('[{"width": 8, "height": 8, "fx": 5, "fy": 5, "cx": 1, "cy": 1, "world_to_camera": '
     '[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]', "not orthonormal"),
    ('{"fl_x": 5, "w": 8, "h": 8, "k1": 0.1, "frames": [{"transform_matrix": '
     '[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "pinhole cameras only"),
])
def test_bad_camera_files_are_one_line_errors(tmp_path, doc, match):
    f = tmp_path / "bad.json"
    f.write_text(doc)
    with pytest.raises(ValueError, match=match) as e:
        read_cameras(f)
    assert str(e.value).startswith(f"--cameras {str(f)!r}") and "\n" not in str(e.value)


def test_missing_camera_file(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        read_cameras(tmp_path / "nope.json")
