"""The camera rig and the ego's motion: :func:`make_rig` (six nuScenes-like cameras),
:func:`ego_pose` (straight drive with an optional smooth lane change) and :func:`render_view`
(one camera of the rig, mounted on the ego at a pose and time, rendered from a
:class:`~clsplat.data.synthetic.street.StreetScene`).
"""
from __future__ import annotations

import math

import numpy as np

from ..scene import CAMERA_NAMES, Camera, make_transform
from .config import _RIG_POS, CAMERA_HEIGHT, RIG_YAWS_DEG, RenderOutput
from .street import StreetScene
from .world import classic_ego_pose

def make_rig(width: int = 320, height: int = 176, hfov_deg: float = 70.0, back_hfov_deg: float = 85.0,
             lateral_shift: float = 0.0) -> list[Camera]:
    """Six-camera nuScenes-like rig (see module docstring); square pixels, centred principal point."""
    cams = []
    for name, yaw_d, (px, py) in zip(CAMERA_NAMES, RIG_YAWS_DEG, _RIG_POS):
        fov = back_hfov_deg if name == "CAM_BACK" else hfov_deg
        f = (width / 2) / math.tan(math.radians(fov) / 2)
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=np.float64)
        yaw = math.radians(yaw_d)
        fwd = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
        down = np.array([0.0, 0.0, -1.0])
        R = np.stack([right, down, fwd], axis=1)
        T = make_transform(R=R, t=[px, py + lateral_shift, CAMERA_HEIGHT])
        cams.append(Camera(name, K, T, width, height))
    return cams


def ego_pose(t: float, speed: float = 8.0, lane_change: bool = True, lane_change_duration: float = 3.0) -> np.ndarray:
    """``[4, 4]`` ego-to-world of the classic street at time ``t``: along +x at ``speed``, optional
    smooth lane change from y=-1.75 to y=+1.75 during ``[0, lane_change_duration]`` (the varied
    worlds: :meth:`~clsplat.data.synthetic.world.WorldParams.ego_pose`)."""
    return classic_ego_pose(t, speed, lane_change, lane_change_duration)


def render_view(scene: StreetScene, camera: Camera, ego_to_world, t: float, supersample: int = 1,
                lighting: bool = True, shade: bool = True) -> RenderOutput:
    """Render ``camera`` (mounted by its ``cam_to_ego``) with the ego at ``ego_to_world`` and time ``t``
    (``shade=False``: the depth alone, :meth:`StreetScene.render`)."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    E = np.asarray(ego_to_world, dtype=np.float64)
    if E.shape != (4, 4):
        raise ValueError(f"ego_to_world must have shape [4, 4], got {list(E.shape)}")
    return scene.render(camera.K, E @ camera.cam_to_ego, camera.width, camera.height, t, supersample, lighting,
                        shade)

