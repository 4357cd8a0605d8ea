"""AutoSplat in the viewer: the scene of a model at a frame (recording cameras and images, ego
trajectory, LiDAR, boxes, a time slider that places the moving objects and their residual SH), for
a checkpoint (``AutoSplatCommands.checkpoint_scene``) and live for ``clsplat train autosplat --view``."""
from __future__ import annotations

import numpy as np
import torch

from clsplat.viewer.scene import ViewBox, ViewCamera, ViewScene

from ..common.view import gaussians_scene

__all__ = ["autosplat_scene"]


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
