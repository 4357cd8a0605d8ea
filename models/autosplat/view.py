"""AutoSplat in the viewer: a checkpoint rebuilt on its run's data, and the scene of a model at a
frame (recording cameras and images, ego trajectory, LiDAR, boxes, a time slider that places the
moving objects and their residual SH), also served live by ``clsplat train autosplat --view``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from clsplat.data.scene import DrivingSequence
from clsplat.viewer.scene import ViewBox, ViewCamera, ViewScene

from ..common.view import gaussians_scene, preset_from_saved
from .data import load_sequence
from .model import Switches
from .trainer import Trainer, prepare_data

__all__ = ["checkpoint_scene", "autosplat_scene"]


def checkpoint_scene(ck: dict, ck_path: Path, run: Path, data: str | None, sample: int = 0, device=None,
                     safe_pickle: bool = True) -> ViewScene:
    """The scene of an AutoSplat checkpoint (``sample`` and ``device`` are unused: the model is the scene;
    ``safe_pickle=False`` trusts the data's pickles)."""

    preset = preset_from_saved("autosplat", ck["preset"])
    spec, scale = "synthetic", preset.scale
    metrics = run / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        spec, scale = m.get("data", spec), m.get("scale", scale)
    spec = data or spec
    want = list(ck.get("train_frames") or [0])
    # the run's frame range is not stored: the first cut of the sequence whose split gives its training frames
    seq = load_sequence(spec, ck.get("cameras"), (0, max(want) + 1 + preset.holdout) if spec == "synthetic" else None,
                        scale, seed=preset.seed, safe_pickle=safe_pickle)
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
        sc = gaussians_scene(g, f"{title}, frame {frame}")
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
