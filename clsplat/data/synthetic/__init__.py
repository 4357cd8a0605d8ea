"""Procedural street scenes with analytic ground truth.

The generator builds a deterministic (from ``seed``) straight urban street and renders it
with an **independent analytic ray caster** written in numpy (vectorised ray-plane and
ray-oriented-box intersection; nothing here uses Gaussian splatting), so its output can be
used to test a splatting engine.

``SyntheticConfig.world`` picks the street's world (:mod:`~clsplat.data.synthetic.world`):
``"classic"`` (the default, described below, bit for bit as it always was), ``"varied"`` (per
street and seeded: the ego's speed profile from standing to 15 m/s, a straight or curved road,
a lane change or none, road width, setback and building heights, parked and moving vehicles,
the sun, gradient, vertical curvature and crossfall on a height field; the content below laid
out along the curved centre line and standing on that ground) or ``"straight"`` (drawn like
varied, but a straight road, no lane change, constant speed and traffic on the ego's left only);
issue 36's moving-object cases are drawn like straight: ``"overtake"`` (one car overtaking close
beside the ego) and ``"busy"`` (20 and more movers: platoons of cars and trucks in both driving
lanes, pedestrians on both sidewalks; boxes labelled ``car``, ``truck``, ``pedestrian``); issue 33's
``"divided"`` is drawn like straight with a median wall taller than the cameras beside the ego's
lane (hiding the other carriageway) and traffic on the ego's right only, in its direction.

Scene content of the classic world (world frame, metres, z up, road along +x; see
:mod:`clsplat.data.scene`):

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

Shading is Lambertian with one directional sun plus ambient; lamps are emissive; no shadows,
except with ``shadow=True``: a footbridge across the street casts the one shadow the moving
vehicles drive through. ``signals=True`` gives the moving vehicles brake lights and side
indicators at a size the cameras resolve (time-varying appearance to score; each view's
``changing`` mask marks those pixels).  Colours are in ``[0, 1]``.

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

The package, by concern:

* :mod:`~clsplat.data.synthetic.config` -- :class:`SyntheticConfig`, layout constants, the
  vehicle / primitive / render-output records;
* :mod:`~clsplat.data.synthetic.textures` -- world-space procedural textures (ground, sky,
  façades, vehicles, canopies);
* :mod:`~clsplat.data.synthetic.street` -- :class:`StreetScene`: the layout and the analytic ray
  caster (trace, shade, render, LiDAR);
* :mod:`~clsplat.data.synthetic.world` -- :class:`WorldParams` and :func:`draw_world`: what
  varies per street, the road's street coordinates, the ground's height field and its exact ray
  intersection, the ego's speed and pose as functions of time;
* :mod:`~clsplat.data.synthetic.rig` -- the camera rig, the ego trajectory, :func:`render_view`;
* :mod:`~clsplat.data.synthetic.views` -- novel viewpoints with exact ground truth (the rig
  mirrored across a vehicle, moved sideways) and correlated tracker noise on the boxes;
* this module -- :func:`generate_sequence`, which puts them together into a
  :class:`~clsplat.data.scene.DrivingSequence`.

Generation time (6 cameras x 10 frames at 176 x 320 with LiDAR, ``supersample`` 1 and 2) is
recorded in ``bench/RESULTS.md`` (section "issue 20: synthetic package split") with its command.
"""
from __future__ import annotations

from ..scene import SEMANTIC_CLASSES, DrivingSequence, Frame
from .config import (
    CAMERA_HEIGHT,
    LIDAR_MOUNT,
    RIG_YAWS_DEG,
    ROAD_HALF,
    SEM,
    SIDEWALK_OUT,
    RenderOutput,
    SyntheticConfig,
    VehicleSpec,
)
from .rig import ego_pose, make_rig, render_view
from .street import StreetScene
from .world import SPEED_BINS, WORLDS, WorldParams, classic_world, draw_world, speed_bin

