"""clsplat/viewer/server.py: the viewer in a real browser (Debian's chromium, headless, WebGL
through SwiftShader) and without one.

The browser test loads the page ``Viewer`` serves for a small two-colour ``.ply``, takes a
screenshot over the DevTools protocol (not blank; the scene's red and blue where the scene is, red
left of blue as the first camera sees them), then moves the browser's camera through viser's API
to the far side and checks that clsplat's server-side render follows (the clusters swap sides).
It skips where chromium is absent, and fails instead when CLSPLAT_REQUIRE_BROWSER=1 (.ci/run).
"""
import os
import time
import urllib.request

import numpy as np
import pytest
import torch

pytest.importorskip("viser", reason="the view extra (pip install 'clsplat[view]') is not installed")

from clsplat.viewer.browser import HeadlessChromium, find_chromium  # noqa: E402
from clsplat.viewer.scene import ViewCamera, look_at_viewmat, scene_from_ply  # noqa: E402
from clsplat.viewer.server import Viewer  # noqa: E402

_CHROMIUM = find_chromium()
_REQUIRED = os.environ.get("CLSPLAT_REQUIRE_BROWSER") == "1"
needs_browser = pytest.mark.skipif(_CHROMIUM is None and not _REQUIRED,
                                   reason="chromium is not installed (apt-get install chromium)")


