"""Checkpoints and run folders of every model family -> a :class:`clsplat.viewer.ViewScene`
(what ``clsplat view`` / ``clsplat render`` show for them).

* AutoSplat (a per-scene optimisation): the model is rebuilt from the checkpoint and the run's
  data (``metrics.json``'s ``data`` and ``scale``, else ``--data``), and the scene carries the
  recording's cameras with their images, the ego trajectory, the LiDAR points, the tracked boxes
  and a time slider that places the moving objects (with their residual SH) at each frame.
* DrivingForward and PGT (feed-forward): the network runs on held-out sample ``sample`` of
  ``data``; the scene is its predicted Gaussians with the input cameras (and their images) and
  the predicted depth maps.
* A run folder without a checkpoint but with ``scene.ply`` shows the ``.ply``.

Every failure is a ValueError naming PATH (unknown family, not a checkpoint, mismatched data).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from clsplat.viewer.scene import ViewBox, ViewCamera, ViewScene, scene_from_ply

__all__ = ["scene_from_checkpoint", "autosplat_scene", "TrainView"]


def _preset_from_saved(family: str, saved: dict):
    """The preset a checkpoint was written with (its named preset plus the fields a run changed)."""
    from .presets import get_preset

    base = get_preset(family, saved.get("name", "?"))
    names = {f.name for f in dataclasses.fields(base)}
    changes = {}
    for k, v in saved.items():
        if k in names and k != "name":
            cur = getattr(base, k)
            v = tuple(v) if isinstance(cur, tuple) and isinstance(v, list) else v
            if v != cur:
                changes[k] = v
    return base.replace(**changes) if changes else base


def _gaussians_scene(g, title: str) -> ViewScene:
    return ViewScene(g.means, g.quats, g.scales, g.opacities, g.sh, title=title)


def _depth_colour(d: np.ndarray, far: float = 80.0) -> np.ndarray:
    """[H, W] metres -> [H, W, 3] turbo-like colours (near warm, far cool; inf/NaN black)."""
    ok = np.isfinite(d)
    t = np.clip(np.log1p(np.where(ok, d, far)) / np.log1p(far), 0, 1)
    rgb = np.stack([1 - t, 1 - np.abs(2 * t - 1), t], -1)
    rgb[~ok] = 0
    return rgb.astype(np.float32)


def _autosplat(ck: dict, ck_path: Path, run: Path, data: str | None) -> ViewScene:
    from ..autosplat.cli import load_sequence
    from ..autosplat.model import Switches
    from ..autosplat.trainer import Trainer, prepare_data

    preset = _preset_from_saved("autosplat", ck["preset"])
    spec, scale = "synthetic", preset.scale
    metrics = run / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        spec, scale = m.get("data", spec), m.get("scale", scale)
    spec = data or spec
    want = list(ck.get("train_frames") or [0])
    # the run's frame range is not stored: the first cut of the sequence whose split gives its training frames
    seq = load_sequence(spec, ck.get("cameras"), (0, max(want) + 1 + preset.holdout) if spec == "synthetic" else None,
                        scale, seed=preset.seed)
    from clsplat.data.scene import DrivingSequence
    for n in range(max(want) + 1, len(seq.frames) + 1):
        d = prepare_data(DrivingSequence(seq.cameras, seq.frames[:n], seq.name, seq.metadata), ck.get("cameras"),
                         preset.holdout)
        if d.train_frames == want:
            seq = d.seq
            break
    else:
        raise ValueError(f"PATH {str(ck_path)!r}: its training frames {ck.get('train_frames')} are not those of "
                         f"--data {spec!r} ({d.train_frames}); name the run's data with --data")
    tr = Trainer(d, preset, Switches(**ck["switches"]), run, progress=False)
    if [t.track_id for t in tr.tracks] != ck.get("tracks"):
        raise ValueError(f"PATH {str(ck_path)!r}: its tracked objects differ from those of --data {spec!r}")
    tr.model.resize_(ck["sizes"])
    tr.model.load_state_dict(ck["model"])
    return autosplat_scene(tr.model.eval(), seq, d, f"AutoSplat {preset.name} ({run.name})")


def autosplat_scene(model, seq, d, title: str, frame: int | None = None) -> ViewScene:
    """The scene of an AutoSplat model at ``frame`` (default the first training frame) with the
    recording's cameras and images, ego trajectory, LiDAR, boxes, and ``at_time`` placing the
    moving objects (and their residual SH) at the frame nearest a time.

    Args:
        model: an ``AutoSplatModel``; seq: its ``DrivingSequence``; d: its ``RunData``.
    """
    frames = list(range(len(seq.frames)))
    times = [float(seq.frames[f].timestamp) for f in frames]

    def at(frame: int, with_extras: bool) -> ViewScene:
        with torch.no_grad():
            g = model.scene_at(frame)[0].detach()
        sc = _gaussians_scene(g, f"{title}, frame {frame}")
        sc.boxes = [ViewBox(f"{b.label} {b.track_id}", b.center, b.size, b.quat, times[frame])
                    for b in seq.frames[frame].boxes]
        if with_extras:
            sc.cameras = [ViewCamera(f"{c} f{f:02d}", seq.camera(c).K, np.linalg.inv(seq.cam_to_world(f, c)),
                                     seq.camera(c).width, seq.camera(c).height, seq.frames[f].images[c], times[f])
                          for f in d.train_frames[:1] + d.test_frames + d.train_frames[1:] for c in d.cameras][:64]
            sc.trajectory = np.stack([seq.frames[f].ego_to_world[:3, 3] for f in frames])
            pts = []
            for f in frames:
                L = seq.frames[f].lidar
                if L is not None:
                    p = L.points.astype(np.float64)
                    if L.frame == "ego":
                        E = seq.frames[f].ego_to_world
                        p = p @ E[:3, :3].T + E[:3, 3]
                    pts.append(p[:: max(1, len(p) // 20000)])
            sc.lidar = np.concatenate(pts).astype(np.float32) if pts else None
            sc.times = times
            sc.at_time = lambda t: at(int(np.argmin(np.abs(np.asarray(times) - t))), False)
        return sc

    return at(d.train_frames[0] if frame is None else frame, True)


#: samples of the held-out split a feed-forward checkpoint's viewer offers
_VARIANT_SAMPLES = 4


def _drivingforward(ck_path: Path, data: str, sample: int, device) -> ViewScene:
    from ..drivingforward.cli import load_model
    from ..drivingforward.data import gt_ego_motion, load_triplet
    from ..drivingforward.evaluation import OFFSETS
    from .data import parse_data

    model, preset = load_model(str(ck_path), device)
    model.eval()
    source = parse_data(data)
    default_frames = (0,) if preset.mode == "SF" else (-1, 1)

    def run(k: int, frames: tuple[int, ...], front_only: bool) -> ViewScene:
        s = load_triplet(source, k, preset, split="test")
        cams = slice(0, 1) if front_only else slice(None)
        fi = [OFFSETS[f] for f in frames]
        M = gt_ego_motion(s)
        to_ref = torch.stack([torch.linalg.inv(M[f].double()).float() for f in fi])
        Ks, E = s["Ks"][cams], s["cam_to_ego"][cams]
        with torch.no_grad():
            g = model.reconstruct(s["images"][fi][:, cams], Ks, E, frame_to_ref=to_ref,
                                  ref=0 if 1 not in fi else fi.index(1))
            depth = model.depth_net(s["images"][1][cams], Ks, E)["depth"][:, 0].numpy()
        names = s["names"][cams]
        sc = _gaussians_scene(g, f"DrivingForward {preset.name} on {data} sample {k}, frames {list(frames)} "
                                 f"(ego frame)")
        V = (s["viewmats"][1][cams] @ s["ego_to_world"][1]).double().numpy()   # ego(t) -> camera
        imgs = s["images"][1][cams].permute(0, 2, 3, 1).numpy()
        sc.cameras = [ViewCamera(n, Ks[i].numpy(), V[i], preset.width, preset.height, imgs[i])
                      for i, n in enumerate(names)]
        sc.depths = {n: _depth_colour(depth[i]) for i, n in enumerate(names)}
        return sc

    options = {f"sample {k}, frames {list(fr)}, {'front camera' if fo else 'all cameras'}": (k, fr, fo)
               for k in range(max(_VARIANT_SAMPLES, sample + 1)) for fr in ((0,), (-1, 1), (-1, 0, 1))
               for fo in (False, True)}
    sc = run(sample, default_frames, False)
    sc.variants = list(options)
    sc.variant = lambda name: run(*options[name])
    return sc


def _pgt(ck: dict, ck_path: Path, data: str, sample: int) -> ViewScene:
    from ..pgt.data import make_sample
    from ..pgt.model import PGT
    from .data import parse_data
    from .presets import check_preset_matches, get_preset

    preset = get_preset("pgt", ck["preset"]["name"])
    check_preset_matches(ck["preset"], preset, str(ck_path))
    model = PGT(preset)
    if any(k.startswith("budget.") for k in ck["model"]):
        model.enable_budget()
    model.load_state_dict(ck["model"])
    model.eval()
    source = parse_data(data)

    def run(k: int) -> ViewScene:
        s = make_sample(source, preset, k, "test", None)
        with torch.no_grad():
            base = model(s.images, s.Ks, s.cam_to_world)
            g = base.gaussians()
        sc = _gaussians_scene(g, f"PGT {preset.name} on {data} sample {k}")
        imgs = s.images.permute(0, 2, 3, 1).numpy()
        H, W = imgs.shape[1:3]
        sc.cameras = [ViewCamera(f"input {i}", s.Ks[i].numpy(), np.linalg.inv(s.cam_to_world[i].double().numpy()),
                                 W, H, imgs[i]) for i in range(len(imgs))]
        sc.cameras += [ViewCamera(f"target {i}", s.target_Ks[i].numpy(), s.target_viewmats[i].double().numpy(), W, H,
                                  s.target_images[i].permute(1, 2, 0).numpy()) for i in range(len(s.target_images))]
        dep = base.depth.reshape(len(imgs), H, W).numpy()
        sc.depths = {f"input {i}": _depth_colour(dep[i], preset.far) for i in range(len(imgs))}
        return sc

    sc = run(sample)
    options = {f"sample {k}": k for k in range(max(_VARIANT_SAMPLES, sample + 1))}
    sc.variants = list(options)
    sc.variant = lambda name: run(options[name])
    return sc


def scene_from_checkpoint(path: str | Path, data: str | None = None, device=None, sample: int = 0) -> ViewScene:
    """The scene of a checkpoint file or run folder (see the module docstring)."""
    from .. import FAMILIES
    from .train import load_checkpoint

    p = Path(path)
    run = p if p.is_dir() else p.parent
    ck_path = p / "checkpoint.pt" if p.is_dir() else p
    if p.is_dir() and not ck_path.is_file():
        return scene_from_ply(p / "scene.ply")
    try:
        ck = load_checkpoint(ck_path)
    except ValueError as e:
        raise ValueError(f"PATH {str(path)!r} is not a scene: {e}; expected an INRIA .ply, a checkpoint.pt "
                         "written by clsplat train, or a run folder holding one") from None
    fam = ck.get("family")
    if fam not in FAMILIES:
        raise ValueError(f"PATH {str(path)!r}: a checkpoint of an unknown model family {fam!r}; "
                         f"known: {', '.join(FAMILIES)}")
    if not isinstance(sample, int) or sample < 0:
        raise ValueError(f"--sample: expected an integer >= 0, got {sample!r}")
    if fam == "autosplat":
        return _autosplat(ck, ck_path, run, data)
    if fam == "drivingforward":
        return _drivingforward(ck_path, data or "synthetic", sample, device)
    return _pgt(ck, ck_path, data or "synthetic", sample)


class TrainView:
    """``clsplat train ... --view``: serve a run's scene while it trains.

    The viewer starts at the first step (once the model has Gaussians). While a browser is
    connected, every ``every`` steps (and when a browser connects) the Gaussians shown are
    replaced by the model's current ones and the loss plot is updated; the exact renders run in
    the training thread between steps (one thread uses the OpenCL device). With no browser a step
    costs a list append and a look at the client table.

    Args:
        scene_fn: ``() -> ViewScene`` of the model now.
        host, port: where to listen; every: steps between refreshes; device: exact-render device.
    """

    def __init__(self, scene_fn, host: str = "127.0.0.1", port: int = 8080, every: int = 10, device=None) -> None:
        from clsplat.viewer.server import check_port_free
        import viser  # noqa: F401  (the view extra, named by clsplat.cli when missing)

        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"--view-every: expected a positive number of steps, got {every!r}")
        check_port_free(host, port)
        self.scene_fn, self.host, self.port, self.every, self.device = scene_fn, host, port, every, device
        self.viewer = None
        self.plot = None
        self.steps: list[int] = []
        self.losses: list[float] = []
        self._seen: set[int] = set()
        self.refreshes = 0

    def start(self) -> None:
        from clsplat.viewer.server import Viewer

        self.viewer = Viewer(self.scene_fn(), host=self.host, port=self.port, device=self.device,
                             render_thread=False)
        self.plot = self.viewer.server.gui.add_uplot(
            data=(np.zeros(1), np.zeros(1)), series=({"label": "step"}, {"label": "loss", "stroke": "red"}),
            title="training loss", aspect=1.6)
        print(f"clsplat train --view: watch the run at {self.viewer.url}", flush=True)

    def on_step(self, step: int, record: dict) -> None:
        """Called by the training loop after each step with its log record."""
        if self.viewer is None:
            self.start()
        if "loss" in record:
            self.steps.append(step)
            self.losses.append(float(record["loss"]))
        clients = self.viewer.clients()
        if not clients:
            self._seen = set()
            return
        if set(clients) - self._seen or step % self.every == 0:
            self._seen = set(clients)
            self.viewer.set_gaussians(self.scene_fn())
            self.plot.data = (np.asarray(self.steps, np.float64), np.asarray(self.losses, np.float64))
            self.refreshes += 1
        self.viewer.render_due()

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.stop()
