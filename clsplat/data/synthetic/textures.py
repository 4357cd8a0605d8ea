"""Procedural textures of the synthetic street, in world space (every view sees the same surface
colour): integer-lattice hash and value noise, the ground's albedo and class (road with lane
markings, paved sidewalk, grass), the sky gradient, and the albedo / emissive flags of box
primitives (façades with windows and shop fronts, vehicle bodies with lamps and hazard lights,
cabins with glass, tree canopies, the divided road's median wall).
"""
from __future__ import annotations

import numpy as np

from .config import FINE_GRAIN_CELLS, FINE_GRAIN_WEIGHTS, ROAD_HALF, SEM, SIDEWALK_OUT, _Box

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


def fine_grain(u: np.ndarray, v: np.ndarray, seed: int, amplitude: float) -> np.ndarray:
    """Multiplicative grain ``[N]`` in ``[1 - amplitude, 1 + amplitude]`` at surface coordinates
    ``(u, v)`` [N] in metres (``SyntheticConfig.fine_texture``): value noise over the lattices
    ``FINE_GRAIN_CELLS``, mixed by ``FINE_GRAIN_WEIGHTS``."""
    g = np.zeros(u.shape[0])
    for k, (cell, w) in enumerate(zip(FINE_GRAIN_CELLS, FINE_GRAIN_WEIGHTS)):
        g += w * _value_noise(u / cell, v / cell, seed + 31 + k)
    return 1.0 + amplitude * (2.0 * g - 1.0)


def _ground_albedo(x: np.ndarray, y: np.ndarray, seed: int, fine: float = 0.0, road_half: float = ROAD_HALF,
                   lane_line: float = 3.5, sidewalk_out: float = SIDEWALK_OUT,
                   lane_dash: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Albedo ``[N,3]`` and semantic ``[N]`` of ground points at street coordinates ``x`` (along the
    road) and ``y`` (lateral) ``[N]``; ``fine``: the grain's amplitude; ``road_half``: the road's
    half-width, ``lane_line``: lateral offset of the lines between the driving and the kerbside
    lanes, ``sidewalk_out``: the sidewalk's outer edge (defaults: the classic street);
    ``lane_dash``: lateral offset of dashed lines between two driving lanes on each side (None:
    none)."""
    n = x.shape[0]
    alb = np.empty((n, 3))
    sem = np.empty(n, dtype=np.uint8)
    ay = np.abs(y)
    road = ay <= road_half
    side = (ay > road_half) & (ay <= sidewalk_out)
    grass = ay > sidewalk_out
    noise = 0.6 * _value_noise(x * 2.0, y * 2.0, seed + 11) + 0.4 * _value_noise(x * 0.3, y * 0.3, seed + 12)
    # road
    g = 0.22 + 0.12 * noise[road]
    alb[road] = np.stack([g, g, g * 1.04], -1)
    sem[road] = SEM["road"]
    xr, yr = x[road], y[road]
    mark = (np.abs(yr) < 0.08) & (np.mod(xr, 6.0) < 3.0)  # dashed centre line
    mark |= np.abs(np.abs(yr) - lane_line) < 0.075  # parking-lane lines
    mark |= np.abs(np.abs(yr) - (road_half - 0.15)) < 0.075  # edge lines
    if lane_dash is not None:
        mark |= (np.abs(np.abs(yr) - lane_dash) < 0.075) & (np.mod(xr, 6.0) < 3.0)
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
    if fine > 0:
        alb = np.clip(alb * fine_grain(x, y, seed, fine)[:, None], 0.0, 1.0)
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
_BRAKE_ON = np.array([1.0, 0.12, 0.08])
_BRAKE_OFF = np.array([0.32, 0.06, 0.05])


def _signal_lamps(b: _Box, pl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(brake [N], indicator [N])`` bool: local hit points ``pl`` [N,3] on the signal lamps of a
    vehicle body with ``signals`` (``SyntheticConfig.signals``): two brake panels across the rear
    above the tail lamps, an indicator at each end of both sides; both depend on ``|y|`` only."""
    n = pl.shape[0]
    if b.kind != "body" or not b.signals:
        z = np.zeros(n, dtype=bool)
        return z, z
    h = b.half
    axis = np.argmax(np.abs(pl) / h, axis=1)
    sign = np.sign(pl[np.arange(n), axis])
    zr = pl[:, 2] + h[2]
    band = (zr > 0.48) & (zr < 0.83)
    brake = band & (axis == 0) & (sign < 0) & (np.abs(pl[:, 1]) > 0.3)
    indicator = band & (axis == 1) & (np.abs(pl[:, 0]) > h[0] - 0.9)
    return brake, indicator


def _box_albedo(b: _Box, pl: np.ndarray, seed: int, fine: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Albedo ``[N,3]`` and emissive flag ``[N]`` for local hit points ``pl`` [N,3] on box ``b``;
    ``fine``: the grain's amplitude (not on lamps, which are emissive or blink).

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
        zr_w = zr - b.ground  # height above the ground at the face (0 on the classic street)
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
        brake, indicator = _signal_lamps(b, pl)
        alb[brake] = _BRAKE_ON if b.brake_on else _BRAKE_OFF
        alb[indicator] = _BLINK_ON if b.indicator_on else _BLINK_OFF
        emis |= (brake & b.brake_on) | (indicator & b.indicator_on)
    elif b.kind == "cabin":
        vert = axis != 2
        glass = vert & (zr > 0.08) & (zr < 2 * h[2] - 0.06)
        glass &= np.where(axis == 1, np.abs(x) < h[0] - 0.1, ay < h[1] - 0.1)
        alb[glass] = _GLASS
    elif b.kind == "median":
        # concrete panels 2 m wide (local x) with joints; each face its own stain pattern
        u = x + h[0]
        face = np.where(y > 0, 57.0, 0.0)
        tone = 0.8 + 0.35 * _value_noise(u * 1.5 + face, z * 1.5, seed + b.key)
        alb = alb * tone[:, None]
        alb[(axis != 2) & (np.mod(u, 2.0) < 0.05)] *= 0.6
    elif b.kind == "canopy":
        nz = _value_noise(pl[:, 0] * 3 + b.key, pl[:, 1] * 3 + pl[:, 2] * 3, seed + 7)
        alb = alb * (0.7 + 0.6 * nz)[:, None]
    if fine > 0:
        # face coordinates in the box's frame, |y| so that vehicles stay left-right symmetric
        ax = np.argmax(np.abs(pl) / h, axis=1)
        u = np.where(ax == 1, x, ay)          # front/back and top: |y|; sides: x
        v = np.where(ax == 2, x, zr)          # top: x; vertical faces: height
        lamps = emis.copy()
        if b.kind == "body":
            brake, indicator = _signal_lamps(b, pl)
            lamps |= brake | indicator
        grain = fine_grain(u, v, seed + b.key, fine)
        alb = np.where(lamps[:, None], alb, alb * grain[:, None])
    return np.clip(alb, 0.0, 1.0), emis

