"""The procedural street and its analytic ray caster: :class:`StreetScene` lays out buildings,
poles, trees and vehicles deterministically from a seed, casts rays against the ground plane and
its oriented boxes (numpy, no Gaussian splatting), shades the hits (Lambertian sun + ambient,
emissive lamps), renders pinhole views with z-depth / semantics / instances and simulates a
spinning LiDAR sweep.
"""
from __future__ import annotations

import math

import numpy as np

from ..scene import Box3D, LidarPoints, invert_transform, make_transform, rotmat_to_quat
from .config import (_AMBIENT, _SUN, BRAKE_PERIOD, FOOTBRIDGE_HALF, FOOTBRIDGE_X, FOOTBRIDGE_Z, LIDAR_MOUNT,
                     ROAD_HALF, SEM, SIDEWALK_OUT, RenderOutput, VehicleSpec, _Box)
from .textures import _box_albedo, _ground_albedo, _signal_lamps, _sky
from .world import BUSY_LANE_VEHICLES, BUSY_PEDESTRIANS, MEDIAN_SEGMENT, STRAIGHT_WORLDS, WorldParams

#: the eight corners of a unit box, the order every box's projection uses
_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


class StreetScene:
    """A procedural street; deterministic from ``seed``.

    Args:
        seed: layout / texture seed.
        x_range: ``(xmin, xmax)`` world extent of buildings and street furniture.
        num_parked, num_moving, poles, trees, blink_period, signals, shadow, fine_texture: see
            :class:`~clsplat.data.synthetic.config.SyntheticConfig`.
        ego_speed: speed of the ego vehicle; moving vehicles drive at speeds relative to it.
        world: the street's :class:`~clsplat.data.synthetic.world.WorldParams`; None or a classic
            one: the classic street (the arguments above, bit for bit).  A varied one lays the
            street out along its centre line (``x_range`` is then the range of ``s``, clipped to
            the window of a curved road) on its height field, with its own vehicle counts, road
            width and sun; ``num_parked``, ``num_moving`` and ``ego_speed`` are ignored.
        t_range: ``(t_lo, t_hi)`` seconds over which moving vehicles of a varied world are kept
            clear of the ego and of each other (the generator passes ``[0, max(4, end)]``).
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
        signals: bool = False,
        shadow: bool = False,
        fine_texture: float = 0.0,
        world: WorldParams | None = None,
        t_range: tuple[float, float] = (0.0, 4.0),
    ) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative int, got {seed!r}")
        if len(x_range) != 2 or not x_range[0] < x_range[1]:
            raise ValueError(f"x_range must be (xmin, xmax) with xmin < xmax, got {x_range!r}")
        self.seed = int(seed)
        self.fine_texture = float(fine_texture)
        self.blink_period = float(blink_period)
        self.world = world
        self.varied = world is not None and world.world != "classic"
        self.sun = _SUN
        if self.varied:
            self.sun = world.sun
            self._layout_varied(world, x_range, poles, trees, signals, shadow, t_range)
            return
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
                                             blink=blink, signals=bool(signals), brake_phase=0.5 + 0.8 * (tid - 1)))
            tid += 1
        slots = rng.permutation(np.arange(-30.0, 60.0, 7.0))
        for i in range(num_parked):
            side = 1.0 if i % 2 == 0 else -1.0
            x = float(slots[i // 2 + (0 if side > 0 else len(slots) // 2)] + rng.uniform(-1, 1))
            size = (rng.uniform(4.0, 4.9), rng.uniform(1.75, 2.0), rng.uniform(1.4, 1.7))
            heading = 0.0 if rng.uniform() < 0.5 else math.pi
            self.vehicles.append(VehicleSpec(tid, size, tuple(rng.uniform(0.1, 0.9, 3)), x, side * 5.25, 0.0, heading))
            tid += 1
        # the footbridge (``shadow``): the only shadow caster, appended last so the layout above is unchanged
        self.casters: list[_Box] = []
        if shadow:
            deck = _Box(make_transform(t=[FOOTBRIDGE_X, 0.0, FOOTBRIDGE_Z]), np.array(FOOTBRIDGE_HALF), "bridge",
                        SEM["building"], 0, np.array([0.5, 0.5, 0.52]))
            self.static.append(deck)
            self.casters.append(deck)
        self.moving_ids = {v.track_id for v in self.vehicles if v.speed != 0}

    # ----------------------------------------------------------------------------------
    def _layout_varied(self, w: WorldParams, s_range, poles: bool, trees: bool, signals: bool, shadow: bool,
                       t_range) -> None:
        """Lay the street of a varied world out along its centre line (see the class docstring)."""
        k = w.curvature
        smin, smax = float(s_range[0]), float(s_range[1])
        self.s_mid = 0.5 * (smin + smax)
        if k != 0.0:                                      # the layout fits in the circle, 40 m to spare
            half = math.pi / abs(k) - 20.0
            smin, smax = max(smin, self.s_mid - half), min(smax, self.s_mid + half)
        self.s_range = (smin, smax)

        def ground_at(s: float, l: float) -> float:
            x, y = w.to_world(s, l)
            return float(w.height(float(x), float(y)))

        def footprint_low(T: np.ndarray, hx: float, hy: float) -> float:
            pts = T[:3, 3][None, :2] + np.array([[a * hx, b * hy] for a in (-1, 0, 1) for b in (-1, 0, 1)]) @ T[:2, :2].T
            return float(np.min(w.height(pts[:, 0], pts[:, 1])))

        rng = np.random.default_rng([self.seed, 1])
        self.static: list[_Box] = []
        key = 0
        hb0, hb1 = w.building_height
        for side in (1.0, -1.0):
            s = smin + rng.uniform(0, 6)
            while s < smax:
                width = rng.uniform(8, 20)
                present = rng.uniform() < 0.85
                d = rng.uniform(8, 14)
                hgt = rng.uniform(hb0, hb1)
                col = np.array([0.55, 0.45, 0.38]) + rng.uniform(-0.18, 0.25, 3)
                setback = rng.uniform(0.0, 1.5)
                gap = rng.uniform(0.5, 4.0)
                l_face = side * (w.sidewalk_out + setback)
                stretch = 1.0 - k * l_face          # arc length along the face per metre of s
                if k * side > 0:                     # inner side of a curve: the face's ends come closer
                    width = min(width, 2.0 * math.sqrt(0.8 * abs(1.0 / k - l_face)))
                if present:
                    sc = s + 0.5 * width / stretch
                    lc = side * (w.sidewalk_out + setback + d / 2)
                    g_face = ground_at(sc, l_face)
                    T = w.upright_pose(sc, lc, 0.0)
                    bottom = min(footprint_low(T, width / 2, d / 2), g_face) - 0.5
                    top = g_face + hgt
                    T[2, 3] = 0.5 * (bottom + top)
                    key += 1
                    self.static.append(_Box(T, np.array([width / 2, d / 2, (top - bottom) / 2]), "facade",
                                            SEM["building"], 0, np.clip(col, 0.1, 0.95), key, ground=g_face - bottom))
                s += (width + gap) / stretch
        rng = np.random.default_rng([self.seed, 2])
        if poles:
            for side in (1.0, -1.0):
                for s in np.arange(smin + rng.uniform(0, 25), smax, 25.0):
                    l = side * (w.road_half + 0.6)
                    g = ground_at(float(s), l)
                    self.static.append(_Box(w.upright_pose(float(s), l, g + 2.85), np.array([0.08, 0.08, 3.15]), "pole",
                                            SEM["other"], 0, np.array([0.45, 0.47, 0.5])))
        rng = np.random.default_rng([self.seed, 3])
        key = 1000
        if trees:
            for side in (1.0, -1.0):
                for s in np.arange(smin + rng.uniform(5, 30), smax, 30.0):
                    key += 1
                    l = side * (w.road_half + min(1.8, 0.6 * w.sidewalk))
                    g = ground_at(float(s), l)
                    self.static.append(_Box(w.upright_pose(float(s), l, g + 1.35), np.array([0.15, 0.15, 1.65]),
                                            "trunk", SEM["other"], 0, np.array([0.35, 0.24, 0.14])))
                    self.static.append(_Box(w.upright_pose(float(s), l, g + 4.2), np.array([1.3, 1.3, 1.2]), "canopy",
                                            SEM["other"], 0, np.array([0.2, 0.45, 0.15]) * rng.uniform(0.8, 1.2), key))
        if w.median_half > 0:
            self.static.extend(self._median(w, smin, smax))
        # vehicles: moving ones (track ids 1..) in the driving lanes, then parked ones at the kerbs
        rng = np.random.default_rng([self.seed, 4])
        self.vehicles: list[VehicleSpec] = []
        ts = np.arange(float(t_range[0]), float(t_range[1]) + 1e-9, 0.1)
        ego_s = np.array([w.ego_distance(float(t)) for t in ts])
        ego_l = np.array([w.ego_lateral(float(s))[0] for s in ego_s])
        tracks = [(ego_s, ego_l, 4.8, 1.9)]              # the ego's own footprint over time
        straight = w.world in STRAIGHT_WORLDS
        tid = 1
        if w.world in ("overtake", "busy"):    # issue 36: their movers (see the world module)
            movers = self._overtaker(w, rng, t_range) if w.world == "overtake" else \
                self._busy_movers(w, rng, ts, tracks)
            for spec in movers:
                self.vehicles.append(VehicleSpec(tid, spec["size"], tuple(rng.uniform(0.1, 0.9, 3)), spec["s0"],
                                                 spec["l"], spec["speed"], spec["heading"], signals=bool(signals),
                                                 brake_phase=0.5 + 0.8 * (tid - 1), world=w, kind=spec["kind"]))
                tid += 1
        for i in range(w.num_moving if w.world not in ("overtake", "busy") else 0):
            for _ in range(30):
                lane = w.lane_width / 2 * (1.0 if (straight or rng.uniform() < 0.5) else -1.0)
                heading = 0.0 if rng.uniform() < 0.5 else math.pi
                if w.median_half > 0:         # divided: the outer lane on the ego's side, its direction
                    lane, heading = w.lane_from - w.lane_width, 0.0
                speed = rng.uniform(3.0, 14.0)
                s0 = rng.uniform(-30.0, 60.0)
                size = (rng.uniform(4.2, 4.8), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.6))
                vs = s0 + speed * ts * math.cos(heading)
                clear = all(np.all((np.abs(vs - ts_s) > (size[0] + L2) / 2 + 3.0)
                                   | (np.abs(lane - ts_l) > (size[1] + W2) / 2 + 0.4))
                            for ts_s, ts_l, L2, W2 in tracks)
                if clear:
                    tracks.append((vs, np.full(ts.size, lane), size[0], size[1]))
                    self.vehicles.append(VehicleSpec(tid, size, tuple(rng.uniform(0.1, 0.9, 3)), s0, lane, speed,
                                                     heading, blink=(tid == 1), signals=bool(signals),
                                                     brake_phase=0.5 + 0.8 * (tid - 1), world=w))
                    tid += 1
                    break
        slots = rng.permutation(np.arange(-30.0, 60.0, 7.0))
        for i in range(w.num_parked):
            if straight:
                side, slot = -1.0, slots[i]
            else:
                side = 1.0 if i % 2 == 0 else -1.0
                slot = slots[i // 2 + (0 if side > 0 else len(slots) // 2)]
            s = float(slot + rng.uniform(-1, 1))
            size = (rng.uniform(4.0, 4.9), rng.uniform(1.75, 2.0), rng.uniform(1.4, 1.7))
            heading = 0.0 if rng.uniform() < 0.5 else math.pi
            self.vehicles.append(VehicleSpec(tid, size, tuple(rng.uniform(0.1, 0.9, 3)), s,
                                             side * (w.road_half - 1.15), 0.0, heading, world=w))
            tid += 1
        self.casters: list[_Box] = []
        if shadow:
            g = ground_at(FOOTBRIDGE_X, 0.0)
            half = np.array([FOOTBRIDGE_HALF[0], max(FOOTBRIDGE_HALF[1], w.sidewalk_out + 2.0), FOOTBRIDGE_HALF[2]])
            deck = _Box(w.upright_pose(FOOTBRIDGE_X, 0.0, g + FOOTBRIDGE_Z), half, "bridge", SEM["building"], 0,
                        np.array([0.5, 0.5, 0.52]))
            self.static.append(deck)
            self.casters.append(deck)
        self.moving_ids = {v.track_id for v in self.vehicles if v.speed != 0}

    # ----------------------------------------------------------------------------------
    @staticmethod
    def _median(w: WorldParams, smin: float, smax: float) -> list[_Box]:
        """The ``divided`` world's median wall on the centre line over ``[smin, smax]``: segments of
        :data:`MEDIAN_SEGMENT` m (2 cm overlap), each pitched with the road's gradient at its
        centre (no roll: the wall stands vertical), ``median_height`` above the ground there and
        sunk 0.5 m below it."""
        out = []
        n = max(1, int(math.ceil((smax - smin) / MEDIAN_SEGMENT)))
        zh = w.median_height
        for i in range(n):
            sc = smin + (i + 0.5) * MEDIAN_SEGMENT
            x, y = (float(v) for v in w.to_world(sc, 0.0))
            g, hx, hy = (float(v) for v in w.height(x, y, grad=True))
            a = w.heading(sc)
            ca, sa = math.cos(a), math.sin(a)
            ex = np.array([ca, sa, hx * ca + hy * sa])
            ex /= np.linalg.norm(ex)
            ey = np.array([-sa, ca, 0.0])
            ez = np.cross(ex, ey)
            T = make_transform(R=np.stack([ex, ey, ez], axis=1), t=np.array([x, y, g]) + 0.5 * (zh - 0.5) * ez)
            out.append(_Box(T, np.array([MEDIAN_SEGMENT / 2 + 0.01, w.median_half, (zh + 0.5) / 2]), "median",
                            SEM["other"], 0, np.array([0.62, 0.61, 0.58]), 2000 + i))
        return out

    @staticmethod
    def _overtaker(w: WorldParams, rng: np.random.Generator, t_range) -> list[dict]:
        """The ``overtake`` world's one mover: a car in the left lane pulled towards the ego,
        faster than it by ``U[2, 4]`` m/s, level with it part way through ``t_range``."""
        t_lo, t_hi = float(t_range[0]), float(t_range[1])
        t_pass = t_lo + (t_hi - t_lo) * rng.uniform(0.25, 0.5)
        speed = w.road_speed(t_pass) + rng.uniform(2.0, 4.0)
        lane = w.lane_width / 2 - rng.uniform(0.0, 0.5)
        size = (rng.uniform(4.2, 4.8), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.6))
        return [{"kind": "car", "size": size, "s0": w.ego_distance(t_pass) - speed * t_pass, "l": lane,
                 "speed": speed, "heading": 0.0}]

    @staticmethod
    def _busy_movers(w: WorldParams, rng: np.random.Generator, ts: np.ndarray, tracks: list) -> list[dict]:
        """The ``busy`` world's movers: a platoon per driving lane (one speed each, so a lane's
        vehicles never close up), then pedestrians on both sidewalks; each try redrawn up to 30
        times while it comes within a margin of a footprint in ``tracks`` (the ego's and those
        placed, appended to) over the times ``ts``."""
        def clear(vs, l, size, gap_s, gap_l):
            return all(np.all((np.abs(vs - ts_s) > (size[0] + L2) / 2 + gap_s)
                              | (np.abs(l - ts_l) > (size[1] + W2) / 2 + gap_l)) for ts_s, ts_l, L2, W2 in tracks)

        out = []
        v_ego = w.road_speed(0.0)
        lanes = [(-w.lane_width / 2, 0.0, v_ego * rng.uniform(0.85, 1.15)),
                 (w.lane_width / 2, 0.0 if rng.uniform() < 0.5 else math.pi, rng.uniform(4.0, 12.0))]
        for lane, heading, speed in lanes:
            for _ in range(BUSY_LANE_VEHICLES):
                for _ in range(30):
                    truck = rng.uniform() < 0.15
                    size = ((rng.uniform(7.0, 9.0), rng.uniform(2.3, 2.5), rng.uniform(2.8, 3.4)) if truck else
                            (rng.uniform(4.2, 4.8), rng.uniform(1.8, 2.0), rng.uniform(1.45, 1.6)))
                    s0 = rng.uniform(-30.0, 80.0)
                    vs = s0 + speed * ts * math.cos(heading)
                    if clear(vs, lane, size, 3.0, 0.4):
                        tracks.append((vs, np.full(ts.size, lane), size[0], size[1]))
                        out.append({"kind": "truck" if truck else "car", "size": size, "s0": s0, "l": lane,
                                    "speed": speed, "heading": heading})
                        break
        for _ in range(BUSY_PEDESTRIANS):
            for _ in range(30):
                side = 1.0 if rng.uniform() < 0.5 else -1.0
                l = side * (w.road_half + w.sidewalk * rng.uniform(0.5, 0.85))
                heading = 0.0 if rng.uniform() < 0.5 else math.pi
                speed = rng.uniform(0.8, 1.8)
                size = (rng.uniform(0.45, 0.65), rng.uniform(0.5, 0.7), rng.uniform(1.6, 1.9))
                s0 = rng.uniform(-20.0, 60.0)
                vs = s0 + speed * ts * math.cos(heading)
                if clear(vs, l, size, 0.5, 0.2):
                    tracks.append((vs, np.full(ts.size, l), size[0], size[1]))
                    out.append({"kind": "pedestrian", "size": size, "s0": s0, "l": l, "speed": speed,
                                "heading": heading})
                    break
        return out

    def _pedestrian_parts(self, v: VehicleSpec, T: np.ndarray) -> list[_Box]:
        """Legs, torso and head of pedestrian ``v`` placed by ``T`` (its box), symmetric in its y."""
        L, W, H = v.size
        col = np.asarray(v.color, dtype=np.float64)
        leg_h, torso_h, head_h = 0.46 * H, 0.36 * H, 0.16 * H
        parts = [("legs", [0.0, sy * W / 4, -H / 2 + leg_h / 2], [0.3 * L, 0.18 * W, leg_h / 2], 0.35 * col)
                 for sy in (-1, 1)]
        parts.append(("torso", [0.0, 0.0, -H / 2 + leg_h + torso_h / 2], [0.4 * L, 0.5 * W, torso_h / 2], col))
        parts.append(("head", [0.0, 0.0, H / 2 - head_h / 2], [0.2 * L, 0.18 * W, head_h / 2],
                      np.array([0.78, 0.6, 0.48])))
        return [_Box(T @ make_transform(t=c), np.asarray(half, dtype=np.float64), kind, SEM["other"], v.track_id,
                     np.asarray(colr, dtype=np.float64), v.track_id) for kind, c, half, colr in parts]

    def vehicle_parts(self, v: VehicleSpec, t: float) -> list[_Box]:
        """Box primitives of vehicle ``v`` at time ``t``, all inside its tracked box."""
        L, W, H = v.size
        T = self._pose(v, t)
        if v.kind == "pedestrian":
            return self._pedestrian_parts(v, T)
        phase_on = math.floor(t / (self.blink_period / 2) + 1e-9) % 2 == 0
        on = v.blink and phase_on
        brake = v.signals and ((t + v.brake_phase) % BRAKE_PERIOD) < BRAKE_PERIOD / 2
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
                            np.asarray(colr, dtype=np.float64), v.track_id, on, v.signals, brake,
                            v.signals and phase_on))
        return out

    def _pose(self, v: VehicleSpec, t: float) -> np.ndarray:
        """``v.pose(t)``; a varied world keeps the last instant's poses (its surface poses cost
        more to make, and the primitives and the boxes of an instant share them)."""
        if not self.varied:
            return v.pose(t)
        cache = getattr(self, "_poses_at", None)
        if cache is None or cache[0] != t:
            cache = self._poses_at = (t, {})
        key = (v.track_id, v.x0, v.y, v.speed, v.heading, v.size)
        T = cache[1].get(key)
        if T is None:
            T = cache[1][key] = v.pose(t)
        return T.copy()

    def primitives(self, t: float) -> list[_Box]:
        """All box primitives at time ``t`` (a varied world keeps the last instant's list: the
        six cameras of a frame share it, and its vehicles' surface poses cost more to make)."""
        if self.varied:
            key = (t, len(self.static), tuple((v.track_id, v.x0, v.y, v.speed, v.heading, v.size, v.color, v.blink,
                                               v.signals, v.brake_phase) for v in self.vehicles))
            cached = getattr(self, "_prims_at", None)
            if cached is not None and cached[0] == key:
                return list(cached[1])
        prims = list(self.static)
        for v in self.vehicles:
            prims.extend(self.vehicle_parts(v, t))
        if self.varied:
            self._prims_at = (key, prims)
            return list(prims)
        return prims

    def boxes(self, t: float) -> list[Box3D]:
        """Tracked vehicle boxes at time ``t`` (world frame)."""
        out = []
        for v in self.vehicles:
            T = self._pose(v, t)
            out.append(Box3D(v.track_id, v.kind, np.array(v.size), T[:3, 3].copy(), rotmat_to_quat(T[:3, :3]),
                             uuid=f"synthetic-{self.seed}-{v.track_id}"))
        return out

    # ----------------------------------------------------------------------------------
    def trace(self, origin: np.ndarray, dirs: np.ndarray, t: float, rects=None, prims=None):
        """Cast rays ``origin + s * dirs``.

        Args:
            origin: ``[3]`` world ray origin.
            dirs: ``[H, W, 3]`` world directions (any length; returned ``s`` is in units of it).
            t: scene time (vehicle poses).
            rects: optional per-primitive ``(y0, y1, x0, x1)`` or None (:meth:`_pixel_rects`),
                restricting the rays tested against each box (``None``: the box cannot be hit).
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
        if self.varied:
            sg = self.world.ground_hit(origin, dirs)
            g = np.isfinite(sg)
        else:
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
                r = rects[i]
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

    def in_shadow(self, points: np.ndarray) -> np.ndarray:
        """``[N]`` bool: world ``points [N, 3]`` whose ray towards the sun hits a shadow caster."""
        out = np.zeros(points.shape[0], dtype=bool)
        for b in self.casters:
            R = b.T[:3, :3]
            ol = (points - b.T[:3, 3]) @ R
            dl = R.T @ self.sun
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-b.half - ol) / dl
                t2 = (b.half - ol) / dl
            tn = np.nanmax(np.minimum(t1, t2), axis=-1)
            tf = np.nanmin(np.maximum(t1, t2), axis=-1)
            out |= (tn <= tf) & (tf > 1e-6)
        return out

    def shade(self, origin, dirs, s, pid, t, prims=None, lighting: bool = True):
        """Colour, semantics, instance ids and (unlit) albedo of traced rays.

        Returns ``(rgb [H,W,3], sem [H,W] uint8, inst [H,W] int32, albedo [H,W,3], emissive [H,W],
        changing [H,W])``; ``changing`` marks hits on signal lamps (on or off) and on moving
        vehicles in shadow.
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
        changing = np.zeros(n, dtype=bool)
        sem = np.full(n, SEM["sky"], dtype=np.uint8)
        inst = np.zeros(n, dtype=np.int32)
        sky = pf == -2
        rgb[sky] = _sky(d[sky])
        alb[sky] = rgb[sky]
        gi = np.nonzero(pf == -1)[0]
        if gi.size:
            p = origin + sf[gi, None] * d[gi]
            if self.varied:
                w = self.world
                ss, ll = w.to_street(p[:, 0], p[:, 1], self.s_mid)
                a, sm = _ground_albedo(ss, ll, self.seed, self.fine_texture, w.road_half, w.lane_line, w.sidewalk_out,
                                       w.lane_dash)
                sun_z = np.clip(w.normal(p[:, 0], p[:, 1]) @ self.sun, 0.0, None)
            else:
                a, sm = _ground_albedo(p[:, 0], p[:, 1], self.seed, self.fine_texture)
                sun_z = _SUN[2]
            alb[gi] = a
            sem[gi] = sm
            lit = np.full(gi.size, 1.0)
            if lighting and self.casters:
                lit[self.in_shadow(p)] = 0.0
            rgb[gi] = a * ((_AMBIENT + (1 - _AMBIENT) * sun_z * lit)[:, None] if lighting else 1.0)
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
                a, em = _box_albedo(b, pl, self.seed, self.fine_texture)
                alb[idx] = a
                emis[idx] = em
                brake, indicator = _signal_lamps(b, pl)
                changing[idx] = brake | indicator
                sem[idx] = b.sem
                inst[idx] = b.inst
                if lighting:
                    axis = np.argmax(np.abs(pl) / b.half, axis=1)
                    nl = np.zeros_like(pl)
                    nl[np.arange(idx.size), axis] = np.sign(pl[np.arange(idx.size), axis])
                    nw = nl @ b.T[:3, :3].T
                    lam = _AMBIENT + (1 - _AMBIENT) * np.clip(nw @ self.sun, 0, None)
                    if self.casters:
                        shadowed = self.in_shadow(p)
                        lam[shadowed] = _AMBIENT
                        if b.inst in self.moving_ids:
                            changing[idx] |= shadowed
                    c = a * lam[:, None]
                    c[em] = a[em]
                    rgb[idx] = c
                else:
                    rgb[idx] = a
        if not lighting:
            rgb[pf == -1] = alb[pf == -1]
        return (np.clip(rgb, 0, 1).reshape(shape + (3,)), sem.reshape(shape), inst.reshape(shape),
                alb.reshape(shape + (3,)), emis.reshape(shape), changing.reshape(shape))

    @staticmethod
    def _pixel_rects(prims: list[_Box], K: np.ndarray, w2c: np.ndarray, width: int,
                     height: int) -> list[tuple[int, int, int, int] | None]:
        """Per primitive, the pixel rectangle ``(y0, y1, x0, x1)`` its projected corners cover (one
        pixel of margin), the whole image when a corner is within 5 cm of the camera plane, None
        when the box is behind the camera or off the image. All boxes at once: most of a view's
        boxes are culled here, and one box at a time this cost more than the tracing."""
        if not prims:
            return []
        half = np.stack([b.half for b in prims])                       # [P, 3]
        Tb = np.stack([b.T for b in prims])                            # [P, 4, 4]
        pw = (_CORNERS[None] * half[:, None, :]) @ Tb[:, :3, :3].transpose(0, 2, 1) + Tb[:, None, :3, 3]
        pc = pw @ w2c[:3, :3].T + w2c[:3, 3]                           # [P, 8, 3] camera frame
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * pc[..., 0] / z + K[0, 2]
            v = K[1, 1] * pc[..., 1] / z + K[1, 2]
        out: list[tuple[int, int, int, int] | None] = []
        behind, near = np.all(z <= 0, axis=1), np.any(z <= 0.05, axis=1)
        umin, umax, vmin, vmax = u.min(1), u.max(1), v.min(1), v.max(1)
        for i in range(len(prims)):
            if behind[i]:
                out.append(None)
                continue
            if near[i]:
                out.append((0, height, 0, width))
                continue
            x0 = max(int(math.floor(umin[i])) - 1, 0)
            x1 = min(int(math.ceil(umax[i])) + 1, width)
            y0 = max(int(math.floor(vmin[i])) - 1, 0)
            y1 = min(int(math.ceil(vmax[i])) + 1, height)
            out.append(None if x0 >= x1 or y0 >= y1 else (y0, y1, x0, x1))
        return out

    # ----------------------------------------------------------------------------------
    def render(self, K, cam_to_world, width: int, height: int, t: float, supersample: int = 1,
               lighting: bool = True, shade: bool = True) -> RenderOutput:
        """Render a pinhole view.

        Args:
            K: ``[3, 3]`` intrinsics.  cam_to_world: ``[4, 4]`` OpenCV camera pose.
            width, height: image size.  t: scene time in seconds.
            supersample: ``s``, RGB averaged over ``s x s`` sub-pixel rays.
            lighting: False renders unlit albedo (used by symmetry tests).
            shade: False traces the depth alone (rgb, semantic and instance zero, ``changing``
                None; ``supersample`` then has nothing to average).
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
        rects = self._pixel_rects(prims, K, invert_transform(T), width, height)

        def dirs_at(offx: float, offy: float) -> np.ndarray:
            u, v = np.meshgrid(np.arange(width) + offx, np.arange(height) + offy)
            dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
            return dc @ T[:3, :3].T  # camera z component is 1 -> s is z-depth

        d = dirs_at(0.5, 0.5)
        s, pid = self.trace(origin, d, t, rects, prims)
        depth = np.where(pid == -2, np.inf, s).astype(np.float32)
        if not shade:
            return RenderOutput(np.zeros((height, width, 3), np.float32), depth, np.zeros((height, width), np.uint8),
                                np.zeros((height, width), np.int32))
        rgb, sem, inst, _, _, changing = self.shade(origin, d, s, pid, t, prims, lighting)
        if supersample > 1:
            acc = np.zeros_like(rgb)
            for j in range(supersample):
                for i in range(supersample):
                    dj = dirs_at((i + 0.5) / supersample, (j + 0.5) / supersample)
                    sj, pj = self.trace(origin, dj, t, rects, prims)
                    acc += self.shade(origin, dj, sj, pj, t, prims, lighting)[0]
            rgb = acc / supersample**2
        return RenderOutput(rgb.astype(np.float32), depth, sem.astype(np.uint8), inst.astype(np.int32), changing)

    def lidar(self, ego_to_world, t: float, n_beams: int = 32, az_step_deg: float = 0.5,
              max_range: float = 80.0, with_semantics: bool = False):
        """Simulated spinning LiDAR sweep at time ``t``; points in the ego frame.

        Beams are evenly spaced in elevation over [-25, +10] degrees; azimuth steps by
        ``az_step_deg``.  Returns points whose range from the sensor is below ``max_range``,
        intensity = unlit albedo luminance (1 for lamps), ring = beam index; with
        ``with_semantics`` the pair ``(points, classes [M] uint8)``, each point's semantic class
        (the per-point labels a PandaSet semseg annotation holds).
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
        # a box whose nearest point is out of range can neither return a point nor hide one
        # (the directions are unit, so ``s`` is the range): most of a long street's boxes
        far = [float(np.linalg.norm(b.T[:3, 3] - origin)) - float(np.linalg.norm(b.half)) > max_range for b in prims]
        everywhere = (0, dw.shape[0], 0, dw.shape[1])
        s, pid = self.trace(origin, dw, t, [None if f else everywhere for f in far], prims)
        _, sem, _, alb, em, _ = self.shade(origin, dw, s, pid, t, prims, lighting=False)
        keep = (pid != -2) & (s < max_range)
        pts = LIDAR_MOUNT + s[keep, None] * dl[keep]
        inten = alb[keep] @ np.array([0.2126, 0.7152, 0.0722])
        inten[em[keep]] = 1.0
        ring = np.broadcast_to(np.arange(n_beams)[:, None], s.shape)[keep]
        lp = LidarPoints(pts.astype(np.float32), inten.astype(np.float32), "ego", ring.astype(np.int32))
        return (lp, sem[keep].astype(np.uint8)) if with_semantics else lp

