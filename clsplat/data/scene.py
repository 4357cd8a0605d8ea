"""Data model for multi-camera driving sequences.

Conventions (stated once, used by every module in :mod:`clsplat.data` and :mod:`clsplat.io`):

* Units are metres, seconds and radians.
* **World** frame: right-handed, z up.  For the synthetic generator the road runs along +x.
* **Ego** frame: rigidly attached to the vehicle, x forward, y left, z up, origin on the
  ground below the rear axle.  ``Frame.ego_to_world`` maps ego coordinates to world.
* **Camera** frame: OpenCV, x right, y down, z forward (optical axis).  ``Camera.cam_to_ego``
  maps camera coordinates to ego; ``DrivingSequence.viewmats`` gives world-to-camera
  matrices, the ``viewmats`` argument of :func:`clsplat.rasterization`.
* Pixel ``(u, v)`` = column, row; the centre of pixel ``(x, y)`` is at ``(x + 0.5, y + 0.5)``,
  so ``K @ [X/Z, Y/Z, 1]`` gives continuous pixel coordinates with that convention.
* Quaternions are ``(w, x, y, z)`` (scalar first), unit norm, rotating from the local frame
  into the parent frame.
* Rigid transforms are float64 ``[4, 4]`` homogeneous matrices; intrinsics float64 ``[3, 3]``.
* Images are float32 ``[H, W, 3]`` RGB in ``[0, 1]`` (linear values as stored, no gamma
  handling).  Depth is float32 ``[H, W]`` **z-depth** (distance along the camera's optical
  axis, not along the ray) in metres, ``inf`` where the ray hits nothing (sky).  Semantic
  masks are uint8 ``[H, W]`` holding indices into :data:`SEMANTIC_CLASSES`; instance masks
  are int32 ``[H, W]`` holding the track id of a tracked object, 0 for none.
* Camera order follows nuScenes: :data:`CAMERA_NAMES`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

from .geometry import (_as_array, _check_rigid, invert_transform, make_transform, project_points, quat_to_rotmat,
                       rotmat_to_quat, unproject_depth)

__all__ = [
    "CAMERA_NAMES",
    "SEMANTIC_CLASSES",
    "Camera",
    "Box3D",
    "LidarPoints",
    "Frame",
    "DrivingSequence",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "make_transform",
    "invert_transform",
    "unproject_depth",
    "project_points",
]

#: Camera names in nuScenes order.
CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_LEFT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
)

#: Semantic classes; a semantic mask stores the index into this tuple.
SEMANTIC_CLASSES: tuple[str, ...] = ("road", "sidewalk", "building", "vehicle", "sky", "other")


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------
def _check_image(img, name: str, hw: tuple[int, int] | None, channels: int | None, dtype) -> np.ndarray:
    arr = np.asarray(img)
    if channels is None:
        if arr.ndim != 2:
            raise ValueError(f"{name} must have shape [H, W], got {list(arr.shape)}")
    elif arr.ndim != 3 or arr.shape[2] != channels:
        raise ValueError(f"{name} must have shape [H, W, {channels}], got {list(arr.shape)}")
    if hw is not None and tuple(arr.shape[:2]) != tuple(hw):
        raise ValueError(f"{name} must be {hw[0]}x{hw[1]} (HxW) to match its camera, got {arr.shape[0]}x{arr.shape[1]}")
    return arr.astype(dtype, copy=False)


# --------------------------------------------------------------------------------------
# geometry helpers
# --------------------------------------------------------------------------------------


@dataclass
class Camera:
    """A pinhole camera rigidly mounted on the ego vehicle.

    Attributes:
        name: camera name, e.g. ``"CAM_FRONT"``.
        K: ``[3, 3]`` float64 intrinsics (fx, fy, cx, cy in pixels, pixel-centre convention of
           the module docstring).
        cam_to_ego: ``[4, 4]`` float64 rigid transform, OpenCV camera frame -> ego frame.
        width, height: image size in pixels.
    """

    name: str
    K: np.ndarray
    cam_to_ego: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Camera.name must be a non-empty string, got {self.name!r}")
        for attr in ("width", "height"):
            v = getattr(self, attr)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
                raise ValueError(f"Camera {self.name}: {attr} must be a positive int, got {v!r}")
            setattr(self, attr, int(v))
        self.K = _as_array(self.K, f"Camera {self.name}: K", (3, 3))
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise ValueError(f"Camera {self.name}: K focal lengths must be positive, got fx={self.K[0, 0]}, fy={self.K[1, 1]}")
        if not np.allclose(self.K[2], [0, 0, 1]) or self.K[1, 0] != 0:
            raise ValueError(f"Camera {self.name}: K must be upper triangular with last row [0, 0, 1]")
        self.cam_to_ego = _as_array(self.cam_to_ego, f"Camera {self.name}: cam_to_ego", (4, 4))
        _check_rigid(self.cam_to_ego, f"Camera {self.name}: cam_to_ego")

    @property
    def hfov_deg(self) -> float:
        """Horizontal field of view in degrees (for a centred principal point)."""
        return float(np.degrees(2 * np.arctan(self.width / (2 * self.K[0, 0]))))


@dataclass
class Box3D:
    """An oriented 3D bounding box of a tracked object at one instant.

    Attributes:
        track_id: positive int, stable over the sequence; equals the value in instance masks.
        label: class name (e.g. ``"car"``).
        size: ``[3]`` full extents (length along local x, width along local y, height along local z).
        center: ``[3]`` box centre in world frame.
        quat: ``[4]`` wxyz rotation, box local frame (x forward, y left, z up) -> world.
        uuid: optional dataset-specific identifier (string).
    """

    track_id: int
    label: str
    size: np.ndarray
    center: np.ndarray
    quat: np.ndarray
    uuid: str = ""

    def __post_init__(self) -> None:
        if isinstance(self.track_id, bool) or not isinstance(self.track_id, (int, np.integer)) or self.track_id <= 0:
            raise ValueError(f"Box3D.track_id must be a positive int, got {self.track_id!r}")
        self.track_id = int(self.track_id)
        self.size = _as_array(self.size, "Box3D.size", (3,))
        if np.any(self.size <= 0):
            raise ValueError(f"Box3D.size must be positive, got {self.size.tolist()}")
        self.center = _as_array(self.center, "Box3D.center", (3,))
        q = _as_array(self.quat, "Box3D.quat", (4,))
        n = np.linalg.norm(q)
        if n < 1e-9:
            raise ValueError("Box3D.quat must be non-zero")
        self.quat = q / n

    @property
    def box_to_world(self) -> np.ndarray:
        """``[4, 4]`` transform from the box frame (origin at its centre) to world."""
        return make_transform(quat=self.quat, t=self.center)

    def corners(self) -> np.ndarray:
        """``[8, 3]`` world-frame corners (all sign combinations of ``±size/2``)."""
        s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        local = s * self.size / 2
        T = self.box_to_world
        return local @ T[:3, :3].T + T[:3, 3]

    def contains(self, points, margin: float = 0.0) -> np.ndarray:
        """Boolean ``[...]`` mask of world points ``[..., 3]`` inside the box grown by ``margin`` metres."""
        p = np.asarray(points, dtype=np.float64)
        T = invert_transform(self.box_to_world)
        local = p @ T[:3, :3].T + T[:3, 3]
        return np.all(np.abs(local) <= self.size / 2 + margin, axis=-1)


@dataclass
class LidarPoints:
    """A LiDAR sweep.

    Attributes:
        points: ``[M, 3]`` float32 xyz in the frame named by ``frame``.
        intensity: ``[M]`` float32 reflectance in ``[0, 1]``.
        frame: ``"ego"`` (ego frame of the owning :class:`Frame`) or ``"world"``.
        ring: optional ``[M]`` int beam index.
    """

    points: np.ndarray
    intensity: np.ndarray
    frame: Literal["ego", "world"] = "ego"
    ring: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = _as_array(self.points, "LidarPoints.points", (-1, 3), np.float32)
        m = self.points.shape[0]
        self.intensity = _as_array(self.intensity, "LidarPoints.intensity", (m,), np.float32)
        if self.frame not in ("ego", "world"):
            raise ValueError(f"LidarPoints.frame must be 'ego' or 'world', got {self.frame!r}")
        if self.ring is not None:
            self.ring = _as_array(self.ring, "LidarPoints.ring", (m,), np.int32)

    def to_world(self, ego_to_world) -> "LidarPoints":
        """Return the sweep in world frame (no-op if it already is)."""
        if self.frame == "world":
            return self
        T = _as_array(ego_to_world, "ego_to_world", (4, 4))
        pts = (self.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        return LidarPoints(pts, self.intensity, "world", self.ring)

    def to_ego(self, ego_to_world) -> "LidarPoints":
        """Return the sweep in ego frame (no-op if it already is)."""
        if self.frame == "ego":
            return self
        T = invert_transform(_as_array(ego_to_world, "ego_to_world", (4, 4)))
        pts = (self.points.astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        return LidarPoints(pts, self.intensity, "ego", self.ring)


@dataclass
class Frame:
    """All sensor data of one time step.

    Attributes:
        timestamp: seconds.
        ego_to_world: ``[4, 4]`` float64 ego pose.
        images: camera name -> float32 ``[H, W, 3]`` in ``[0, 1]``.
        depths: optional camera name -> float32 ``[H, W]`` z-depth (``inf`` = sky).
        semantics: optional camera name -> uint8 ``[H, W]`` indices into :data:`SEMANTIC_CLASSES`.
        instances: optional camera name -> int32 ``[H, W]`` track ids (0 = none).
        lidar: optional :class:`LidarPoints`.
        boxes: tracked boxes visible at this instant.
        camera_poses: optional camera name -> ``[4, 4]`` camera-to-world pose that overrides
            ``ego_to_world @ cam_to_ego`` (real datasets, where cameras fire at different times).
    """

    timestamp: float
    ego_to_world: np.ndarray
    images: dict[str, np.ndarray]
    depths: dict[str, np.ndarray] = field(default_factory=dict)
    semantics: dict[str, np.ndarray] = field(default_factory=dict)
    instances: dict[str, np.ndarray] = field(default_factory=dict)
    lidar: LidarPoints | None = None
    boxes: list[Box3D] = field(default_factory=list)
    camera_poses: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            self.timestamp = float(self.timestamp)
        except (TypeError, ValueError):
            raise ValueError(f"Frame.timestamp must be a number of seconds, got {self.timestamp!r}") from None
        if not np.isfinite(self.timestamp):
            raise ValueError("Frame.timestamp must be finite")
        self.ego_to_world = _as_array(self.ego_to_world, "Frame.ego_to_world", (4, 4))
        _check_rigid(self.ego_to_world, "Frame.ego_to_world")
        if not isinstance(self.images, dict):
            raise ValueError(f"Frame.images must be a dict camera name -> image, got {type(self.images).__name__}")
        self.images = {k: _check_image(v, f"Frame.images[{k!r}]", None, 3, np.float32) for k, v in self.images.items()}
        for k, img in self.images.items():
            if img.size and (np.nanmin(img) < 0 or np.nanmax(img) > 1):
                raise ValueError(f"Frame.images[{k!r}] values must lie in [0, 1], got [{img.min()}, {img.max()}]")
        for attr, dtype in (("depths", np.float32), ("semantics", np.uint8), ("instances", np.int32)):
            d = getattr(self, attr)
            if not isinstance(d, dict):
                raise ValueError(f"Frame.{attr} must be a dict, got {type(d).__name__}")
            out = {}
            for k, v in d.items():
                if k not in self.images:
                    raise ValueError(f"Frame.{attr}[{k!r}] has no matching entry in Frame.images")
                out[k] = _check_image(v, f"Frame.{attr}[{k!r}]", self.images[k].shape[:2], None, dtype)
            setattr(self, attr, out)
        for k, v in self.semantics.items():
            if v.size and v.max() >= len(SEMANTIC_CLASSES):
                raise ValueError(f"Frame.semantics[{k!r}] has class index {v.max()} >= {len(SEMANTIC_CLASSES)}")
        if self.lidar is not None and not isinstance(self.lidar, LidarPoints):
            raise ValueError(f"Frame.lidar must be LidarPoints or None, got {type(self.lidar).__name__}")
        if not all(isinstance(b, Box3D) for b in self.boxes):
            raise ValueError("Frame.boxes must be a list of Box3D")
        poses = {}
        for k, v in self.camera_poses.items():
            T = _as_array(v, f"Frame.camera_poses[{k!r}]", (4, 4))
            _check_rigid(T, f"Frame.camera_poses[{k!r}]")
            poses[k] = T
        self.camera_poses = poses


@dataclass
class DrivingSequence:
    """A multi-camera driving sequence: a fixed rig of :class:`Camera` and a list of :class:`Frame`.

    Every frame must have an image for every camera, of that camera's size.
    """

    cameras: list[Camera]
    frames: list[Frame]
    name: str = ""
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.cameras or not all(isinstance(c, Camera) for c in self.cameras):
            raise ValueError("DrivingSequence.cameras must be a non-empty list of Camera")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"DrivingSequence.cameras has duplicate names: {names}")
        if not all(isinstance(f, Frame) for f in self.frames):
            raise ValueError("DrivingSequence.frames must be a list of Frame")
        for i, f in enumerate(self.frames):
            for c in self.cameras:
                if c.name not in f.images:
                    raise ValueError(f"DrivingSequence.frames[{i}] has no image for camera {c.name!r}")
                if f.images[c.name].shape[:2] != (c.height, c.width):
                    raise ValueError(
                        f"DrivingSequence.frames[{i}].images[{c.name!r}] is {f.images[c.name].shape[0]}x"
                        f"{f.images[c.name].shape[1]}, camera says {c.height}x{c.width}"
                    )

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def camera(self, name: str) -> Camera:
        """The camera called ``name`` (ValueError naming the known cameras otherwise)."""
        for c in self.cameras:
            if c.name == name:
                return c
        raise ValueError(f"camera {name!r} not in sequence; cameras are {self.camera_names}")

    def _frame(self, index: int) -> Frame:
        if not -len(self.frames) <= index < len(self.frames):
            raise ValueError(f"frame index {index} out of range for {len(self.frames)} frames")
        return self.frames[index]

    def cam_to_world(self, frame_index: int, camera: str) -> np.ndarray:
        """``[4, 4]`` camera-to-world pose of ``camera`` at ``frame_index``."""
        f = self._frame(frame_index)
        if camera in f.camera_poses:
            return f.camera_poses[camera]
        return f.ego_to_world @ self.camera(camera).cam_to_ego

    def viewmats(self, frame_index: int, cameras: Sequence[str] | None = None) -> np.ndarray:
        """``[C, 4, 4]`` world-to-camera matrices (OpenCV), rig order unless ``cameras`` given."""
        names = list(cameras) if cameras is not None else self.camera_names
        return np.stack([invert_transform(self.cam_to_world(frame_index, n)) for n in names])

    def Ks(self, cameras: Sequence[str] | None = None) -> np.ndarray:
        """``[C, 3, 3]`` intrinsics, rig order unless ``cameras`` given."""
        names = list(cameras) if cameras is not None else self.camera_names
        return np.stack([self.camera(n).K for n in names])

    def images(self, frame_index: int, cameras: Sequence[str] | None = None) -> np.ndarray:
        """``[C, H, W, 3]`` float32 images (all selected cameras must share one size)."""
        names = list(cameras) if cameras is not None else self.camera_names
        f = self._frame(frame_index)
        shapes = {f.images[n].shape for n in names}
        if len(shapes) != 1:
            raise ValueError(f"cameras {names} have different image sizes {sorted(shapes)}; select one size")
        return np.stack([f.images[n] for n in names])

    def depths(self, frame_index: int, cameras: Sequence[str] | None = None) -> np.ndarray:
        """``[C, H, W]`` float32 z-depth maps (ValueError if a camera has none)."""
        names = list(cameras) if cameras is not None else self.camera_names
        f = self._frame(frame_index)
        missing = [n for n in names if n not in f.depths]
        if missing:
            raise ValueError(f"frame {frame_index} has no depth for cameras {missing}")
        return np.stack([f.depths[n] for n in names])
