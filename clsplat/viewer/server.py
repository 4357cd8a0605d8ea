"""The browser viewer behind ``clsplat view``: a viser server showing a :class:`~.scene.ViewScene`.

Two renderers side by side: the browser draws the Gaussians with viser's WebGL splats (fluid,
DC colour only, one global depth sort per frame); the server renders the current camera exactly
with :func:`clsplat.rasterization` (:func:`~.render.render_view`) on the chosen OpenCL device,
on demand ("Render now") and whenever the camera has rested for ``rest_s`` seconds, and shows
it in the side panel (or, toggled, as the view's background) with its render time. A browser
that has just connected reports viser's placeholder camera first and the start view only once it
has applied it: its first exact render waits for the start view (at most ``start_wait_s``).

Driving extras, where the scene has them: recorded cameras as frusta with their images (click
"go to camera"), the ego trajectory, LiDAR points (toggle), tracked boxes, a time slider that
re-places moving objects, and the benchmark views (lane change 1-3 m from the first camera,
far side of the first box).

It serves nothing but the scene: viser's client page and its websocket, bound to ``host``
(127.0.0.1 by default). Needs the ``view`` extra (viser).
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import socket
import sys
import threading
import time
from typing import Any

import numpy as np

from .render import render_view
from .scene import ViewCamera, ViewScene, covariances, default_camera

__all__ = ["Viewer", "check_port_free"]


def check_port_free(host: str, port: int, args: tuple[str, str] = ("--host", "--port")) -> None:
    """ValueError naming the port argument (or the host's) when nothing can listen on (host, port);
    ``args``: the two arguments' names on the command line (``clsplat train --view``: --view-host, --view-port)."""
    if not (isinstance(port, int) and 0 <= port <= 65535):
        raise ValueError(f"{args[1]}: expected 0..65535, got {port!r}")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as e:
        raise ValueError(f"{args[0]} {host!r}: cannot be resolved ({e.strerror})") from None
    fam, _, _, _, addr = infos[0]
    s = socket.socket(fam, socket.SOCK_STREAM)
    # as the server will (asyncio's default on POSIX): connections of a stopped viewer in TIME_WAIT do
    # not block a restart, a listening socket does
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        s.bind(addr)
        s.listen(1)
    except OSError as e:
        what = "in use" if e.errno in (98, 48) else e.strerror
        raise ValueError(f"{args[1]} {port}: cannot listen on {host}:{port} ({what})") from None
    finally:
        s.close()


def _wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> quaternion wxyz [4]."""
    import viser.transforms as vtf
    return vtf.SO3.from_matrix(R).wxyz


class Viewer:
    """A running viewer. Construct, print :attr:`url`, then :meth:`wait` (or :meth:`stop`).

    Args:
        scene: what to show.
        host, port: where to listen (port 0: any free port).
        device: OpenCL device of the exact renders (None: CLSPLAT_DEVICE, else GPU, else PoCL).
        render_width: width in pixels of the exact render (the height follows the view's aspect).
        rest_s: seconds the camera must rest before the exact render runs.
        render_thread: run the exact renders on a thread of the viewer's own; False: the caller
            calls :meth:`render_due` (a training loop, so that one thread uses the OpenCL device).
        up: the world's up axis as viser names it ("+z" for driving scenes, "-y" for COLMAP ones).
        start_wait_s: how long a new client's first exact render waits for the browser to report
            the start view (a URL's ``initialCameraPosition`` replaces it, and then it never comes).
    """

    def __init__(self, scene: ViewScene, host: str = "127.0.0.1", port: int = 8080, device=None,
                 render_width: int = 480, rest_s: float = 0.4, up: str = "+z", auto_render: bool = True,
                 background: tuple[float, float, float] = (1.0, 1.0, 1.0), render_thread: bool = True,
                 start_wait_s: float = 10.0) -> None:
        check_port_free(host, port)
        import viser  # the view extra; a ModuleNotFoundError is named by the CLI

        # a browser closing its socket mid-handshake is routine here, not a traceback on the console
        logging.getLogger("websockets").setLevel(logging.CRITICAL)
        self.background = background   # viser's page is white: the exact render uses the same
        if not (16 <= render_width <= 4096):
            raise ValueError(f"--render-width: expected 16..4096, got {render_width}")
        self.scene = scene
        self._base = scene                     # the scene as loaded: its time slider and model inputs
        self.device = device
        self.render_width = render_width
        self.rest_s = rest_s
        self.start_wait_s = start_wait_s
        self.auto_render = auto_render
        self.renders = 0                       # exact renders done (all clients)
        self.last: dict[int, dict[str, Any]] = {}  # client id -> last exact render (image, seconds, viewmat)
        self._lock = threading.Lock()
        self._render_lock = threading.Lock()   # OpenCL work from one thread at a time
        self._moved: dict[int, float] = {}     # client id -> time of the last camera message not yet rendered
        # client id -> (connect time, start position [3], start look-at [3]) until its camera shows the start view
        self._starting: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        self._clients: dict[int, dict[str, Any]] = {}
        self._stop = threading.Event()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner: the CLI prints the address
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        if port and self.server.get_port() != port:  # viser moves to the next port when one is taken
            self.server.stop()
            raise ValueError(f"--port {port}: cannot listen on {host}:{port} (in use)")
        self.host = host
        self.server.gui.configure_theme(control_width="large")
        if up not in ("+x", "-x", "+y", "-y", "+z", "-z"):
            self.server.stop()
            raise ValueError(f"--up: expected one of +x -x +y -y +z -z, got {up!r}")
        self.server.scene.set_up_direction(up)
        self._up = up
        self._time = scene.times[0] if scene.times else None
        self._build_scene(scene)
        self._build_gui()
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(lambda c: self._forget(c.client_id))
        self._worker = threading.Thread(target=self._render_loop, name="clsplat-exact-render", daemon=True)
        if render_thread:
            self._worker.start()

    # ------------------------------------------------------------------ public
    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        h = self.host if ":" not in self.host else f"[{self.host}]"
        return f"http://{'127.0.0.1' if h in ('0.0.0.0', '') else h}:{self.port}"

    def clients(self) -> dict:
        return self.server.get_clients()

    def set_gaussians(self, scene: ViewScene) -> None:
        """Replace the Gaussians (and boxes) shown, e.g. during training or at a new time."""
        with self._lock:
            self.scene = scene
        self._add_splats(scene)
        self._add_boxes(scene)
        with self._lock:  # every client's exact render is stale now
            for cid in self._clients:
                self._moved[cid] = 0.0

    def render_client(self, client_id: int) -> dict[str, Any]:
        """Run the exact render of one client's current camera now and show it; returns
        {"image" [H,W,3], "seconds", "viewmat" [4,4]}."""
        c = self.server.get_clients()[client_id]
        cam = self.client_camera(c)
        with self._render_lock:
            with self._lock:
                scene = self.scene
            img, secs = render_view(scene, cam, device=self.device, background=self.background)
        rec = {"image": img, "seconds": secs, "viewmat": cam.viewmat, "time": time.time()}
        with self._lock:
            self.last[client_id] = rec
            self.renders += 1
            gui = self._clients.get(client_id)
        if gui is not None:
            gui["image"].image = img
            gui["text"].content = (f"clsplat exact render: {secs * 1e3:.0f} ms, {cam.width}x{cam.height}, "
                                 f"{len(scene)} Gaussians")
            if gui["background"].value:
                c.scene.set_background_image(img)
        return rec

    def client_camera(self, client) -> ViewCamera:
        """The :class:`ViewCamera` of a viser client's current view (OpenCV axes, as viser's)."""
        import viser.transforms as vtf

        cam = client.camera
        R = vtf.SO3(np.asarray(cam.wxyz)).as_matrix()
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = R, np.asarray(cam.position)
        aspect = float(cam.aspect) if cam.aspect and cam.aspect > 0 else 4 / 3
        w = self.render_width
        h = max(16, min(4096, int(round(w / aspect))))
        f = h / (2 * math.tan(float(cam.fov) / 2))
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
        return ViewCamera("viewer", K, np.linalg.inv(c2w), w, h)

    def set_client_camera(self, client, camera: ViewCamera) -> None:
        """Move a client's view to ``camera`` (position, orientation and vertical field of view)."""
        c2w = camera.cam_to_world
        with client.atomic():
            client.camera.wxyz = _wxyz(c2w[:3, :3])
            client.camera.position = c2w[:3, 3]
            client.camera.fov = camera.fov_y
        with self._lock:
            self._moved[client.client_id] = time.time()
            self._starting.pop(client.client_id, None)   # the server placed it: nothing to wait for

    def wait(self) -> None:
        """Serve until Ctrl-C (KeyboardInterrupt) or :meth:`stop`."""
        try:
            while not self._stop.wait(0.5):
                pass
        finally:
            self.stop()

    def stop(self) -> None:
        if not self._stop.is_set():
            self._stop.set()
            with contextlib.redirect_stdout(io.StringIO()):  # viser's "Server stopped"
                self.server.stop()
            if self._worker.is_alive():
                self._worker.join(timeout=10)

    # ------------------------------------------------------------------ scene
    def _add_splats(self, scene: ViewScene) -> None:
        if len(scene) == 0:
            return
        self.server.scene.add_gaussian_splats(
            "/gaussians", centers=scene.means.numpy(), covariances=covariances(scene.quats, scene.scales),
            rgbs=scene.rgb(), opacities=scene.opacities.numpy()[:, None])

    def _add_boxes(self, scene: ViewScene) -> None:
        for h in getattr(self, "_box_handles", []):
            h.remove()
        self._box_handles = [
            self.server.scene.add_box(f"/boxes/{i:03d}", color=(255, 140, 0), dimensions=tuple(np.asarray(b.size)),
                                      wireframe=True, wxyz=np.asarray(b.wxyz), position=np.asarray(b.center),
                                      visible=self._boxes_visible) for i, b in enumerate(scene.boxes)]

    def _add_cameras(self, scene: ViewScene) -> None:
        for h in getattr(self, "_camera_handles", []):
            h.remove()
        self._camera_handles = []
        r = scene.bounds()[1]
        for i, cam in enumerate(scene.cameras):
            c2w = cam.cam_to_world
            img = None
            if cam.image is not None:
                step = max(1, cam.image.shape[1] // 160)   # thumbnails keep the page light
                img = (np.clip(cam.image[::step, ::step], 0, 1) * 255).astype(np.uint8)
            self._camera_handles.append(self.server.scene.add_camera_frustum(
                f"/cameras/{i:03d}_{cam.name}", fov=cam.fov_y, aspect=cam.width / cam.height, scale=0.05 * r,
                image=img, wxyz=_wxyz(c2w[:3, :3]), position=c2w[:3, 3], color=(40, 90, 200), thickness=2.0,
                thickness_units="screen"))

    def set_depths(self, scene: ViewScene) -> None:
        """Show ``scene``'s depth maps: the images are replaced in place when the names are those
        shown (a training run's refresh), else the panel is rebuilt."""
        handles = getattr(self, "_depth_handles", [])
        if list(scene.depths) == getattr(self, "_depth_names", None) and len(handles) == len(scene.depths):
            for h, d in zip(handles, scene.depths.values()):
                h.image = (np.clip(d, 0, 1) * 255).astype(np.uint8)
        else:
            self._add_depths(scene)

    def _add_depths(self, scene: ViewScene) -> None:
        self._depth_names = list(scene.depths)
        for h in getattr(self, "_depth_handles", []):
            h.remove()
        self._depth_handles = []
        if scene.depths and getattr(self, "_depth_folder", None) is None:
            self._depth_folder = self.server.gui.add_folder("Predicted depth", expand_by_default=False)
        for name, d in scene.depths.items():
            with self._depth_folder:
                self._depth_handles.append(self.server.gui.add_image((np.clip(d, 0, 1) * 255).astype(np.uint8),
                                                                     label=name))

    def set_scene(self, scene: ViewScene) -> None:
        """Replace everything the scene shows: Gaussians, boxes, cameras and depth maps (another
        input of a feed-forward model)."""
        self.set_gaussians(scene)
        self._add_cameras(scene)
        self._add_depths(scene)

    def _build_scene(self, scene: ViewScene) -> None:
        s = self.server.scene
        self._boxes_visible = True
        self._add_splats(scene)
        c, r = scene.bounds()
        self._add_cameras(scene)
        if scene.trajectory is not None and len(scene.trajectory) >= 2:
            t = np.asarray(scene.trajectory, dtype=np.float32)
            seg = np.stack([t[:-1], t[1:]], axis=1)
            s.add_line_segments("/trajectory", seg, colors=(230, 30, 30), thickness=3.0, thickness_units="screen")
        self._lidar = None
        if scene.lidar is not None and len(scene.lidar):
            p = np.asarray(scene.lidar, dtype=np.float32)
            z = p[:, 2]
            t = (z - z.min()) / max(float(np.ptp(z)), 1e-6)
            col = np.stack([t, 1 - np.abs(2 * t - 1), 1 - t], 1)
            self._lidar = s.add_point_cloud("/lidar", p, colors=(col * 255).astype(np.uint8), point_size=0.04,
                                            visible=False)
        self._add_boxes(scene)
        init = default_camera(scene)
        c2w = init.cam_to_world
        # start behind and above the first camera, looking where it looks: the recorded cameras'
        # frusta (with their images) are then small ahead of the view, not filling it
        ax = "xyz".index(self._up[1])
        up = np.zeros(3)
        up[ax] = 1.0 if self._up[0] == "+" else -1.0
        back, lift = (0.5, 0.2) if scene.cameras else (0.15, 0.0)
        eye = c2w[:3, 3] - c2w[:3, 2] * back * r + up * lift * r - c2w[:3, 1] * 0.05 * r
        self.server.initial_camera.position = eye
        self.server.initial_camera.look_at = c2w[:3, 3] + c2w[:3, 2] * r
        self.server.initial_camera.fov = init.fov_y

    # ------------------------------------------------------------------ GUI shared by all clients
    def _build_gui(self) -> None:
        g = self.server.gui
        sc = self.scene
        g.add_markdown(f"**{sc.title}**: {len(sc)} Gaussians (SH degree {sc.sh_degree}), "
                       f"{len(sc.cameras)} cameras")
        if self._lidar is not None:
            cb = g.add_checkbox("LiDAR points", initial_value=False)
            cb.on_update(lambda _: self.show_lidar(cb.value))
        if sc.boxes:
            bb = g.add_checkbox("Tracked boxes", initial_value=True)
            bb.on_update(lambda _: self.show_boxes(bb.value))
        if sc.variants and sc.variant is not None:
            with g.add_folder("Model input"):
                dd = g.add_dropdown("Input", options=tuple(sc.variants))
                run = g.add_button("Run the model")
                status = g.add_markdown("")

            def _run(_) -> None:
                status.content = f"running the model on {dd.value} ..."
                status.content = self.run_variant(dd.value)
            run.on_click(_run)
        self._add_depths(sc)
        if sc.times and sc.at_time is not None:
            sl = g.add_slider("Time (s)", min=float(min(sc.times)), max=float(max(sc.times)),
                              step=float(np.min(np.diff(sorted(sc.times)))) if len(sc.times) > 1 else 1.0,
                              initial_value=float(sc.times[0]))
            sl.on_update(lambda _: self.set_time(sl.value))

    # ------------------------------------------------------------------ what the shared controls do
    def show_lidar(self, on: bool) -> None:
        """The "LiDAR points" toggle."""
        if self._lidar is not None:
            self._lidar.visible = bool(on)

    def show_boxes(self, on: bool) -> None:
        """The "Tracked boxes" toggle."""
        self._boxes_visible = bool(on)
        self._add_boxes(self.scene)

    def set_time(self, t: float) -> None:
        """The time slider: the Gaussians and boxes of the scene at time ``t`` (AutoSplat's moving
        objects placed, with their residual SH); the recorded cameras and depth maps stay."""
        if self._base.at_time is None:
            raise ValueError("this scene has no time slider (it is static)")
        new = self._base.at_time(float(t))
        if not new.cameras:
            new.cameras = self._base.cameras
        self._time = float(t)
        self.set_gaussians(new)

    def run_variant(self, name: str) -> str:
        """The "Model input" dropdown's "Run the model": rerun a feed-forward model on another input
        and show its scene; returns the status line shown under the button."""
        if self._base.variant is None or name not in self._base.variants:
            return f"{name}: not an input this scene offers"
        t0 = time.perf_counter()
        try:
            self.set_scene(self._base.variant(name))
        except ValueError as e:
            return f"{name}: {e}"
        return f"{name}: {len(self.scene)} Gaussians in {time.perf_counter() - t0:.1f} s"

    # ------------------------------------------------------------------ per client
    def _on_connect(self, client) -> None:
        g = client.gui
        with g.add_folder("clsplat exact render"):
            text = g.add_markdown("clsplat exact render: waiting for the camera to rest")
            image = g.add_image(np.zeros((8, 8, 3), np.uint8), label="server side, clsplat.rasterization")
            btn = g.add_button("Render now")
            bg = g.add_checkbox("Show as the view's background", initial_value=False)
        btn.on_click(lambda _: self._request_render(client.client_id))

        def _bg(_) -> None:
            if not bg.value:
                client.scene.set_background_image(None)
            elif client.client_id in self.last:
                client.scene.set_background_image(self.last[client.client_id]["image"])
        bg.on_update(_bg)
        views = self.views()
        if views:
            with g.add_folder("Views"):
                dd = g.add_dropdown("Camera", options=tuple(views))
                go = g.add_button("Go to camera")
                # the views of the scene now (the far side of a car at the slider's time)
                go.on_click(lambda _: self.set_client_camera(client, self.views().get(dd.value, views[dd.value])))
        start = self.server.initial_camera
        with self._lock:
            self._clients[client.client_id] = {"image": image, "text": text, "background": bg}
            self._moved[client.client_id] = time.time()  # its first camera message may have come already
            self._starting[client.client_id] = (time.time(), np.array(start.position, dtype=np.float64),
                                                np.array(start.look_at, dtype=np.float64))
        client.camera.on_update(lambda cam: self._camera_moved(client.client_id))

    def views(self) -> dict[str, ViewCamera]:
        """Recorded cameras and the benchmark views: lane change 1-3 m (the first camera moved
        left along its own x axis) and the far side of the first tracked box."""
        sc = self.scene
        views = {c.name: c for c in sc.cameras}
        if sc.cameras:
            c0 = sc.cameras[0]
            for m in (1, 2, 3):
                V = c0.viewmat.copy()
                V[:3, 3] += np.array([m, 0.0, 0.0])  # centre - m * (camera x axis): m metres to the left
                views[f"lane change {m} m ({c0.name})"] = ViewCamera(f"lane_{m}m", c0.K, V, c0.width, c0.height)
        if sc.boxes and sc.cameras:
            from .scene import look_at_viewmat
            b, c0 = sc.boxes[0], sc.cameras[0]
            eye0 = c0.cam_to_world[:3, 3]
            centre = np.asarray(b.center, dtype=np.float64)
            d = centre - eye0
            d[2] = 0
            eye = centre + d / max(np.linalg.norm(d), 1e-6) * max(np.linalg.norm(d), 3 * float(np.max(b.size)))
            eye[2] = eye0[2]
            views[f"far side of {b.name}"] = ViewCamera("far_side", c0.K, look_at_viewmat(eye, centre), c0.width,
                                                        c0.height)
        return views

    def _request_render(self, client_id: int) -> None:
        with self._lock:
            self._moved[client_id] = 0.0   # due at once, rendered by whoever renders (one thread)
            self._starting.pop(client_id, None)   # asked for: the camera as it is

    def _waits_for_start_view(self, client_id: int, camera) -> bool:
        """True while a new client's camera is not yet at the start view (viser's placeholder
        camera comes first) and ``start_wait_s`` has not passed since it connected."""
        with self._lock:
            s = self._starting.get(client_id)
        if s is None:
            return False
        t0, pos, look = s
        tol = 1e-3 * max(float(np.linalg.norm(look - pos)), 1e-6)
        at_start = (float(np.linalg.norm(np.asarray(camera.position) - pos)) <= tol
                    and float(np.linalg.norm(np.asarray(camera.look_at) - look)) <= tol)
        if at_start and time.time() - camera.update_timestamp < self.rest_s:
            return True      # just arrived: its own camera callback makes it due once it has rested
        if at_start or time.time() - t0 >= self.start_wait_s:
            with self._lock:
                self._starting.pop(client_id, None)
            return False
        return True

    def _camera_moved(self, client_id: int) -> None:
        with self._lock:
            self._moved[client_id] = time.time()

    def _forget(self, client_id: int) -> None:
        with self._lock:
            self._clients.pop(client_id, None)
            self._moved.pop(client_id, None)
            self._starting.pop(client_id, None)
            self.last.pop(client_id, None)

    def render_due(self) -> int:
        """Render every client whose camera has rested ``rest_s`` since its last move (or that asked
        with "Render now"); returns how many were rendered. The worker thread calls this; with
        ``render_thread=False`` (a training loop that owns the OpenCL device) the owner does."""
        now = time.time()
        with self._lock:
            due = [cid for cid, t in self._moved.items() if now - t >= self.rest_s]
            for cid in due:
                del self._moved[cid]
        done = 0
        for cid in due:
            try:
                camera = self.server.get_clients()[cid].camera
                if camera.update_timestamp == 0.0 or self._waits_for_start_view(cid, camera):
                    self._camera_moved(cid)   # no camera message from the browser yet, or not the start view
                    continue
                self.render_client(cid)
                done += 1
            except KeyError:   # the client left meanwhile
                pass
            except Exception as e:  # keep serving; show the failure where the image would be, and on the console
                print(f"clsplat view: exact render failed: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
                gui = self._clients.get(cid)
                if gui is not None:
                    gui["text"].content = f"clsplat exact render failed: {type(e).__name__}: {e}"
        return done

    def _render_loop(self) -> None:
        while not self._stop.wait(0.05):
            if self.auto_render:
                self.render_due()
