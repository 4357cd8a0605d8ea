"""clsplat/viewer/render.py and ``clsplat render``: the exact render shows the scene's colours
where the scene is, a moved camera sees it elsewhere, and the batch command writes one image per
camera (atomically, with per-view times) from every camera-file layout."""
import json

import numpy as np

from clsplat.cli import main
from clsplat.io.images import read_image
from clsplat.viewer.cameras import cameras_to_json
from clsplat.viewer.render import render_view
from clsplat.viewer.scene import ViewCamera, default_camera, look_at_viewmat, scene_from_ply


def _halves(img):
    w = img.shape[1] // 2
    return img[:, :w].mean((0, 1)), img[:, w:].mean((0, 1))


def test_exact_render_puts_the_colours_where_the_scene_is(two_colour_ply):
    ply, cam = two_colour_ply
    scene = scene_from_ply(ply)
    img, secs = render_view(scene, cam)
    assert img.shape == (48, 64, 3) and secs > 0
    left, right = _halves(img)
    assert left[0] > 0.1 and left[0] > 5 * left[2]      # red cluster at x < 0: the camera's left
    assert right[2] > 0.1 and right[2] > 5 * right[0]   # blue at x > 0: its right
    # from the other side (+y looking back) the clusters swap sides
    back = ViewCamera("back", cam.K, look_at_viewmat([0, 4, 0.5], [0, 0, 0]), 64, 48)
    left, right = _halves(render_view(scene, back)[0])
    assert left[2] > 5 * left[0] and right[0] > 5 * right[2]
    # a white background shows where no Gaussian is: the corners
    w = render_view(scene, cam, background=(1, 1, 1))[0]
    np.testing.assert_allclose(w[0, 0], 1, atol=0.02)


def test_default_camera_sees_the_scene(two_colour_ply):
    scene = scene_from_ply(two_colour_ply[0])
    img = render_view(scene, default_camera(scene, 64, 48))[0]
    assert img.max() > 0.3


def test_render_command_writes_each_view(two_colour_ply, tmp_path, capsys):
    ply, cam = two_colour_ply
    back = ViewCamera("back", cam.K, look_at_viewmat([0, 4, 0.5], [0, 0, 0]), 64, 48)
    cams = tmp_path / "cams.json"
    cams.write_text(cameras_to_json([cam, back]))
    out = tmp_path / "out"
    assert main(["render", str(ply), "--cameras", str(cams), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "2/2" in err and "back:" in err and " ms" in err           # progress bar and per-view time
    assert sorted(p.name for p in out.iterdir()) == ["back.png", "front.png", "render_times.json"]  # no temp files
    t = json.loads((out / "render_times.json").read_text())
    assert [v["name"] for v in t["views"]] == ["front", "back"] and all(v["render_s"] > 0 for v in t["views"])
    scene = scene_from_ply(ply)
    np.testing.assert_allclose(read_image(out / "front.png"), render_view(scene, cam)[0], atol=1 / 255 + 1e-6)


def test_render_command_bad_input(two_colour_ply, tmp_path, capsys):
    ply, cam = two_colour_ply
    cams = tmp_path / "cams.json"
    cams.write_text(cameras_to_json([cam]))
    for args, match in ((["render", str(ply), "--cameras", str(tmp_path / "x.json"), "--out", str(tmp_path)],
                         "--cameras"),
                        (["render", str(cams), "--cameras", str(cams), "--out", str(tmp_path / "o")], "not a scene"),
                        (["render", str(ply), "--cameras", str(cams), "--out", str(ply)], "--out"),
                        (["render", str(ply), "--cameras", str(cams), "--out", str(tmp_path / "o"),
                          "--background", "2,0,0"], "--background")):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert match in err and len(err.splitlines()) == 1 and err.startswith("clsplat render:")