__all__ = [
    "SyntheticConfig",
    "WorldParams",
    "draw_world",
    "classic_world",
    "speed_bin",
    "SPEED_BINS",
    "WORLDS",
    "StreetScene",
    "RenderOutput",
    "VehicleSpec",
    "make_rig",
    "render_view",
    "generate_sequence",
    "config_world",
    "ego_pose",
    "RIG_YAWS_DEG",
    "CAMERA_HEIGHT",
    "LIDAR_MOUNT",
    "ROAD_HALF",
    "SIDEWALK_OUT",
    "SEM",
    "SEMANTIC_CLASSES",
]


def config_world(cfg: SyntheticConfig) -> WorldParams:
    """The :class:`WorldParams` of the street ``cfg`` generates (classic: its constants with the
    config's speed, lane change and counts; varied / straight: drawn from ``cfg.seed``)."""
    if cfg.world == "classic":
        return classic_world(cfg.seed, cfg.speed, cfg.lane_change, cfg.lane_change_duration, cfg.num_parked,
                             cfg.num_moving)
    return draw_world(cfg.seed, cfg.world)


def generate_sequence(config: SyntheticConfig | None = None, world_params: WorldParams | None = None,
                      **overrides) -> DrivingSequence:
    """Generate a synthetic multi-camera sequence.

    Args:
        config: a :class:`SyntheticConfig` (default values if None).
        world_params: a varied or straight :class:`WorldParams` to use instead of the one drawn
            from the config's seed (e.g. ``dataclasses.replace(draw_world(s, "varied"),
            speed_kind="pulling_away", v0=0.0, accel=2.0, t_accel=2.0)``: an ego that stands for
            2 s, then pulls away); ``config.world`` is then ignored.
        **overrides: fields of :class:`SyntheticConfig` to replace, e.g. ``num_frames=2``.
    Returns:
        :class:`DrivingSequence` with images, depths, semantics, instances, boxes, and LiDAR
        (if enabled) per frame; ``metadata`` holds the config, the :class:`StreetScene`
        (key ``"scene"``) for rendering extra viewpoints and the street's :class:`WorldParams`
        (key ``"world"``: its ego pose and speed as functions of time, its drawn parameters).
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
    if world_params is not None:
        if not isinstance(world_params, WorldParams) or world_params.world == "classic":
            raise ValueError("world_params must be a varied or straight WorldParams (the classic street is "
                             f"SyntheticConfig(world='classic')), got {world_params!r}")
        world = world_params
    else:
        world = config_world(cfg)
    if world.world == "classic":
        scene = StreetScene(cfg.seed, (-80.0, cfg.speed * duration + 160.0), cfg.num_parked, cfg.num_moving,
                            cfg.poles, cfg.trees, cfg.blink_period, cfg.speed, cfg.signals, cfg.shadow,
                            cfg.fine_texture)
    else:
        s_range = (world.ego_distance(min(cfg.t0, 0.0)) - 80.0, world.ego_distance(duration) + 160.0)
        scene = StreetScene(cfg.seed, s_range, world.num_parked, world.num_moving, cfg.poles, cfg.trees,
                            cfg.blink_period, world.v0, cfg.signals, cfg.shadow, cfg.fine_texture, world=world,
                            t_range=(min(cfg.t0, 0.0), max(4.0, duration)))
    cams = make_rig(cfg.width, cfg.height, cfg.hfov_deg, cfg.back_hfov_deg, cfg.lateral_shift)
    if cfg.cameras is not None:
        by_name = {c.name: c for c in cams}
        cams = [by_name[n] for n in cfg.cameras]
    frames = []
    for k in range(cfg.num_frames):
        t = cfg.t0 + k * cfg.dt
        E = ego_pose(t, cfg.speed, cfg.lane_change, cfg.lane_change_duration) if world.world == "classic" \
            else world.ego_pose(t)
        imgs, deps, sems, insts = {}, {}, {}, {}
        for c in cams:
            r = render_view(scene, c, E, t, cfg.supersample, shade=not cfg.depth_only)
            imgs[c.name], deps[c.name], sems[c.name], insts[c.name] = r.rgb, r.depth, r.semantic, r.instance
        lid = scene.lidar(E, t) if cfg.lidar else None
        frames.append(Frame(t, E, imgs, deps, sems, insts, lid, scene.boxes(t)))
    return DrivingSequence(cams, frames, name=f"synthetic-seed{cfg.seed}", metadata={"config": cfg, "scene": scene, "world": world})
