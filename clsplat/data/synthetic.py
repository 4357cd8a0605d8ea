"""Procedural street scenes with analytic ground truth.

The generator builds a deterministic (from ``seed``) straight urban street and renders it
with an **independent analytic ray caster** written in numpy (vectorised ray-plane and
ray-oriented-box intersection; nothing here uses Gaussian splatting), so its output can be
used to test a splatting engine.

Scene content (world frame, metres, z up, road along +x; see :mod:`clsplat.data.scene`):

* ground plane ``z = 0``: road ``|y| <= 7`` (asphalt texture, dashed centre line at ``y = 0``,
  solid lines at ``|y| = 3.5`` separating the parking lanes, solid edge lines), sidewalks
  ``7 < |y| <= 10`` (paving tiles), grass beyond (class ``other``);
* building blocks (axis-aligned boxes) on both sides from ``|y| = 10`` with façade texture
  (floors, windows, shop fronts) and random gaps;
* sky at infinity with an elevation gradient (depth ``inf``);
* vehicles built from boxes (body, cabin, four wheels), left-right symmetric in their own
  frame (x forward, y left, z up; albedo depends on ``|y|`` only): parked ones in the
  parking lanes ``|y| = 5.25`` and moving ones in the driving lanes ``|y| = 1.75``; vehicle 1
  has hazard lights (both sides) blinking with period ``blink_period`` seconds;
* optional poles and trees (class ``other``) on the sidewalks.

Shading is Lambertian with one directional sun plus ambient; no shadows; lamps are
emissive.  Colours are in ``[0, 1]``.

Ground truth per camera: RGB (optionally supersampled ``s x s`` per pixel), **z-depth**
(distance along the optical axis, at the pixel centre; ``inf`` for sky), semantic class
(:data:`~clsplat.data.scene.SEMANTIC_CLASSES`) and instance id (track id of the vehicle,
0 otherwise).  A spinning LiDAR (32 beams, -25..+10 deg elevation, 0.5 deg azimuth
step, 80 m range, mounted at ``(0, 0, 1.8)`` in ego) gives points in the ego frame; all
points of a sweep are taken at the frame's instant (no motion distortion).

The rig is nuScenes-like: six cameras in :data:`~clsplat.data.scene.CAMERA_NAMES` order with
yaws 0, +55, -55, +110, -110, 180 degrees, 70 degrees horizontal FOV (85 degrees for
``CAM_BACK``, so that neighbours overlap by 7.5-15 degrees everywhere), mounted 1.6 m above
the ground.  Any extra viewpoint (e.g. the rig shifted 1-3 m sideways) can be rendered with
:func:`render_view` or ``generate_sequence(..., lateral_shift=...)``.

Measured cost on the 2-core development machine (Xeon, numpy 2.4.6): 6 cameras x 10 frames at
176 x 320 with LiDAR and ``supersample=1``: **6.6-8.1 s** (``supersample=2``: 21-25 s);
``tests/test_synthetic.py::test_generation_time`` checks it stays under 30 s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .scene import (
    CAMERA_NAMES,
    SEMANTIC_CLASSES,
    Box3D,
    Camera,
    DrivingSequence,
    Frame,
    LidarPoints,
    invert_transform,
    make_transform,
    rotmat_to_quat,
)

__all__ = [
    "SyntheticConfig",
    "StreetScene",
    "RenderOutput",
    "VehicleSpec",
    "make_rig",
    "render_view",
    "generate_sequence",
    "RIG_YAWS_DEG",
]

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


# --------------------------------------------------------------------------------------
# configuration and layout
# --------------------------------------------------------------------------------------
@dataclass
class SyntheticConfig:
    """Parameters of :func:`generate_sequence`.

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

    def pose(self, t: float) -> np.ndarray:
        """``[4, 4]`` box-centre-to-world transform at time ``t``."""
        x = self.x0 + self.speed * t * math.cos(self.heading)
        c, s = math.cos(self.heading), math.sin(self.heading)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return make_transform(R=R, t=[x, self.y, self.size[2] / 2])


