"""The street's world: what varies from street to street (:class:`WorldParams`, drawn by
:func:`draw_world`) and the geometry that follows from it -- the road's centre line in street
coordinates, the ground's height field and its exact ray intersection, the ego's speed profile
and pose, and surface-following poses for vehicles.

Three worlds (``SyntheticConfig.world``):

* ``"classic"``: the street every test and cached result was made on: straight road along +x,
  flat ground ``z = 0``, constant ego speed (``SyntheticConfig.speed``), the same lane change,
  road half-width 7 m, one sun. :func:`draw_world` returns its constants; the generator keeps its
  original code path for it, bit for bit.
* ``"varied"``: every parameter below drawn per street from ``seed`` (its own stream,
  ``np.random.default_rng([seed, 7])``).
* ``"straight"``: drawn like ``varied`` (same stream, same distributions for road width, layout,
  sun, gradient and crossfall), but the road is straight, the ego keeps the right lane (no lane
  change) and cruises at a constant speed ``U[5, 12]`` m/s, ``U{1..4}`` moving vehicles all
  drive in the left lane (either direction, so the side of each that faces away from the ego is
  never seen by its cameras) and parked vehicles stand on the right only.  For novel-view tests
  (AutoSplat, issue 33).
* ``"overtake"`` and ``"busy"`` (issue 36, moving objects as sharp as the street): drawn like
  ``straight`` (the same parameters from the same stream; :class:`StreetScene` lays out their
  movers).  ``overtake``: one car in the left lane, ``U[0, 0.5]`` m of its lane towards the ego
  (0.6-1.7 m between their sides), ``U[2, 4]`` m/s faster than the ego, level with it at a time
  ``U[0.25, 0.5]`` of the way through ``[0, max(4 s, the sequence's end)]``, no other mover.
  ``busy``: :data:`BUSY_LANE_VEHICLES` tries per driving lane, each lane a platoon at one speed
  (the ego's lane ``U[0.85, 1.15]`` times the ego's speed, the left lane ``U[4, 12]`` m/s in
  either direction; a truck with p 0.15), from ``s ~ U[-30, 80]`` m, and :data:`BUSY_PEDESTRIANS`
  tries of pedestrians walking ``U[0.8, 1.8]`` m/s along either sidewalk, each try redrawn up to
  30 times while it comes too close to the ego or another mover (20 and more movers on every
  street, tested).
* ``"divided"`` (issue 33, views a lateral shift truly uncovers): drawn like ``straight`` (the
  same parameters from the same stream), plus a continuous median wall on the centre line
  (``U[0.16, 0.20]`` m thick, ``U[2.0, 2.5]`` m tall: taller than the cameras, 1.6 m) from
  the stream ``np.random.default_rng([seed, 8])``.  Each carriageway has two driving lanes and
  the drawn kerbside lane (``road_half`` = the median's half-width + the ego's distance to it +
  1.5 lanes + the drawn ``road_half - lane_width``).  The ego keeps the inner lane, its centre
  ``U[2.03, 2.12]`` m from the median's face, so that AutoSplat's 1 m lane-change rig stays on
  its side, the 3 m rig stands wholly beyond it (its cameras sit up to 0.6 m off the rig's
  centre) and no camera of the 1, 2 or 3 m rigs is inside the wall; the moving vehicles drive in
  the outer lane on the ego's right, in its direction (their right sides face the kerb), and
  nothing drives or parks on the other carriageway.  The median hides the other carriageway,
  its kerb, footway and the façades' lower floors from every camera of the ego.

Street coordinates: ``s`` along the centre line (m, 0 = the ego at ``t = 0``), ``l`` lateral
(m, left positive).  The centre line starts at the world origin heading +x; with curvature
``kappa != 0`` it is a circular arc of radius ``R = 1/kappa`` (left turn for ``kappa > 0``)
about ``(0, R)``; :meth:`WorldParams.to_street` maps world ``(x, y)`` back by polar coordinates
about that centre, ``s`` wrapped into ``[s_mid - pi|R|, s_mid + pi|R|)`` about the middle of the
scene's layout (which is kept shorter than the circle, so the cut lies in the open country half a
circle away).

Distributions of ``varied`` (per street; U = uniform, "p" = probability):

* ego speed profile (along the road, :meth:`WorldParams.road_speed`; the true speed
  :meth:`WorldParams.ego_speed` is a few per cent higher during a lane change or off the centre
  line of a curve) ``v(t) = clip(v0 + a * max(t - t_a, 0), 0, 15)`` m/s, one of
  standing (p 0.15: v0 = 0, a = 0), pulling away (p 0.20: v0 = 0, a ~ U[1, 3] m/s^2,
  t_a ~ U[-1, 0.5] s), braking (p 0.20: v0 ~ U[3, 15], a ~ -U[2, 5], t_a ~ U[-1, 0.5], to a stop),
  cruising (p 0.45: v0 ~ U[0.5, 15], a ~ U[-0.3, 0.3] from t_a = 0).  Never negative.  Over 200
  seeds at t in [0, 0.2] s each speed bin (standing < 0.5, 0.5-5, 5-10, 10-15 m/s) holds >= 10 %
  (tested).
* path: straight (p 0.35) or a circular arc of radius ``R ~ exp(U[ln 60, ln 400])`` m, left or
  right (p 0.5 each);
* lane change (p 0.4): from the right lane to the left one or back (p 0.5 each), starting at
  ``t_lc ~ U[-2.5, 1]`` s over ``T_lc ~ U[2.5, 5]`` s; laid out along the path (the ego changes
  lanes over the distance ``clip(T_lc * max(v(t_lc), v(t_lc + T_lc)), 12, 60)`` m from where it
  is at ``t_lc``), so a standing ego never moves sideways; without a lane change the ego keeps
  the right lane (p 0.8) or the left one;
* road half-width ``U[5.5, 9]`` m, driving lanes ``U[3.0, 3.6]`` m wide on each side of the
  centre line (the rest of each half is a kerbside lane where vehicles park), sidewalk (building
  setback) ``U[2, 5]`` m, building heights ``U[h_lo, h_lo + U[6, 20]]`` with ``h_lo ~ U[4, 10]`` m;
* parked vehicles ``U{0..12}`` (kerbside lanes, 1.15 m from the kerb, either heading), moving
  ``U{0..4}`` (driving lanes ``+-lane_width / 2``, either direction, ``U[3, 14]`` m/s, from
  ``s ~ U[-30, 60]`` m; a draw that comes within 3 m, bumper to bumper, of the ego or another
  moving vehicle in ``[0, max(4 s, the sequence's end)]`` is redrawn, up to 30 times, then left
  out);
* sun azimuth ``U[0, 360)`` deg, elevation ``U[20, 70]`` deg;
* ground height field ``h(x, y) = A sin(x / L) + B (1 - cos(x / L)) + c Lc tanh(l / Lc)`` with
  ``L ~ U[200, 500]`` m, ``A = g L`` (gradient ``g = 0`` with p 0.4, else ``U[-0.06, 0.06]``),
  ``B = clip(q L^2, -12, 12)`` (vertical curvature ``q = 0`` with p 0.6, else
  ``U[-1/1500, 1/1500]`` 1/m), crossfall ``c = 0`` with p 0.4 else ``U[-0.03, 0.03]`` and
  ``Lc = 40`` m (bounded far away).  The profile runs along the start heading (world x): on a
  straight road ``x = s`` and ``g`` is the road's gradient; on a curved one the gradient turns
  into a side slope as the road turns (a road along a hillside).  Every slope is bounded by
  ``G = |g| + |B|/L + |c|`` (at most 0.15), every height by ``|A| + 2|B| + |c| Lc``.

Ground intersection (:meth:`WorldParams.ground_hit`), along a ray ``o + u d`` with ``f(u)`` its
height above the ground (``f(0) > 0``): the ground can rise along the ray at most at
``S = Sx |d_x| + |c| |d_xy|`` per unit ``u`` (``Sx = (|A| + |B|) / L``), and lies within
``+-max|h|``.  Rays with ``d_z >= S`` never meet it.  Rays with ``d_z < -S`` cross it exactly
once, inside ``[0, u_end]`` (``u_end``: where the ray is below ``-max|h|``); Newton starts from
the tangent plane below the origin.  The rest (rays near the horizon) are marched at 16
geometric samples from ``f(0) / (S - d_z)`` (no crossing can come earlier) to ``u_end``; the
first sample below the ground closes a bracket, Newton starts from its secant point.  Newton is
safeguarded (a step leaving the bracket bisects it instead) and runs until ``|f| < 1e-9`` m (at
most 40 steps); the residual on every rendered ground pixel is below 1e-6 m
(``tests/test_synthetic_world.py``).  A near-horizon ray that enters and leaves the ground
between two march samples (possible only for a ray grazing a crest hundreds of metres away, the
samples being 20-50 % apart) is not seen to cross there; hits beyond ``U_MAX`` are sky.

Poses: the ego and the vehicles stand on the surface: their z axis is the surface normal at their
footprint (pitch from the gradient, roll from the crossfall), their x axis the direction of travel
projected onto the surface; the cameras, mounted 1.6 m above the ego origin, are 1.6 m above the
local ground along the normal.  Buildings, poles and trees stand upright (world z), aligned with
the road's local heading, sunk below the lowest ground point of their footprint (façade floors
count from the ground at the front face).  The ego drives in the lane centres ``+-lane_width / 2``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..scene import make_transform

__all__ = ["WORLDS", "STRAIGHT_WORLDS", "MEDIAN_HALF_RANGE", "MEDIAN_HEIGHT_RANGE", "MEDIAN_GAP_RANGE",
           "MEDIAN_SEGMENT", "BUSY_LANE_VEHICLES", "BUSY_PEDESTRIANS", "SPEED_KINDS", "SPEED_BINS", "WorldParams", "draw_world", "classic_world",
           "classic_ego_pose", "speed_bin"]

WORLDS: tuple[str, ...] = ("classic", "varied", "straight", "overtake", "busy", "divided")
#: worlds drawn like ``straight`` (straight road, constant speed, no lane change, the ego on the right)
STRAIGHT_WORLDS: tuple[str, ...] = ("straight", "overtake", "busy", "divided")
#: ``divided``: the median wall's half-thickness, its height and the ego's distance (centre to the
#: wall's near face) ranges (m), and the length of the wall's segments along the road
MEDIAN_HALF_RANGE = (0.08, 0.10)
MEDIAN_HEIGHT_RANGE = (2.0, 2.5)
MEDIAN_GAP_RANGE = (2.03, 2.12)
MEDIAN_SEGMENT = 8.0
#: ``busy``: placement tries of vehicles per driving lane and of pedestrians (both sidewalks)
BUSY_LANE_VEHICLES = 10
BUSY_PEDESTRIANS = 12
SPEED_KINDS: tuple[str, ...] = ("standing", "pulling_away", "braking", "cruising")
#: the ego-speed bins of issue 32 (m/s): name -> [lo, hi)
SPEED_BINS: dict[str, tuple[float, float]] = {"standing": (0.0, 0.5), "0.5-5": (0.5, 5.0), "5-10": (5.0, 10.0),
                                              "10-15": (10.0, math.inf)}
V_MAX = 15.0
#: centre of the window ``s`` is wrapped into on a curved road (the layout's middle)
S_MID = 60.0
#: ground hits farther than this (in units of the ray direction) are sky
U_MAX = 3000.0
#: ground intersection: samples of the march along a near-horizon ray, and Newton's step limit
MARCH_SAMPLES = 16
NEWTON_STEPS = 40
#: lateral scale of the bounded crossfall term (m)
CROSSFALL_SCALE = 40.0
_SPEED_P = (0.15, 0.20, 0.20, 0.45)


def speed_bin(v: float) -> str:
    """The issue-32 bin name of ego speed ``v`` (m/s)."""
    for name, (lo, hi) in SPEED_BINS.items():
        if lo <= v < hi:
            return name
    raise ValueError(f"speed must be a non-negative number, got {v!r}")


def classic_ego_pose(t: float, speed: float = 8.0, lane_change: bool = True,
                     lane_change_duration: float = 3.0) -> np.ndarray:
    """``[4, 4]`` ego-to-world of the classic street at time ``t``: along +x at ``speed``, optional
    smooth lane change from y=-1.75 to y=+1.75 during ``[0, lane_change_duration]``."""
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


def _smooth(u: float) -> tuple[float, float]:
    """Smooth step ``3u^2 - 2u^3`` of ``u`` clipped to [0, 1] and its derivative."""
    u = min(max(u, 0.0), 1.0)
    return 3 * u * u - 2 * u ** 3, 6 * u - 6 * u * u


@dataclass(frozen=True)
class WorldParams:
    """Every drawn parameter of one street (see the module docstring for the distributions).

    Attributes:
        world: one of :data:`WORLDS`.  seed: the street's seed.
        speed_kind: ``"classic"`` or one of :data:`SPEED_KINDS`.
        v0, accel, t_accel: ego speed ``v(t) = clip(v0 + accel * max(t - t_accel, 0), 0, 15)`` m/s
            (classic: constant ``v0``).
        lane_change: whether the ego changes lanes.  lane_from, lane_to: its lateral offset ``l``
            (m) before and after (equal without a lane change).
        lc_t_start, lc_duration: the lane change's drawn start time and duration (s; classic: by
            time from ``t = 0``).  lc_s_start, lc_length: where it starts along the path and its
            length (m; the varied worlds lay it out by distance).
        curvature: ``1/R`` of the centre line (1/m, left positive; 0 = straight).
        road_half: road half-width (m).  lane_width: driving-lane width (m).
        sidewalk: sidewalk width = building setback from the road edge (m).
        building_height: ``(lo, hi)`` range of building heights (m).
        num_parked, num_moving: vehicle counts.
        sun_azimuth_deg, sun_elevation_deg: the sun's direction (azimuth counter-clockwise from
            world +x).
        grade: road gradient at the start (rise per metre).  vcurv: vertical curvature ``B / L^2``
            at the start (1/m; positive = sag).  crossfall: lateral slope (rise per metre to the
            left).  profile_length: ``L`` of the vertical profile (m).
        median_half, median_height: the ``divided`` world's median wall on the centre line: its
            half-thickness and height (m); 0 elsewhere (no median).
    """

    world: str
    seed: int
    speed_kind: str
    v0: float
    accel: float
    t_accel: float
    lane_change: bool
    lane_from: float
    lane_to: float
    lc_t_start: float
    lc_duration: float
    lc_s_start: float
    lc_length: float
    curvature: float
    road_half: float
    lane_width: float
    sidewalk: float
    building_height: tuple[float, float]
    num_parked: int
    num_moving: int
    sun_azimuth_deg: float
    sun_elevation_deg: float
    grade: float
    vcurv: float
    crossfall: float
    profile_length: float
    median_half: float = 0.0
    median_height: float = 0.0

    # ------------------------------------------------------------------ derived constants
    @property
    def lane_line(self) -> float:
        """Lateral offset of the painted lines between the driving and the kerbside lanes (m):
        ``lane_width``; with a median, beyond the ego's (inner) lane and the outer one."""
        if self.median_half > 0:
            return abs(self.lane_from) + 1.5 * self.lane_width
        return self.lane_width

    @property
    def lane_dash(self) -> float | None:
        """With a median, the lateral offset of the dashed line between the inner and the outer
        driving lane (m); None otherwise (a dashed centre line)."""
        return abs(self.lane_from) + 0.5 * self.lane_width if self.median_half > 0 else None

    @property
    def flat(self) -> bool:
        """True when the ground is the plane ``z = 0``."""
        return self.grade == 0.0 and self.vcurv == 0.0 and self.crossfall == 0.0

    @property
    def sun(self) -> np.ndarray:
        """``[3]`` unit vector towards the sun (world)."""
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    @property
    def _amp(self) -> tuple[float, float]:
        L = self.profile_length
        return self.grade * L, self.vcurv * L * L

    @property
    def max_slope(self) -> float:
        """``G``: a bound on ``|grad h|`` everywhere."""
        A, B = self._amp
        return (abs(A) + abs(B)) / self.profile_length + abs(self.crossfall)

    @property
    def sidewalk_out(self) -> float:
        """Lateral offset of the sidewalk's outer edge (the building line), m."""
        return self.road_half + self.sidewalk

    # ------------------------------------------------------------------ ego motion
    def road_speed(self, t: float) -> float:
        """The drawn speed profile at time ``t``: ``ds/dt`` along the centre line (m/s, >= 0)."""
        if self.speed_kind == "classic":
            return float(self.v0)
        return float(min(max(self.v0 + self.accel * max(t - self.t_accel, 0.0), 0.0), V_MAX))

    def ego_speed(self, t: float) -> float:
        """The ego's true speed at time ``t`` (m/s, >= 0): ``|d position / dt|`` in 3-D, the road
        speed times the path's stretch (lateral motion of a lane change, the offset from the
        centre line on a curve, the climb), at most a few per cent above it.  Classic: ``speed``
        (its velocity along x)."""
        v = self.road_speed(t)
        if self.speed_kind == "classic" or v == 0.0:
            return v
        s, e = self.ego_distance(t), 1e-4
        return float(v * np.linalg.norm(self._path_point(s + e) - self._path_point(s - e)) / (2 * e))

    def _path_point(self, s: float) -> np.ndarray:
        """``[3]`` the ego's ground point at path position ``s``."""
        l = self.ego_lateral(s)[0]
        x, y = self.to_world(s, l)
        return np.array([float(x), float(y), float(self.height(float(x), float(y)))])

    def _g(self, t: float) -> float:
        """Antiderivative of :meth:`road_speed` with ``_g(t_accel) = 0``."""
        v0 = min(max(self.v0, 0.0), V_MAX)
        tau = t - self.t_accel
        if tau <= 0 or self.accel == 0:
            return v0 * tau
        a = self.accel
        t1 = ((V_MAX - v0) / a) if a > 0 else (v0 / -a)
        if tau <= t1:
            return v0 * tau + 0.5 * a * tau * tau
        vend = V_MAX if a > 0 else 0.0
        return v0 * t1 + 0.5 * a * t1 * t1 + vend * (tau - t1)

    def ego_distance(self, t: float) -> float:
        """Centre-line position ``s`` of the ego at ``t`` (m, 0 at ``t = 0``): the integral of
        :meth:`road_speed`."""
        if self.speed_kind == "classic":
            return float(self.v0 * t)
        return float(self._g(t) - self._g(0.0))

    def ego_lateral(self, s: float) -> tuple[float, float]:
        """The ego's lateral offset ``l`` (m) at path position ``s`` and ``dl/ds``."""
        if not self.lane_change:
            return self.lane_from, 0.0
        w, dw = _smooth((s - self.lc_s_start) / self.lc_length)
        return (self.lane_from + (self.lane_to - self.lane_from) * w,
                (self.lane_to - self.lane_from) * dw / self.lc_length)

    def ego_pose(self, t: float) -> np.ndarray:
        """``[4, 4]`` ego-to-world at time ``t`` (frame k is at ``t0 + k * dt``)."""
        if self.world == "classic":
            return classic_ego_pose(t, self.v0, self.lane_change, self.lc_duration)
        s = self.ego_distance(t)
        l, dl = self.ego_lateral(s)
        yaw = math.atan2(dl, 1.0 - self.curvature * l)
        return self.surface_pose(s, l, yaw)

    # ------------------------------------------------------------------ street coordinates
    def to_world(self, s, l):
        """World ``(x, y)`` of street coordinates ``(s, l)`` (scalars or arrays)."""
        k = self.curvature
        if k == 0.0:
            return s, l
        R = 1.0 / k
        th = k * np.asarray(s, dtype=np.float64)
        r = R - np.asarray(l, dtype=np.float64)
        return r * np.sin(th), R - r * np.cos(th)

    def to_street(self, x, y, s_mid: float = S_MID):
        """Street ``(s, l)`` of world ``(x, y)`` (arrays); ``s`` wrapped into the window
        ``[s_mid - pi|R|, s_mid + pi|R|)`` on a curved road (a scene passes the middle of its
        layout)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        k = self.curvature
        if k == 0.0:
            return x, y
        R = 1.0 / k
        sg = 1.0 if k > 0 else -1.0
        dy = y - R
        rho = np.hypot(x, dy)
        th = np.arctan2(sg * x, -sg * dy)
        th_mid = k * s_mid
        th = th_mid + np.mod(th - th_mid + math.pi, 2 * math.pi) - math.pi
        return th / k, R - sg * rho

    def heading(self, s: float) -> float:
        """World yaw of the centre line's tangent at ``s`` (rad)."""
        return self.curvature * s

    # ------------------------------------------------------------------ ground
    def height(self, x, y, grad: bool = False):
        """Ground height ``h`` at world ``(x, y)`` (arrays); with ``grad`` also ``(dh/dx, dh/dy)``."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        A, B = self._amp
        L = self.profile_length
        c = self.crossfall
        k = self.curvature
        zero = np.zeros(np.broadcast(x, y).shape)
        h = hx = hy = zero
        if A != 0.0 or B != 0.0:
            ph = x * (1.0 / L)
            sn = np.sin(ph)
            h = A * sn
            if B != 0.0 or grad:
                cs = np.cos(ph)
                if B != 0.0:
                    h = h + B * (1.0 - cs)
            if grad:
                hx = (A / L) * cs + (B / L) * sn if B != 0.0 else (A / L) * cs
        if c != 0.0:
            if k == 0.0:
                th = np.tanh(y * (1.0 / CROSSFALL_SCALE))
            else:
                R = 1.0 / k
                sg = 1.0 if k > 0 else -1.0
                dy = y - R
                rho = np.maximum(np.sqrt(x * x + dy * dy), 1e-12)
                th = np.tanh((R - sg * rho) * (1.0 / CROSSFALL_SCALE))
            h = h + (c * CROSSFALL_SCALE) * th
            if grad:
                hl = c * (1.0 - th * th)
                if k == 0.0:
                    hy = hl
                else:
                    q = hl * (-sg) / rho
                    hx = hx + q * x
                    hy = q * dy
        if not grad:
            return h + zero if h is not zero else zero
        return h + zero, hx + zero, hy + zero

    def normal(self, x, y) -> np.ndarray:
        """``[..., 3]`` unit upward surface normal at world ``(x, y)``."""
        _, hx, hy = self.height(x, y, grad=True)
        n = np.stack([-hx, -hy, np.ones_like(hx)], -1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def surface_pose(self, s: float, l: float, yaw: float = 0.0, lift: float = 0.0) -> np.ndarray:
        """``[4, 4]`` frame standing on the ground at street ``(s, l)``: z = surface normal, x =
        the surface direction whose horizontal part points at ``yaw`` from the road's tangent, origin
        ``lift`` metres above the surface along the normal."""
        x, y = self.to_world(s, l)
        x, y = float(x), float(y)
        z = float(self.height(x, y))
        n = self.normal(x, y)
        a = self.heading(s) + yaw
        ca, sa = math.cos(a), math.sin(a)
        ex = np.array([ca, sa, -(n[0] * ca + n[1] * sa) / n[2]])      # in the surface, above the heading
        ex /= np.linalg.norm(ex)
        ey = np.cross(n, ex)
        return make_transform(R=np.stack([ex, ey, n], axis=1), t=np.array([x, y, z]) + lift * n)

    def upright_pose(self, s: float, l: float, z: float, yaw: float = 0.0) -> np.ndarray:
        """``[4, 4]`` upright (world z) frame at street ``(s, l)``, height ``z``, x axis at ``yaw``
        from the road's tangent (buildings, poles, trees)."""
        x, y = self.to_world(s, l)
        a = self.heading(s) + yaw
        c, sn = math.cos(a), math.sin(a)
        return make_transform(R=[[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]], t=[float(x), float(y), z])

    @property
    def max_height(self) -> float:
        """A bound on ``|h|`` everywhere (m)."""
        A, B = self._amp
        return abs(A) + 2 * abs(B) + abs(self.crossfall) * CROSSFALL_SCALE

    def ground_hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """First intersection of the rays ``origin + u * dirs`` with the ground (see the module
        docstring for the method and its residual).

        Args:
            origin: ``[3]`` world ray origin.  dirs: ``[..., 3]`` directions (any length).
        Returns:
            ``[...]`` hit parameter ``u`` (inf = no hit within ``U_MAX``).  An origin on or below
            the ground sees no ground (the surface is seen from above only).
        """
        o = np.asarray(origin, dtype=np.float64)
        shape = dirs.shape[:-1]
        d = dirs.reshape(-1, 3).astype(np.float64, copy=False)
        out = np.full(d.shape[0], np.inf)
        if self.flat:
            with np.errstate(divide="ignore", invalid="ignore"):
                u = -o[2] / d[:, 2]
            ok = (d[:, 2] < 0) & (u > 0) & (o[2] > 0) & (u < U_MAX)
            out[ok] = u[ok]
            return out.reshape(shape)
        h0, hx0, hy0 = (float(v) for v in self.height(o[0], o[1], grad=True))
        f0 = o[2] - h0
        if f0 <= 0:
            return out.reshape(shape)
        A, B = self._amp
        sx = (abs(A) + abs(B)) / self.profile_length * (1.0 + 1e-9)       # slope bound of the profile (in x)
        sl = abs(self.crossfall) * (1.0 + 1e-9)                            # of the crossfall (|grad l| = 1)
        Hm = self.max_height + 1e-6
        dxy = np.hypot(d[:, 0], d[:, 1])
        dz = d[:, 2]
        slope = sx * np.abs(d[:, 0]) + sl * dxy + 1e-15   # the fastest the ground can rise along the ray
        # the range a hit can lie in: while the ray is within +-max|h|
        with np.errstate(divide="ignore", invalid="ignore"):
            u_end = np.where(dz > 0, (Hm - o[2]) / dz, (o[2] + Hm) / -dz)
        u_end = np.minimum(np.nan_to_num(u_end, nan=U_MAX, posinf=U_MAX), U_MAX)
        idx = np.nonzero((dz < slope) & (u_end > 0))[0]   # the others rise faster than the ground
        dd, ue, sl_r = d[idx], u_end[idx], slope[idx]
        n = idx.size
        steep = dd[:, 2] < -sl_r                          # f strictly decreasing: one crossing

        def f_at(u: np.ndarray, rows, grad: bool = False):
            r = dd[rows]
            p = o + u[:, None] * r
            if not grad:
                return p[:, 2] - self.height(p[:, 0], p[:, 1])
            h, hx, hy = self.height(p[:, 0], p[:, 1], grad=True)
            return p[:, 2] - h, r[:, 2] - hx * r[:, 0] - hy * r[:, 1]

        # brackets [a, b] with f(a) > 0 >= f(b), and a start u in them
        a = np.zeros(n)
        b = ue.copy()
        u = np.zeros(n)
        has = np.zeros(n, dtype=bool)
        st = np.nonzero(steep)[0]
        if st.size:
            has[st] = True                                # at b the ray is below -max|h| ...
            far = st[b[st] >= U_MAX]                      # ... unless b was cut at U_MAX
            if far.size:
                has[far] = f_at(b[far], far) <= 0
            den = dd[st, 2] - hx0 * dd[st, 0] - hy0 * dd[st, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                u0 = np.where(den < 0, f0 / -den, 0.5 * b[st])
            u[st] = np.clip(u0, a[st], b[st])
        bd = np.nonzero(~steep)[0]
        if bd.size:
            # march from the first point the ray can reach the ground at to the end of its range
            ua = np.minimum(f0 / (sl_r[bd] - dd[bd, 2]), ue[bd])
            prev = np.zeros(bd.size)
            fprev = np.full(bd.size, f0)
            act = np.arange(bd.size)
            for j in range(MARCH_SAMPLES):
                uj = ua[act] * (ue[bd][act] / ua[act]) ** (j / (MARCH_SAMPLES - 1.0))
                fj = f_at(uj, bd[act])
                hit = fj <= 0
                rows = bd[act[hit]]
                a[rows], b[rows], has[rows] = prev[act[hit]], uj[hit], True
                fa_, fb_ = fprev[act[hit]], fj[hit]
                u[rows] = prev[act[hit]] + (uj[hit] - prev[act[hit]]) * fa_ / (fa_ - fb_)     # secant
                prev[act[~hit]], fprev[act[~hit]] = uj[~hit], fj[~hit]
                act = act[~hit]
                if not act.size:
                    break
        # safeguarded Newton in the brackets (bisection when Newton leaves them) to |f| < 1e-9 m
        act = np.nonzero(has)[0]
        for _ in range(NEWTON_STEPS):
            if not act.size:
                break
            f, fp = f_at(u[act], act, grad=True)
            done = np.abs(f) < 1e-9
            above = f > 0
            a[act] = np.where(above, u[act], a[act])
            b[act] = np.where(above, b[act], u[act])
            with np.errstate(divide="ignore", invalid="ignore"):
                nxt = u[act] - f / fp
            bad = ~np.isfinite(nxt) | (nxt <= a[act]) | (nxt >= b[act])
            nxt = np.where(bad, 0.5 * (a[act] + b[act]), nxt)
            u[act] = np.where(done, u[act], nxt)
            act = act[~done]
        res = np.where(has, u, np.inf)
        res[res >= U_MAX] = np.inf
        out[idx] = res
        return out.reshape(shape)


def classic_world(seed: int = 0, speed: float = 8.0, lane_change: bool = True, lane_change_duration: float = 3.0,
                  num_parked: int = 6, num_moving: int = 2) -> WorldParams:
    """The classic street's parameters (its constants; speed, lane change and counts from the config)."""
    sun = np.array([0.35, 0.45, 0.82])
    return WorldParams(
        world="classic", seed=int(seed), speed_kind="classic", v0=float(speed), accel=0.0, t_accel=0.0,
        lane_change=bool(lane_change), lane_from=-1.75, lane_to=1.75 if lane_change else -1.75,
        lc_t_start=0.0, lc_duration=float(lane_change_duration), lc_s_start=0.0,
        lc_length=float(speed * lane_change_duration), curvature=0.0, road_half=7.0, lane_width=3.5, sidewalk=3.0,
        building_height=(6.0, 22.0), num_parked=int(num_parked), num_moving=int(num_moving),
        sun_azimuth_deg=math.degrees(math.atan2(sun[1], sun[0])),
        sun_elevation_deg=math.degrees(math.asin(sun[2] / np.linalg.norm(sun))),
        grade=0.0, vcurv=0.0, crossfall=0.0, profile_length=300.0)


def draw_world(seed: int, world: str = "varied") -> WorldParams:
    """Draw street ``seed``'s :class:`WorldParams` for ``world`` (``"classic"`` returns the classic
    constants). Deterministic: the same ``(seed, world)`` gives the same parameters."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {list(WORLDS)}, got {world!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    if world == "classic":
        return classic_world(int(seed))
    rng = np.random.default_rng([int(seed), 7])
    straight = world in STRAIGHT_WORLDS
    # speed profile
    kind = SPEED_KINDS[int(rng.choice(4, p=_SPEED_P))]
    u_kind = rng.uniform(size=3)        # always three draws, so the rest of the stream is kind-independent
    if straight:
        kind, v0, a, ta = "cruising", 5.0 + 7.0 * u_kind[0], 0.0, 0.0
    elif kind == "standing":
        v0, a, ta = 0.0, 0.0, 0.0
    elif kind == "pulling_away":
        v0, a, ta = 0.0, 1.0 + 2.0 * u_kind[0], -1.0 + 1.5 * u_kind[1]
    elif kind == "braking":
        v0, a, ta = 3.0 + 12.0 * u_kind[0], -(2.0 + 3.0 * u_kind[1]), -1.0 + 1.5 * u_kind[2]
    else:
        v0, a, ta = 0.5 + 14.5 * u_kind[0], -0.3 + 0.6 * u_kind[1], 0.0
    # path
    u_path = rng.uniform(size=3)
    curv = 0.0
    if not straight and u_path[0] >= 0.35:
        R = math.exp(math.log(60.0) + (math.log(400.0) - math.log(60.0)) * u_path[1])
        curv = (1.0 if u_path[2] < 0.5 else -1.0) / R
    # road
    road_half = float(rng.uniform(5.5, 9.0))
    lane_width = float(rng.uniform(3.0, 3.6))
    sidewalk = float(rng.uniform(2.0, 5.0))
    h_lo = float(rng.uniform(4.0, 10.0))
    b_height = (h_lo, h_lo + float(rng.uniform(6.0, 20.0)))
    # lane change
    u_lc = rng.uniform(size=5)
    right, left = -lane_width / 2, lane_width / 2
    lc = bool((not straight) and u_lc[0] < 0.4)
    if lc:
        lane_from, lane_to = (right, left) if u_lc[1] < 0.5 else (left, right)
    else:
        lane_from = right if (straight or u_lc[1] < 0.8) else left
        lane_to = lane_from
    lc_t = -2.5 + 3.5 * u_lc[2]
    lc_dur = 2.5 + 2.5 * u_lc[3]
    # counts, sun, ground
    num_parked = int(rng.integers(0, 13))
    num_moving = int(rng.integers(1 if straight else 0, 5))
    if world == "overtake":
        num_moving = 1
    elif world == "busy":     # the most the layout tries to place; it places as many as fit
        num_moving = 2 * BUSY_LANE_VEHICLES + BUSY_PEDESTRIANS
    sun_az = float(rng.uniform(0.0, 360.0))
    sun_el = float(rng.uniform(20.0, 70.0))
    u_g = rng.uniform(size=7)
    L = 200.0 + 300.0 * u_g[0]
    grade = 0.0 if u_g[1] < 0.4 else -0.06 + 0.12 * u_g[2]
    q = 0.0 if u_g[3] < 0.6 else (-1.0 + 2.0 * u_g[4]) / 1500.0
    vcurv = float(np.clip(q * L * L, -12.0, 12.0)) / (L * L)
    crossfall = 0.0 if u_g[5] < 0.4 else -0.03 + 0.06 * u_g[6]
    w = WorldParams(
        world=world, seed=int(seed), speed_kind=kind, v0=float(v0), accel=float(a), t_accel=float(ta),
        lane_change=lc, lane_from=float(lane_from), lane_to=float(lane_to), lc_t_start=float(lc_t),
        lc_duration=float(lc_dur), lc_s_start=0.0, lc_length=1.0, curvature=float(curv), road_half=road_half,
        lane_width=lane_width, sidewalk=sidewalk, building_height=b_height, num_parked=num_parked,
        num_moving=num_moving, sun_azimuth_deg=sun_az, sun_elevation_deg=sun_el, grade=float(grade),
        vcurv=float(vcurv), crossfall=float(crossfall), profile_length=float(L))
    vref = max(w.road_speed(lc_t), w.road_speed(lc_t + lc_dur))
    length = float(np.clip(lc_dur * vref, 12.0, 60.0))
    extra: dict = {}
    if world == "divided":            # the median, from its own stream: the rest is straight's street
        u_m = np.random.default_rng([int(seed), 8]).uniform(size=3)
        mh = MEDIAN_HALF_RANGE[0] + (MEDIAN_HALF_RANGE[1] - MEDIAN_HALF_RANGE[0]) * u_m[0]
        mz = MEDIAN_HEIGHT_RANGE[0] + (MEDIAN_HEIGHT_RANGE[1] - MEDIAN_HEIGHT_RANGE[0]) * u_m[1]
        gap = MEDIAN_GAP_RANGE[0] + (MEDIAN_GAP_RANGE[1] - MEDIAN_GAP_RANGE[0]) * u_m[2]
        ego = -(mh + gap)
        extra = {"median_half": float(mh), "median_height": float(mz), "lane_from": float(ego),
                 "lane_to": float(ego), "road_half": float(mh + gap + 0.5 * lane_width + road_half)}
    return WorldParams(**{**w.__dict__, "lc_s_start": w.ego_distance(lc_t), "lc_length": length, **extra})