def _wait(pred, timeout: float, what: str):
    t0 = time.time()
    while time.time() - t0 < timeout:
        v = pred()
        if v:
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _red_blue(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (r > 150) & (g < 90) & (b < 90), (b > 150) & (r < 90) & (g < 90)


@pytest.mark.slow   # drives a headless browser
@pytest.mark.browser
@needs_browser
def test_chromium_shows_the_scene_and_the_server_render_follows_the_camera(two_colour_ply, tmp_path):
    assert _CHROMIUM is not None, "CLSPLAT_REQUIRE_BROWSER=1 but no chromium on PATH"
    ply, cam = two_colour_ply
    scene = scene_from_ply(ply)
    K = np.diag([10.0, 10.0, 1.0]) @ cam.K   # the fixture's camera at 640x480
    scene.cameras = [ViewCamera("front", K, cam.viewmat, 640, 480)]
    viewer = Viewer(scene, port=0, render_width=160, rest_s=0.3)
    browser = HeadlessChromium(viewer.url, 1000, 640)
    try:
        _wait(lambda: len(viewer.clients()) > 0, 120, "the browser to connect")
        cid = next(iter(viewer.clients()))
        _wait(lambda: cid in viewer.last, 120, "the first exact render")
        # drawn from the start view, the pose the browser reports, not from viser's placeholder camera
        start, first = viewer.server.initial_camera, viewer.last[cid]
        np.testing.assert_allclose(np.linalg.inv(first["viewmat"])[:3, 3], start.position, atol=1e-6)
        np.testing.assert_allclose(first["viewmat"], viewer.client_camera(viewer.clients()[cid]).viewmat, atol=1e-6)
        time.sleep(3)  # let WebGL draw the splats
        shots: list = []

        def splats_drawn() -> bool:   # WebGL in software takes a few frames to draw the splats
            shots.append(browser.screenshot())
            return int(_red_blue(shots[-1])[0].sum()) > 200
        _wait(splats_drawn, 60, "the splats in the screenshot")
        shot = shots[-1]
        from clsplat.io.images import write_image
        write_image(os.environ.get("CLSPLAT_VIEWER_SCREENSHOT", str(tmp_path / "screenshot.png")), shot / 255.0)
        assert shot.std() > 10, "the screenshot is blank"
        red, blue = _red_blue(shot[:, :480])   # the 3D view; the GUI panel is on the right
        assert red.sum() > 200 and blue.sum() > 200, (red.sum(), blue.sum())
        assert np.nonzero(red)[1].mean() < np.nonzero(blue)[1].mean()   # red left of blue, as the camera sees them
        first = viewer.last[cid]
        fr, fb = _red_blue((first["image"] * 255).astype(np.uint8))
        assert np.nonzero(fr)[1].mean() < np.nonzero(fb)[1].mean()
        # move the browser's camera through viser's API to the far side: the server render follows
        n = viewer.renders
        back = ViewCamera("back", K, look_at_viewmat([0, 4, 0.5], [0, 0, 0]), 640, 480)
        viewer.set_client_camera(viewer.clients()[cid], back)
        _wait(lambda: viewer.renders > n and viewer.last[cid]["time"] > first["time"], 120, "a new exact render")
        second = viewer.last[cid]
        assert not np.allclose(second["viewmat"], first["viewmat"])
        np.testing.assert_allclose(np.linalg.inv(second["viewmat"])[:3, 3], [0, 4, 0.5], atol=1e-3)
        sr, sb = _red_blue((second["image"] * 255).astype(np.uint8))
        assert sr.sum() > 20 and sb.sum() > 20
        assert np.nonzero(sr)[1].mean() > np.nonzero(sb)[1].mean()   # from behind, red is on the right
    finally:
        browser.close()
        viewer.stop()


class _SocketClient:
    """A browser's side of viser's websocket, without the browser: it reports camera poses (the
    ``ViewerCameraMessage`` viser's web client sends, msgpack-encoded) and reads nothing back."""

    def __init__(self, url: str) -> None:
        import viser
        from websockets.sync.client import connect

        self.ws = connect(url.replace("http://", "ws://"), subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None)

    def report(self, eye, target, fov: float) -> None:
        import msgspec
        import viser.transforms as vtf
        from viser import _messages

        c2w = np.linalg.inv(look_at_viewmat(eye, target))
        m = _messages.ViewerCameraMessage(tuple(vtf.SO3.from_matrix(c2w[:3, :3]).wxyz), tuple(map(float, eye)),
                                          float(fov), 0.01, 1000.0, 480, 640, tuple(map(float, target)),
                                          (0.0, 0.0, 1.0))
        self.ws.send(msgspec.msgpack.encode(m.as_serializable_dict()))

    def close(self) -> None:
        self.ws.close()


def test_the_first_exact_render_waits_for_the_start_view(two_colour_ply):
    """A browser reports viser's placeholder camera first and the start view once it has applied
    it: the first exact render is drawn from the start view, the pose the browser then reports
    (viewmat equal to 1e-9), not from the placeholder, however long the start view takes. A
    client whose camera never reaches the start view (a URL's initialCameraPosition) is rendered
    after ``start_wait_s``; without the wait (start_wait_s=0) the placeholder is what is drawn."""
    ply, cam = two_colour_ply
    scene = scene_from_ply(ply)
    scene.cameras = [cam]
    placeholder = ([3.0, 3.0, 0.2], [0.0, 0.0, 0.2], 75 * np.pi / 180)
    for wait in (10.0, 0.0):
        v = Viewer(scene, port=0, render_width=64, rest_s=0.2, start_wait_s=wait)
        start = v.server.initial_camera
        client = _SocketClient(v.url)
        try:
            client.report(*placeholder)
            _wait(lambda: len(v.clients()) == 1, 60, "the client to connect")
            cid = next(iter(v.clients()))
            time.sleep(1.5)                       # the placeholder has rested 7x rest_s
            if wait == 0.0:
                _wait(lambda: cid in v.last, 60, "the first exact render")
                np.testing.assert_allclose(np.linalg.inv(v.last[cid]["viewmat"])[:3, 3], placeholder[0], atol=1e-9)
                continue
            assert v.renders == 0 and cid not in v.last
            client.report(start.position, start.look_at, start.fov)
            _wait(lambda: cid in v.last, 60, "the first exact render")
            time.sleep(0.5)
            assert v.renders == 1
            first = v.last[cid]["viewmat"]
            np.testing.assert_allclose(first, v.client_camera(v.clients()[cid]).viewmat, atol=1e-9)
            np.testing.assert_allclose(first, look_at_viewmat(start.position, start.look_at), atol=1e-9)
            # a second client that never shows the start view is rendered once the wait is over
            v.start_wait_s = 1.0
            other = _SocketClient(v.url)
            try:
                other.report(*placeholder)
                _wait(lambda: len(v.last) == 2, 60, "the second client's exact render")
                oid = next(c for c in v.last if c != cid)
                np.testing.assert_allclose(np.linalg.inv(v.last[oid]["viewmat"])[:3, 3], placeholder[0], atol=1e-9)
            finally:
                other.close()
        finally:
            client.close()
            v.stop()


def test_viewer_without_a_browser(two_colour_ply):
    ply, cam = two_colour_ply
    scene = scene_from_ply(ply)
    scene.cameras = [cam]
    v = Viewer(scene, port=0)
    try:
        assert v.url.startswith("http://127.0.0.1:") and v.port > 0
        page = urllib.request.urlopen(v.url, timeout=30).read()
        assert b"html" in page.lower()
        views = v.views()
        # lane change m metres: the first camera's centre moved m to its left (-x of the camera), same orientation
        c0 = cam.cam_to_world
        for m in (1, 2, 3):
            c = views[f"lane change {m} m (front)"].cam_to_world
            np.testing.assert_allclose(c[:3, 3], c0[:3, 3] - m * c0[:3, 0], atol=1e-9)
            np.testing.assert_allclose(c[:3, :3], c0[:3, :3], atol=1e-12)
        v.set_gaussians(scene_from_ply(ply))
        # another model input: cameras, boxes and depth maps are replaced, not added to
        other = scene_from_ply(ply)
        other.cameras = [cam, ViewCamera("back", cam.K, look_at_viewmat([0, 4, 0.5], [0, 0, 0]), 64, 48)]
        other.depths = {"front": np.zeros((48, 64, 3), np.float32)}
        v.set_scene(other)
        assert len(v._camera_handles) == 2 and len(v._depth_handles) == 1 and v.scene is other
        # a training run's refresh: the same depth map names update the images in place
        h = v._depth_handles[0]
        other.depths = {"front": np.ones((48, 64, 3), np.float32)}
        v.set_depths(other)
        assert v._depth_handles == [h] and (h.image == 255).all()
        v.set_scene(scene_from_ply(ply))
        assert v._camera_handles == [] and v._depth_handles == []
    finally:
        v.stop()
    # the port is free again once stopped (for a restart: connections in TIME_WAIT do not count)
    from clsplat.viewer.server import check_port_free
    check_port_free("127.0.0.1", v.port)


def test_driving_controls_without_a_browser(two_colour_ply):
    """The shared controls' actions: LiDAR and box toggles, the time slider (a moving object and its
    box placed at t, recorded cameras kept), the far side of the first box at the slider's time, and
    the model-input dropdown rerunning a model."""
    from clsplat.viewer.scene import ViewBox

    ply, cam = two_colour_ply

    def at(t: float, extras: bool = True):
        sc = scene_from_ply(ply)
        sc.means[:200, 0] += t        # the red cluster drives along +x at 1 m/s
        sc.boxes = [ViewBox("car 7", np.array([-0.8 + t, 0, 0]), np.array([1.0, 0.8, 0.6]), np.array([1.0, 0, 0, 0]), t)]
        if extras:
            sc.cameras = [cam]
            sc.lidar = np.random.default_rng(0).normal(size=(50, 3))
            sc.times = [0.0, 1.0, 2.0]
            sc.at_time = lambda t: at(t, False)
            sc.variants = ["sample 1"]
            sc.variant = lambda name: scene_from_ply(ply)
        return sc

    v = Viewer(at(0.0), port=0)
    try:
        assert v._lidar is not None and not v._lidar.visible
        v.show_lidar(True)
        assert v._lidar.visible
        v.show_boxes(False)
        assert len(v._box_handles) == 1 and not v._box_handles[0].visible
        v.show_boxes(True)
        far0 = v.views()["far side of car 7"]
        v.set_time(2.0)
        assert torch.allclose(v.scene.means[:200, 0], scene_from_ply(ply).means[:200, 0] + 2.0)
        np.testing.assert_allclose(v.scene.boxes[0].center, [1.2, 0, 0])
        assert v.scene.cameras == [cam] and "lane change 2 m (front)" in v.views()
        far = v.views()["far side of car 7"]
        # the far side: beyond the box as the first camera sees it, looking at the box where it is at t
        eye0, eye, centre = cam.cam_to_world[:3, 3], far.cam_to_world[:3, 3], np.array([1.2, 0, 0])
        assert np.dot(eye - centre, centre - eye0) > 0
        p = far.K @ (far.viewmat[:3, :3] @ centre + far.viewmat[:3, 3])
        np.testing.assert_allclose(p[:2] / p[2], [far.width / 2, far.height / 2], atol=1e-6)
        assert not np.allclose(far.viewmat, far0.viewmat)
        assert v.run_variant("no such input").startswith("no such input: not an input")
        assert "Gaussians in" in v.run_variant("sample 1") and v.scene.boxes == []
    finally:
        v.stop()