@dataclass
class _Box:
    """A ray-castable oriented box primitive."""

    T: np.ndarray  # [4,4] local (centre) -> world
    half: np.ndarray  # [3]
    kind: str  # facade, body, cabin, wheel, pole, trunk, canopy
    sem: int
    inst: int
    color: np.ndarray  # [3]
    key: int = 0  # texture key
    blink_on: bool = False


@dataclass
class RenderOutput:
    """Ground truth of one view: ``rgb`` [H,W,3] float32, ``depth`` [H,W] float32 z-depth
    (inf = sky), ``semantic`` [H,W] uint8, ``instance`` [H,W] int32."""

    rgb: np.ndarray
    depth: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray


# --------------------------------------------------------------------------------------
# procedural textures (world-space, so every view sees the same surface colour)
# --------------------------------------------------------------------------------------
def _hash2(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic hash of integer lattice points -> float64 in [0, 1)."""
    h = (ix.astype(np.int64) * 374761393 + iy.astype(np.int64) * 668265263 + int(seed) * 982451653) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h.astype(np.float64) / 4294967296.0


def _value_noise(x: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    """Bilinear value noise in [0, 1) with unit lattice spacing."""
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    fx = fx * fx * (3 - 2 * fx)
    fy = fy * fy * (3 - 2 * fy)
    a = _hash2(x0, y0, seed)
    b = _hash2(x0 + 1, y0, seed)
    c = _hash2(x0, y0 + 1, seed)
    d = _hash2(x0 + 1, y0 + 1, seed)
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _ground_albedo(x: np.ndarray, y: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Albedo ``[N,3]`` and semantic ``[N]`` of ground points."""
    n = x.shape[0]
    alb = np.empty((n, 3))
    sem = np.empty(n, dtype=np.uint8)
    ay = np.abs(y)
    road = ay <= ROAD_HALF
    side = (ay > ROAD_HALF) & (ay <= SIDEWALK_OUT)
    grass = ay > SIDEWALK_OUT
    noise = 0.6 * _value_noise(x * 2.0, y * 2.0, seed + 11) + 0.4 * _value_noise(x * 0.3, y * 0.3, seed + 12)
    # road
    g = 0.22 + 0.12 * noise[road]
    alb[road] = np.stack([g, g, g * 1.04], -1)
    sem[road] = SEM["road"]
    xr, yr = x[road], y[road]
    mark = (np.abs(yr) < 0.08) & (np.mod(xr, 6.0) < 3.0)  # dashed centre line
    mark |= np.abs(np.abs(yr) - 3.5) < 0.075  # parking-lane lines
    mark |= np.abs(np.abs(yr) - (ROAD_HALF - 0.15)) < 0.075  # edge lines
    sub = alb[road]
    sub[mark] = [0.92, 0.92, 0.88]
    alb[road] = sub
    # sidewalk: 1 m tiles with joints
    xs, ys = x[side], y[side]
    tile = 0.55 + 0.1 * _hash2(np.floor(xs), np.floor(ys), seed + 13) + 0.08 * noise[side]
    joint = (np.mod(xs, 1.0) < 0.04) | (np.mod(ys, 1.0) < 0.04)
    tile = np.where(joint, tile * 0.7, tile)
    alb[side] = np.stack([tile, tile * 0.98, tile * 0.93], -1)
    sem[side] = SEM["sidewalk"]
    # grass
    gn = noise[grass]
    alb[grass] = np.stack([0.18 + 0.1 * gn, 0.38 + 0.15 * gn, 0.12 + 0.05 * gn], -1)
    sem[grass] = SEM["other"]
    return alb, sem


def _sky(d: np.ndarray) -> np.ndarray:
    """Sky colour ``[N,3]`` for world ray directions ``[N,3]`` (gradient in elevation)."""
    e = d[:, 2] / np.linalg.norm(d, axis=1)
    s = np.clip(e, 0.0, 1.0)[:, None] ** 0.6
    horizon = np.array([0.86, 0.90, 0.95])
    zenith = np.array([0.30, 0.50, 0.85])
    return horizon * (1 - s) + zenith * s


_LIGHT_HEAD = np.array([1.0, 0.96, 0.82])
_LIGHT_TAIL = np.array([0.95, 0.08, 0.06])
_BLINK_ON = np.array([1.0, 0.6, 0.05])
_BLINK_OFF = np.array([0.35, 0.22, 0.08])
_GLASS = np.array([0.10, 0.13, 0.17])


def _box_albedo(b: _Box, pl: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Albedo ``[N,3]`` and emissive flag ``[N]`` for local hit points ``pl`` [N,3] on box ``b``.

    Vehicle parts depend on ``|y|`` only (left-right symmetry in the vehicle frame).
    """
    n = pl.shape[0]
    h = b.half
    axis = np.argmax(np.abs(pl) / h, axis=1)
    sign = np.sign(pl[np.arange(n), axis])
    alb = np.tile(b.color, (n, 1))
    emis = np.zeros(n, dtype=bool)
    x, y, z = pl[:, 0], pl[:, 1], pl[:, 2]
    ay = np.abs(y)
    zr = z + h[2]  # height above the part's bottom
    if b.kind == "facade":
        wx = b.T[:3, 3] + b.T[:3, :3] @ np.zeros(3)
        # u: horizontal coordinate along the face (world x on +-y faces, world y on +-x faces)
        u = np.where(axis == 1, x + wx[0], y + wx[1])
        vert = axis != 2
        zr_w = zr
        floor = np.floor(zr_w / 3.2)
        fz = zr_w - floor * 3.2
        fu = np.mod(u, 2.6)
        win = vert & (floor >= 1) & (fz > 0.9) & (fz < 2.3) & (fu > 0.6) & (fu < 2.0)
        shop = vert & (floor == 0) & (fz > 0.4) & (fz < 2.6) & (np.mod(u, 6.0) > 0.8)
        tone = 0.85 + 0.3 * _value_noise(u * 0.7, zr_w * 0.7, seed + b.key)
        alb = alb * tone[:, None]
        wv = _hash2(np.floor(u / 2.6), floor, seed + 100 + b.key)
        alb[win] = np.stack([0.12 + 0.25 * wv[win], 0.16 + 0.25 * wv[win], 0.22 + 0.28 * wv[win]], -1)
        alb[shop] = [0.2, 0.24, 0.28]
        roof = axis == 2
        alb[roof] = [0.35, 0.33, 0.32]
    elif b.kind == "body":
        W = h[1]
        band = (zr > 0.25) & (zr < 0.45)
        front = (axis == 0) & (sign > 0)
        back = (axis == 0) & (sign < 0)
        lamp = band & (ay > W - 0.45) & (ay < W - 0.15)
        blink = band & (ay >= W - 0.15) & (ay < W - 0.02)
        plate = (ay < 0.26) & (zr > 0.1) & (zr < 0.24)
        alb[front & lamp] = _LIGHT_HEAD
        alb[back & lamp] = _LIGHT_TAIL
        emis |= (front | back) & lamp
        bl = (front | back) & blink
        alb[bl] = _BLINK_ON if b.blink_on else _BLINK_OFF
        emis |= bl & b.blink_on
        alb[(front | back) & plate] = [0.92, 0.92, 0.9]
        side = axis == 1
        stripe = side & (zr > 0.32) & (zr < 0.38)
        alb[stripe] = b.color * 0.55
    elif b.kind == "cabin":
        vert = axis != 2
        glass = vert & (zr > 0.08) & (zr < 2 * h[2] - 0.06)
        glass &= np.where(axis == 1, np.abs(x) < h[0] - 0.1, ay < h[1] - 0.1)
        alb[glass] = _GLASS
    elif b.kind == "canopy":
        nz = _value_noise(pl[:, 0] * 3 + b.key, pl[:, 1] * 3 + pl[:, 2] * 3, seed + 7)
        alb = alb * (0.7 + 0.6 * nz)[:, None]
    return np.clip(alb, 0.0, 1.0), emis


# --------------------------------------------------------------------------------------
# the scene
# --------------------------------------------------------------------------------------
class StreetScene:
    """A procedural street; deterministic from ``seed``.

    Args:
        seed: layout / texture seed.
        x_range: ``(xmin, xmax)`` world extent of buildings and street furniture.
        num_parked, num_moving, poles, trees, blink_period: see :class:`SyntheticConfig`.
        ego_speed: speed of the ego vehicle; moving vehicles drive at speeds relative to it.
    """

    def __init__(
        self,
        seed: int = 0,
        x_range: tuple[float, float] = (-80.0, 160.0),
        num_parked: int = 6,
        num_moving: int = 2,
        poles: bool = True,
        trees: bool = True,
        blink_period: float = 1.0,
        ego_speed: float = 8.0,
    ) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        if len(x_range) != 2 or not x_range[0] < x_range[1]:
            raise ValueError(f"x_range must be (xmin, xmax) with xmin < xmax, got {x_range!r}")
        self.seed = int(seed)
        self.blink_period = float(blink_period)
        # one random stream per feature, so that extending x_range only appends content
        rng = np.random.default_rng([self.seed, 1])
        self.static: list[_Box] = []
        xmin, xmax = float(x_range[0]), float(x_range[1])
        # buildings
        key = 0
        for side in (1.0, -1.0):
            x = xmin + rng.uniform(0, 6)
            while x < xmax:
                w = rng.uniform(8, 20)
                if rng.uniform() < 0.85:
                    d = rng.uniform(8, 14)
                    hgt = rng.uniform(6, 22)
                    col = np.array([0.55, 0.45, 0.38]) + rng.uniform(-0.18, 0.25, 3)
                    c = [x + w / 2, side * (SIDEWALK_OUT + rng.uniform(0.0, 1.5) + d / 2), hgt / 2]
                    key += 1
                    self.static.append(_Box(make_transform(t=c), np.array([w / 2, d / 2, hgt / 2]), "facade",
                                            SEM["building"], 0, np.clip(col, 0.1, 0.95), key))
                x += w + rng.uniform(0.5, 4.0)
        rng = np.random.default_rng([self.seed, 2])
        if poles:
            for side in (1.0, -1.0):
                for x in np.arange(xmin + rng.uniform(0, 25), xmax, 25.0):
                    self.static.append(_Box(make_transform(t=[x, side * (ROAD_HALF + 0.6), 3.0]),
                                            np.array([0.08, 0.08, 3.0]), "pole", SEM["other"], 0,
                                            np.array([0.45, 0.47, 0.5])))
        rng = np.random.default_rng([self.seed, 3])
        key = 1000
        if trees:
            for side in (1.0, -1.0):
                for x in np.arange(xmin + rng.uniform(5, 30), xmax, 30.0):
                    key += 1
                    yy = side * (ROAD_HALF + 1.8)
                    self.static.append(_Box(make_transform(t=[x, yy, 1.5]), np.array([0.15, 0.15, 1.5]), "trunk",
                                            SEM["other"], 0, np.array([0.35, 0.24, 0.14])))
                    self.static.append(_Box(make_transform(t=[x, yy, 4.2]), np.array([1.3, 1.3, 1.2]), "canopy",
                                            SEM["other"], 0, np.array([0.2, 0.45, 0.15]) * rng.uniform(0.8, 1.2), key))
        # vehicles: track ids 1..
        rng = np.random.default_rng([self.seed, 4])
        self.vehicles: list[VehicleSpec] = []
        tid = 1
        moving = [(-1.75, 14.0, 0.0, True), (1.75, 25.0, 1.0, False), (-1.75, -12.0, 0.0, False)]
        for y, dx, dv, blink in moving[:num_moving]:
            size = (rng.uniform(4.2, 4.8), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.6))
            self.vehicles.append(VehicleSpec(tid, size, tuple(rng.uniform(0.1, 0.9, 3)), dx, y, ego_speed + dv, 0.0,
                                             blink=blink))
            tid += 1
        slots = rng.permutation(np.arange(-30.0, 60.0, 7.0))
        for i in range(num_parked):
            side = 1.0 if i % 2 == 0 else -1.0
            x = float(slots[i // 2 + (0 if side > 0 else len(slots) // 2)] + rng.uniform(-1, 1))
            size = (rng.uniform(4.0, 4.9), rng.uniform(1.75, 2.0), rng.uniform(1.4, 1.7))
            heading = 0.0 if rng.uniform() < 0.5 else math.pi
            self.vehicles.append(VehicleSpec(tid, size, tuple(rng.uniform(0.1, 0.9, 3)), x, side * 5.25, 0.0, heading))
            tid += 1

    # ----------------------------------------------------------------------------------
    def vehicle_parts(self, v: VehicleSpec, t: float) -> list[_Box]:
        """Box primitives of vehicle ``v`` at time ``t``, all inside its tracked box."""
        L, W, H = v.size
        T = v.pose(t)
        on = v.blink and (math.floor(t / (self.blink_period / 2) + 1e-9) % 2 == 0)
        col = np.asarray(v.color)
        parts = []
        body_h = 0.58 * H
        clearance = 0.2
        body_c = [0.0, 0.0, -H / 2 + clearance + body_h / 2]
        parts.append(("body", body_c, [L / 2, W / 2, body_h / 2], col))
        cab_h = H - clearance - body_h
        parts.append(("cabin", [-0.06 * L, 0.0, H / 2 - cab_h / 2], [0.27 * L, W / 2 - 0.1, cab_h / 2], col))
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(("wheel", [sx * 0.32 * L, sy * (W / 2 - 0.12), -H / 2 + 0.32], [0.32, 0.12, 0.32],
                              np.array([0.05, 0.05, 0.05])))
        out = []
        for kind, c, half, colr in parts:
            Tl = T @ make_transform(t=c)
            out.append(_Box(Tl, np.asarray(half, dtype=np.float64), kind, SEM["vehicle"], v.track_id,
                            np.asarray(colr, dtype=np.float64), v.track_id, on))
        return out

    def primitives(self, t: float) -> list[_Box]:
        """All box primitives at time ``t``."""
        prims = list(self.static)
        for v in self.vehicles:
            prims.extend(self.vehicle_parts(v, t))
        return prims

    def boxes(self, t: float) -> list[Box3D]:
        """Tracked vehicle boxes at time ``t`` (world frame)."""
        out = []
        for v in self.vehicles:
            T = v.pose(t)
            out.append(Box3D(v.track_id, "car", np.array(v.size), T[:3, 3].copy(), rotmat_to_quat(T[:3, :3]),
                             uuid=f"synthetic-{self.seed}-{v.track_id}"))
        return out

    # ----------------------------------------------------------------------------------
    def trace(self, origin: np.ndarray, dirs: np.ndarray, t: float, rects=None, prims=None):
        """Cast rays ``origin + s * dirs``.

        Args:
            origin: ``[3]`` world ray origin.
            dirs: ``[H, W, 3]`` world directions (any length; returned ``s`` is in units of it).
            t: scene time (vehicle poses).
            rects: optional callable ``box -> (y0, y1, x0, x1) or None`` restricting the rays
                tested against that box (``None`` = box cannot be hit).
            prims: primitives (default :meth:`primitives` at ``t``).
        Returns:
            ``(s, pid)``: ``[H, W]`` hit parameter (inf = none) and primitive index
            (-1 ground, -2 sky).
        """
        if prims is None:
            prims = self.primitives(t)
        Hh, Ww = dirs.shape[:2]
        s = np.full((Hh, Ww), np.inf)
        pid = np.full((Hh, Ww), -2, dtype=np.int32)
        dz = dirs[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            sg = -origin[2] / dz
        g = (dz < 0) & (sg > 0)
        s[g] = sg[g]
        pid[g] = -1
        for i, b in enumerate(prims):
            if rects is None:
                r = (0, Hh, 0, Ww)
            else:
                r = rects(b)
                if r is None:
                    continue
            y0, y1, x0, x1 = r
            d = dirs[y0:y1, x0:x1]
            R = b.T[:3, :3]
            ol = R.T @ (origin - b.T[:3, 3])
            dl = d @ R
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / dl
                t1 = (-b.half - ol) * inv
                t2 = (b.half - ol) * inv
            tn = np.nanmax(np.minimum(t1, t2), axis=-1)
            tf = np.nanmin(np.maximum(t1, t2), axis=-1)
            hit = (tn <= tf) & (tn > 1e-6)
            cur = s[y0:y1, x0:x1]
            upd = hit & (tn < cur)
            if np.any(upd):
                cur[upd] = tn[upd]
                pid[y0:y1, x0:x1][upd] = i
        return s, pid

    def shade(self, origin, dirs, s, pid, t, prims=None, lighting: bool = True):
        """Colour, semantics, instance ids and (unlit) albedo of traced rays.

        Returns ``(rgb [H,W,3], sem [H,W] uint8, inst [H,W] int32, albedo [H,W,3], emissive [H,W])``.
        """
        if prims is None:
            prims = self.primitives(t)
        shape = s.shape
        d = dirs.reshape(-1, 3)
        sf = s.reshape(-1)
        pf = pid.reshape(-1)
        n = sf.shape[0]
        rgb = np.zeros((n, 3))
        alb = np.zeros((n, 3))
        emis = np.zeros(n, dtype=bool)
        sem = np.full(n, SEM["sky"], dtype=np.uint8)
        inst = np.zeros(n, dtype=np.int32)
        sky = pf == -2
        rgb[sky] = _sky(d[sky])
        alb[sky] = rgb[sky]
        gi = np.nonzero(pf == -1)[0]
        if gi.size:
            p = origin + sf[gi, None] * d[gi]
            a, sm = _ground_albedo(p[:, 0], p[:, 1], self.seed)
            alb[gi] = a
            sem[gi] = sm
            rgb[gi] = a * (_AMBIENT + (1 - _AMBIENT) * _SUN[2] if lighting else 1.0)
        hit = np.nonzero(pf >= 0)[0]
        if hit.size:
            order = hit[np.argsort(pf[hit], kind="stable")]
            ids, starts = np.unique(pf[order], return_index=True)
            bounds = list(starts[1:]) + [order.size]
            for k, i0, i1 in zip(ids, starts, bounds):
                idx = order[i0:i1]
                b = prims[k]
                p = origin + sf[idx, None] * d[idx]
                Tinv = invert_transform(b.T)
                pl = p @ Tinv[:3, :3].T + Tinv[:3, 3]
                a, em = _box_albedo(b, pl, self.seed)
                alb[idx] = a
                emis[idx] = em
                sem[idx] = b.sem
                inst[idx] = b.inst
                if lighting:
                    axis = np.argmax(np.abs(pl) / b.half, axis=1)
                    nl = np.zeros_like(pl)
                    nl[np.arange(idx.size), axis] = np.sign(pl[np.arange(idx.size), axis])
                    nw = nl @ b.T[:3, :3].T
                    lam = _AMBIENT + (1 - _AMBIENT) * np.clip(nw @ _SUN, 0, None)
                    c = a * lam[:, None]
                    c[em] = a[em]
                    rgb[idx] = c
                else:
                    rgb[idx] = a
        if not lighting:
            rgb[pf == -1] = alb[pf == -1]
        return (np.clip(rgb, 0, 1).reshape(shape + (3,)), sem.reshape(shape), inst.reshape(shape),
                alb.reshape(shape + (3,)), emis.reshape(shape))

    # ----------------------------------------------------------------------------------
    def render(self, K, cam_to_world, width: int, height: int, t: float, supersample: int = 1,
               lighting: bool = True) -> RenderOutput:
        """Render a pinhole view.

        Args:
            K: ``[3, 3]`` intrinsics.  cam_to_world: ``[4, 4]`` OpenCV camera pose.
            width, height: image size.  t: scene time in seconds.
            supersample: ``s``, RGB averaged over ``s x s`` sub-pixel rays.
            lighting: False renders unlit albedo (used by symmetry tests).
        """
        K = np.asarray(K, dtype=np.float64)
        T = np.asarray(cam_to_world, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must have shape [3, 3], got {list(K.shape)}")
        if T.shape != (4, 4):
            raise ValueError(f"cam_to_world must have shape [4, 4], got {list(T.shape)}")
        for name, v in (("width", width), ("height", height), ("supersample", supersample)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be a positive int, got {v!r}")
        prims = self.primitives(t)
        origin = T[:3, 3].copy()
        w2c = invert_transform(T)
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)

        def rects(b: _Box):
            pw = (corners * b.half) @ b.T[:3, :3].T + b.T[:3, 3]
            pc = pw @ w2c[:3, :3].T + w2c[:3, 3]
            z = pc[:, 2]
            if np.all(z <= 0):
                return None
            if np.any(z <= 0.05):
                return (0, height, 0, width)
            u = K[0, 0] * pc[:, 0] / z + K[0, 2]
            v = K[1, 1] * pc[:, 1] / z + K[1, 2]
            x0 = max(int(math.floor(u.min())) - 1, 0)
            x1 = min(int(math.ceil(u.max())) + 1, width)
            y0 = max(int(math.floor(v.min())) - 1, 0)
            y1 = min(int(math.ceil(v.max())) + 1, height)
            if x0 >= x1 or y0 >= y1:
                return None
            return (y0, y1, x0, x1)

        def dirs_at(offx: float, offy: float) -> np.ndarray:
            u, v = np.meshgrid(np.arange(width) + offx, np.arange(height) + offy)
            dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
            return dc @ T[:3, :3].T  # camera z component is 1 -> s is z-depth

        d = dirs_at(0.5, 0.5)
        s, pid = self.trace(origin, d, t, rects, prims)
        rgb, sem, inst, _, _ = self.shade(origin, d, s, pid, t, prims, lighting)
        if supersample > 1:
            acc = np.zeros_like(rgb)
            for j in range(supersample):
                for i in range(supersample):
                    dj = dirs_at((i + 0.5) / supersample, (j + 0.5) / supersample)
                    sj, pj = self.trace(origin, dj, t, rects, prims)
                    acc += self.shade(origin, dj, sj, pj, t, prims, lighting)[0]
            rgb = acc / supersample**2
        depth = np.where(pid == -2, np.inf, s).astype(np.float32)
        return RenderOutput(rgb.astype(np.float32), depth, sem.astype(np.uint8), inst.astype(np.int32))

    def lidar(self, ego_to_world, t: float, n_beams: int = 32, az_step_deg: float = 0.5,
              max_range: float = 80.0) -> LidarPoints:
        """Simulated spinning LiDAR sweep at time ``t``; points in the ego frame.

        Beams are evenly spaced in elevation over [-25, +10] degrees; azimuth steps by
        ``az_step_deg``.  Returns points whose range from the sensor is below ``max_range``,
        intensity = unlit albedo luminance (1 for lamps), ring = beam index.
        """
        E = np.asarray(ego_to_world, dtype=np.float64)
        if E.shape != (4, 4):
            raise ValueError(f"ego_to_world must have shape [4, 4], got {list(E.shape)}")
        el = np.radians(np.linspace(-25.0, 10.0, n_beams))
        az = np.radians(np.arange(0.0, 360.0, az_step_deg))
        ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
        dl = np.stack([ce * np.cos(az)[None], ce * np.sin(az)[None], np.broadcast_to(se, (n_beams, az.size))], -1)
        dw = dl @ E[:3, :3].T
        origin = E[:3, :3] @ LIDAR_MOUNT + E[:3, 3]
        prims = self.primitives(t)
        s, pid = self.trace(origin, dw, t, None, prims)
        _, _, _, alb, em = self.shade(origin, dw, s, pid, t, prims, lighting=False)
        keep = (pid != -2) & (s < max_range)
        pts = LIDAR_MOUNT + s[keep, None] * dl[keep]
        inten = alb[keep] @ np.array([0.2126, 0.7152, 0.0722])
        inten[em[keep]] = 1.0
        ring = np.broadcast_to(np.arange(n_beams)[:, None], s.shape)[keep]
        return LidarPoints(pts.astype(np.float32), inten.astype(np.float32), "ego", ring.astype(np.int32))


# --------------------------------------------------------------------------------------
# rig, trajectory, sequence
# --------------------------------------------------------------------------------------
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
    """``[4, 4]`` ego-to-world at time ``t``: along +x at ``speed``, optional smooth lane change
    from y=-1.75 to y=+1.75 during ``[0, lane_change_duration]``."""
    y0, y1 = -1.75, 1.75
    x = speed * t
    if lane_change:
        u = min(max(t / lane_change_duration, 0.0), 1.0)
        y = y0 + (y1 - y0) * (3 * u * u - 2 * u**3)
        dydt = (y1 - y0) * (6 * u - 6 * u * u) / lane_change_duration if 0 < u < 1 else 0.0
    else:
        y, dydt = y0, 0.0
    yaw = math.atan2(dydt, speed) if speed > 0 else 0.0
    c, s = math.cos(yaw), math.sin(yaw)
    return make_transform(R=[[c, -s, 0], [s, c, 0], [0, 0, 1]], t=[x, y, 0.0])


def render_view(scene: StreetScene, camera: Camera, ego_to_world, t: float, supersample: int = 1,
                lighting: bool = True) -> RenderOutput:
    """Render ``camera`` (mounted by its ``cam_to_ego``) with the ego at ``ego_to_world`` and time ``t``."""
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    E = np.asarray(ego_to_world, dtype=np.float64)
    if E.shape != (4, 4):
        raise ValueError(f"ego_to_world must have shape [4, 4], got {list(E.shape)}")
    return scene.render(camera.K, E @ camera.cam_to_ego, camera.width, camera.height, t, supersample, lighting)


def generate_sequence(config: SyntheticConfig | None = None, **overrides) -> DrivingSequence:
    """Generate a synthetic multi-camera sequence.

    Args:
        config: a :class:`SyntheticConfig` (default values if None).
        **overrides: fields of :class:`SyntheticConfig` to replace, e.g. ``num_frames=2``.
    Returns:
        :class:`DrivingSequence` with images, depths, semantics, instances, boxes, and LiDAR
        (if enabled) per frame; ``metadata`` holds the config and the :class:`StreetScene`
        (key ``"scene"``) for rendering extra viewpoints.
    """
    cfg = config if config is not None else SyntheticConfig()
    if not isinstance(cfg, SyntheticConfig):
        raise ValueError(f"config must be a SyntheticConfig, got {type(cfg).__name__}")
    if overrides:
        bad = [k for k in overrides if k not in SyntheticConfig.__dataclass_fields__]
        if bad:
            raise ValueError(f"unknown SyntheticConfig fields {bad}")
        cfg = SyntheticConfig(**{**cfg.__dict__, **overrides})
    cfg.validate()
    duration = cfg.t0 + cfg.dt * (cfg.num_frames - 1)
    scene = StreetScene(cfg.seed, (-80.0, cfg.speed * duration + 160.0), cfg.num_parked, cfg.num_moving,
                        cfg.poles, cfg.trees, cfg.blink_period, cfg.speed)
    cams = make_rig(cfg.width, cfg.height, cfg.hfov_deg, cfg.back_hfov_deg, cfg.lateral_shift)
    if cfg.cameras is not None:
        by_name = {c.name: c for c in cams}
        cams = [by_name[n] for n in cfg.cameras]
    frames = []
    for k in range(cfg.num_frames):
        t = cfg.t0 + k * cfg.dt
        E = ego_pose(t, cfg.speed, cfg.lane_change, cfg.lane_change_duration)
        imgs, deps, sems, insts = {}, {}, {}, {}
        for c in cams:
            r = render_view(scene, c, E, t, cfg.supersample)
            imgs[c.name], deps[c.name], sems[c.name], insts[c.name] = r.rgb, r.depth, r.semantic, r.instance
        lid = scene.lidar(E, t) if cfg.lidar else None
        frames.append(Frame(t, E, imgs, deps, sems, insts, lid, scene.boxes(t)))
    return DrivingSequence(cams, frames, name=f"synthetic-seed{cfg.seed}", metadata={"config": cfg, "scene": scene})
