"""Constants and plain data of the synthetic street: :class:`SyntheticConfig` (what
:func:`~clsplat.data.synthetic.generate_sequence` takes), the street's layout constants (road,
sidewalk, rig and LiDAR mounts, sun), :class:`VehicleSpec` (a vehicle and its motion),
``_Box`` (the ray-castable primitive every surface is made of) and :class:`RenderOutput`
(one view's ground truth). No rendering happens here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..scene import CAMERA_NAMES, SEMANTIC_CLASSES, make_transform

SEM = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}

#: camera yaw in the ego frame (degrees, counter-clockwise from ego +x), rig order.
RIG_YAWS_DEG: tuple[float, ...] = (0.0, 55.0, -55.0, 110.0, -110.0, 180.0)
_RIG_POS = ((1.7, 0.0), (1.5, 0.5), (1.5, -0.5), (0.0, 0.6), (0.0, -0.6), (-1.0, 0.0))
CAMERA_HEIGHT = 1.6
LIDAR_MOUNT = np.array([0.0, 0.0, 1.8])
ROAD_HALF = 7.0
SIDEWALK_OUT = 10.0
_SUN = np.array([0.35, 0.45, 0.82]) / np.linalg.norm([0.35, 0.45, 0.82])
_AMBIENT = 0.55
#: ``shadow``: the footbridge's centre x (m), deck half-extents (x, y, z) and deck centre height;
#: placed so that the shadow band (offset by the sun towards -x, -y) is crossed by both moving
#: vehicles of the default layout within the first 3 s (vehicle 2 near t = 0, vehicle 1 near t = 1.6 s)
FOOTBRIDGE_X = 29.0
FOOTBRIDGE_HALF = (2.0, 12.0, 0.3)
FOOTBRIDGE_Z = 5.3
#: ``signals``: brake lights are on for the first half of every period (seconds)
BRAKE_PERIOD = 2.0
#: ``fine_texture``: lattice spacings (m) of the grain's two octaves and their weights; 4 cm is
#: about one pixel on the road 5 m ahead at 480 x 270 (70 deg FOV), 12 cm a few pixels
FINE_GRAIN_CELLS = (0.04, 0.12)
FINE_GRAIN_WEIGHTS = (0.6, 0.4)


@dataclass
class SyntheticConfig:
    """Parameters of :func:`~clsplat.data.synthetic.generate_sequence`.

    Attributes:
        height, width: image size of every camera (pixels).
        num_frames: number of frames; frame k is at ``k * dt`` seconds.
        seed: layout / texture seed; same seed and config -> identical output.
        dt: frame interval in seconds.
        speed: ego speed in m/s along +x.
        lane_change: if True the ego moves from the right lane (y=-1.75) to the left lane
            (y=+1.75) with a smooth-step profile over ``lane_change_duration`` seconds from t=0.
        num_parked: parked vehicles.  num_moving: moving vehicles (<= 3).
        poles, trees: add street furniture.
        lidar: simulate the LiDAR sweep per frame.
        supersample: ``s``; RGB is the mean of ``s x s`` sub-pixel rays (depth/semantics
            always use the pixel centre ray).
        hfov_deg, back_hfov_deg: horizontal FOV of the five front/side cameras and of CAM_BACK.
        lateral_shift: shift of the whole camera rig along ego +y (novel-view evaluation).
        blink_period: period of the hazard lights of vehicle 1, seconds.
        cameras: names of the cameras to render (a subset of CAMERA_NAMES, in any order); the
            default renders all six. Cameras left out are never rendered.
        t0: time of frame 0 in seconds (frame k is at ``t0 + k * dt``).
        signals: moving vehicles carry brake lights (two panels across the rear, about 0.6 x
            0.35 m each, on for half of every ``BRAKE_PERIOD`` seconds, phase per vehicle) and
            side indicators (0.9 x 0.35 m at each end of both sides, blinking with
            ``blink_period``): time-varying appearance at a size a camera resolves.
        shadow: a footbridge across the street at ``x = FOOTBRIDGE_X`` casts the only shadow of
            the scene (sun direction fixed), which the moving vehicles drive through.
        fine_texture: amplitude in ``[0, 1]`` of a fine world-space grain (value noise at
            ``FINE_GRAIN_CELLS`` metres) multiplying the albedo of the ground, façades and
            vehicles: detail a few pixels wide at PandaSet-like resolutions, so that a blurred
            reconstruction costs SSIM (the default street's texture varies over 0.5 m and more,
            which blur hardly changes). 0 (default) leaves the street as it was, bit for bit.
        world: ``"classic"`` (default: the street above, bit for bit), ``"varied"`` (speed profile,
            path curvature, lane change, road width, layout, traffic, sun, gradient and crossfall
            drawn per street from ``seed``; ``speed``, ``lane_change``, ``lane_change_duration``,
            ``num_parked`` and ``num_moving`` are then ignored) or ``"straight"`` (drawn like
            varied, but a straight road, no lane change, constant speed, traffic on the ego's left
            only); issue 36's test cases for moving objects: ``"overtake"`` (drawn like straight,
            one car overtaking close beside the ego) and ``"busy"`` (drawn like straight, 20 and
            more movers: platoons of cars and trucks in both driving lanes, pedestrians on both
            sidewalks); issue 33's ``"divided"`` (drawn like straight, a median wall taller than
            the cameras beside the ego's lane, traffic on the ego's side only). See
            :mod:`clsplat.data.synthetic.world`.
        depth_only: trace the depth maps only, no shading: images, semantics and instances are
            zero (what an image-blind control reads: a window's depth and ego poses, at about
            half the cost of a full frame).
    """

    height: int = 176
    width: int = 320
    num_frames: int = 10
    seed: int = 0
    dt: float = 0.1
    speed: float = 8.0
    lane_change: bool = True
    lane_change_duration: float = 3.0
    num_parked: int = 6
    num_moving: int = 2
    poles: bool = True
    trees: bool = True
    lidar: bool = True
    supersample: int = 1
    hfov_deg: float = 70.0
    back_hfov_deg: float = 85.0
    lateral_shift: float = 0.0
    blink_period: float = 1.0
    cameras: tuple[str, ...] | None = None
    t0: float = 0.0
    signals: bool = False
    shadow: bool = False
    fine_texture: float = 0.0
    world: str = "classic"
    depth_only: bool = False

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        for name in ("height", "width", "num_frames", "supersample"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"SyntheticConfig.{name} must be a positive int, got {v!r}")
        for name in ("num_parked", "num_moving"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ValueError(f"SyntheticConfig.{name} must be a non-negative int, got {v!r}")
        if self.num_moving > 3:
            raise ValueError(f"SyntheticConfig.num_moving must be <= 3, got {self.num_moving}")
        if self.num_parked > 16:
            raise ValueError(f"SyntheticConfig.num_parked must be <= 16, got {self.num_parked}")
        for name in ("dt", "lane_change_duration", "blink_period"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"SyntheticConfig.{name} must be a positive number, got {v!r}")
        if not (isinstance(self.speed, (int, float)) and math.isfinite(self.speed) and self.speed >= 0):
            raise ValueError(f"SyntheticConfig.speed must be a non-negative number, got {self.speed!r}")
        for name in ("hfov_deg", "back_hfov_deg"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 1.0 <= v <= 170.0):
                raise ValueError(f"SyntheticConfig.{name} must be in [1, 170] degrees, got {v!r}")
        if self.cameras is not None:
            names = list(self.cameras) if isinstance(self.cameras, (list, tuple)) else None
            bad = [c for c in names or [] if c not in CAMERA_NAMES]
            if names is None or not names or bad or len(set(names)) != len(names):
                raise ValueError(f"SyntheticConfig.cameras must be distinct names from {list(CAMERA_NAMES)}, "
                                 f"got {self.cameras!r}")
        if not (isinstance(self.t0, (int, float)) and math.isfinite(self.t0) and self.t0 >= 0):
            raise ValueError(f"SyntheticConfig.t0 must be a non-negative number, got {self.t0!r}")
        if not isinstance(self.depth_only, bool):
            raise ValueError(f"SyntheticConfig.depth_only must be a bool, got {self.depth_only!r}")
        if not (isinstance(self.fine_texture, (int, float)) and not isinstance(self.fine_texture, bool)
                and 0.0 <= self.fine_texture <= 1.0):
            raise ValueError(f"SyntheticConfig.fine_texture must be a number in [0, 1], got {self.fine_texture!r}")
        worlds = ("classic", "varied", "straight", "overtake", "busy", "divided")
        if self.world not in worlds:
            raise ValueError(f"SyntheticConfig.world must be one of {list(worlds)}, got {self.world!r}")
        if not (isinstance(self.lateral_shift, (int, float)) and abs(self.lateral_shift) <= 5.0):
            raise ValueError(f"SyntheticConfig.lateral_shift must be a number in [-5, 5] m, got {self.lateral_shift!r}")


@dataclass
class VehicleSpec:
    """A vehicle: box size (length, width, height), colour, motion along x in lane ``y``."""

    track_id: int
    size: tuple[float, float, float]
    color: tuple[float, float, float]
    x0: float
    y: float
    speed: float
    heading: float  # 0 = +x, pi = -x
    blink: bool = False
    signals: bool = False     # brake lights and side indicators
    brake_phase: float = 0.0  # seconds: brake lights are on while (t + phase) mod BRAKE_PERIOD < half of it
    #: the varied worlds: ``x0``/``y`` are street coordinates ``(s, l)`` of
    #: :class:`~clsplat.data.synthetic.world.WorldParams`, ``heading`` is relative to the road, and
    #: the vehicle stands on the ground (tilted with it); None: the classic street
    world: Any = None
    #: what it is (issue 36's ``busy`` world): ``"car"`` (every vehicle before it), ``"truck"`` (the
    #: car's parts at a truck's size) or ``"pedestrian"`` (legs, torso, head; semantic class
    #: ``other``); its tracked boxes carry it as their label
    kind: str = "car"

    def pose(self, t: float) -> np.ndarray:
        """``[4, 4]`` box-centre-to-world transform at time ``t``."""
        if self.world is not None and self.world.world != "classic":
            s = self.x0 + self.speed * t * math.cos(self.heading)
            return self.world.surface_pose(s, self.y, self.heading, lift=self.size[2] / 2)
        x = self.x0 + self.speed * t * math.cos(self.heading)
        c, s = math.cos(self.heading), math.sin(self.heading)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return make_transform(R=R, t=[x, self.y, self.size[2] / 2])


@dataclass
class _Box:
    """A ray-castable oriented box primitive."""

    T: np.ndarray  # [4,4] local (centre) -> world
    half: np.ndarray  # [3]
    kind: str  # facade, body, cabin, wheel, pole, trunk, canopy, median
    sem: int
    inst: int
    color: np.ndarray  # [3]
    key: int = 0  # texture key
    blink_on: bool = False
    signals: bool = False     # brake lights and side indicators (``SyntheticConfig.signals``)
    brake_on: bool = False
    indicator_on: bool = False
    ground: float = 0.0       # façades: height of the ground at the face above the box's bottom (m)


@dataclass
class RenderOutput:
    """Ground truth of one view: ``rgb`` [H,W,3] float32, ``depth`` [H,W] float32 z-depth
    (inf = sky), ``semantic`` [H,W] uint8, ``instance`` [H,W] int32, ``changing`` [H,W] bool:
    pixels whose colour changes with time in the object's own frame (signal lamps, on or off,
    and vehicle surfaces in shadow)."""

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    changing: np.ndarray | None = None

