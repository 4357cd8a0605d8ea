"""Background losses: the photometric loss of both phases and the flatness constraint C.

Phase 1 renders the road set and the sky set **alone** and supervises each on its own pixels;
phase 2 renders all background Gaussians and supervises every pixel that is not foreground
(a tracked object's instance pixel, or a pixel whose ray hits a tracked box).

``L = (1 - λ) L1 + λ (1 - SSIM) + β C`` with SSIM over an 11x11 Gaussian window, the per-pixel map
with 'same' padding (:func:`clsplat.image_metrics.ssim_map`, as 3DGS's loss) so that it lines up
with the mask, both photometric terms averaged over the mask.

Flatness (MODELS.md §3): ``C = mean over road and sky Gaussians of |roll| + |pitch| + |s_z|``,
angles and the vertical scale expressed in each Gaussian's reference frame (road: the road's
local frame, z = the local road normal from LiDAR; sky: the dome's tangent frame, z radial).
Roll and pitch are measured modulo π (a disc flipped upside down is still flat).
"""
from __future__ import annotations

import numpy as np
import torch

from clsplat.data.scene import DrivingSequence
from clsplat.image_metrics import ssim_map

from ..common.geometry import quat_to_matrix

__all__ = ["masked_photometric", "flatness", "reference_frames", "foreground_mask", "box_hit_masks",
           "box_hit_counts"]


def masked_photometric(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None,
                       lambda_dssim: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(loss, l1, dssim)`` of ``render`` vs ``target`` ``[C, H, W, 3]`` over ``mask`` ``[C, H, W]`` (bool)."""
    a = render.permute(0, 3, 1, 2)
    b = target.permute(0, 3, 1, 2)
    l1_map = (a - b).abs().mean(1)
    s_map = ssim_map(a, b, padding="same").mean(1)
    if mask is None:
        l1, dssim = l1_map.mean(), 1 - s_map.mean()
    else:
        m = mask.to(a.dtype)
        denom = m.sum().clamp_min(1.0)
        l1 = (l1_map * m).sum() / denom
        dssim = ((1 - s_map) * m).sum() / denom
    return (1 - lambda_dssim) * l1 + lambda_dssim * dssim, l1, dssim


def reference_frames(normals: torch.Tensor) -> torch.Tensor:
    """``[N, 3, 3]`` rotations whose third column is the unit normal ``[N, 3]`` (columns = frame axes)."""
    z = torch.nn.functional.normalize(normals, dim=-1)
    helper = torch.where((z[:, :1].abs() < 0.9), z.new_tensor([1.0, 0, 0]), z.new_tensor([0, 1.0, 0]))
    x = torch.nn.functional.normalize(torch.cross(helper, z, dim=-1), dim=-1)
    y = torch.cross(z, x, dim=-1)
    return torch.stack([x, y, z], -1)


def flatness(quats: torch.Tensor, scales: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """Mean of ``|roll| + |pitch| + |s_z|`` of Gaussians ``quats [N,4]``, ``scales [N,3]`` in
    reference ``frames [N,3,3]`` (0 for N = 0)."""
    if quats.shape[0] == 0:
        return quats.sum() * 0
    R = frames.transpose(1, 2) @ quat_to_matrix(torch.nn.functional.normalize(quats, dim=-1))
    # ZYX Euler angles of the Gaussian's frame in the reference frame, modulo pi
    sign = torch.where(R[:, 2, 2] < 0, -1.0, 1.0)
    roll = torch.atan2(R[:, 2, 1] * sign, R[:, 2, 2].abs().clamp_min(1e-12))
    pitch = torch.asin((-R[:, 2, 0]).clamp(-1 + 1e-6, 1 - 1e-6))
    return (roll.abs() + pitch.abs() + scales[:, 2].abs()).mean()


_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
#: the box's 12 edges as corner index pairs (the corners differ in one sign)
_EDGES = [(i, i ^ bit) for i in range(8) for bit in (1, 2, 4) if i < i ^ bit]


def _pixel_bounds(u: np.ndarray, v: np.ndarray, width: int, height: int):
    """(y0, y1, x0, x1), half-open, of the pixels whose centres lie within a pixel of the points
    ``(u, v)`` ``[N]``' bounding rectangle, cut to the image; None when that is empty."""
    x0, x1 = max(0, int(np.floor(u.min() - 0.5)) - 1), min(width, int(np.ceil(u.max() - 0.5)) + 2)
    y0, y1 = max(0, int(np.floor(v.min() - 0.5)) - 1), min(height, int(np.ceil(v.max() - 0.5)) + 2)
    if x0 >= x1 or y0 >= y1:
        return None
    return y0, y1, x0, x1


def _near_box_rect(pc: np.ndarray, half: np.ndarray, K: np.ndarray, width: int, height: int):
    """The rectangle of a box with a corner at or behind the camera plane (``pc`` ``[8, 3]``: its
    corners in the camera frame, ``half`` ``[3]``: its half size): the bounding rectangle of the box
    cut at ``z = eps``, where ``eps`` is half the smallest depth at which an image pixel's ray can meet
    the box; the whole image when the camera centre is (nearly) on or in the box. At least two
    columns wide (the slab test's matrix products then take the path they take on the whole image)."""
    centre = pc.mean(0)
    axes = np.stack([(pc[4] - pc[0]), (pc[2] - pc[0]), (pc[1] - pc[0])], 1) / (2 * half)   # box axes, columns
    o = axes.T @ -centre                                   # the camera centre in the box's frame
    dist = float(np.linalg.norm(np.maximum(np.abs(o) - half, 0.0)))
    xm = max(abs(K[0, 2]), abs(width - K[0, 2])) / K[0, 0]
    ym = max(abs(K[1, 2]), abs(height - K[1, 2])) / K[1, 1]
    # a ray t (x, y, 1) through the image meets the box at |t (x, y, 1)| >= dist: t >= dist / sqrt(1 + xm^2 + ym^2)
    eps = 0.5 * dist / np.sqrt(1.0 + xm * xm + ym * ym)
    if not eps > 1e-6 * max(1.0, float(np.abs(centre).max())):
        return 0, height, 0, width
    z = pc[:, 2]
    pts = [pc[z >= eps]]
    for i, j in _EDGES:
        if (z[i] - eps) * (z[j] - eps) < 0:
            pts.append((pc[i] + (eps - z[i]) / (z[j] - z[i]) * (pc[j] - pc[i]))[None])
    q = np.concatenate(pts)
    if not len(q):
        return None
    q = q[:, :2] / np.maximum(q[:, 2:], eps)
    rect = _pixel_bounds(K[0, 0] * q[:, 0] + K[0, 2], K[1, 1] * q[:, 1] + K[1, 2], width, height)
    if rect is not None and rect[3] - rect[2] < 2:
        y0, y1, x0, x1 = rect
        rect = (y0, y1, x0, x0 + 2) if x0 + 2 <= width else (y0, y1, x1 - 2, x1)
    return rect


def _box_pixel_rect(box, w2c: np.ndarray, K: np.ndarray, width: int, height: int,
                    box_to_world: np.ndarray | None = None):
    """(y0, y1, x0, x1), half-open, holding every pixel whose centre ray can hit ``box``;
    None when the box lies wholly behind the camera or outside the image.

    With every corner in front of the camera the box projects inside its corners' 2D
    bounding rectangle (widened by a pixel against rounding); otherwise inside that of the box
    cut just in front of the camera (:func:`_near_box_rect`).
    ``box_to_world`` ``[4, 4]``: the box's pose when the caller has it already (else computed)."""
    half = box.size / 2
    corners = _CORNER_SIGNS * half
    T = box.box_to_world if box_to_world is None else box_to_world
    world = corners @ T[:3, :3].T + T[:3, 3]
    pc = world @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    if (z <= 0).all():
        return None  # points along a pixel ray have z > 0
    if (z <= 1e-6).any():
        return _near_box_rect(pc, np.asarray(half, np.float64), K, width, height)
    u = K[0, 0] * pc[:, 0] / z + K[0, 2]
    v = K[1, 1] * pc[:, 1] / z + K[1, 2]
    return _pixel_bounds(u, v, width, height)


def _box_hits(cam, cam_to_world: np.ndarray, boxes, width: int, height: int, poses=None):
    """For each box that projects into the image, ``(box, (y0, y1, x0, x1), hit [y1-y0, x1-x0] bool)``:
    the pixels of the box's projected rectangle (:func:`_box_pixel_rect`) whose ray through the pixel
    centre hits the box (a slab test in the box's frame). Rays are made for the rectangle's pixels
    only, the same numbers as for the whole image. ``poses``: per box ``(box_to_world,
    world_to_box)`` ``[4, 4]`` each, when the caller has them (else computed here)."""
    T = cam_to_world
    K = cam.K
    o = T[:3, 3]
    w2c = np.linalg.inv(T)
    for k, b in enumerate(boxes):
        if poses is None:
            b2w = b.box_to_world
            B = np.linalg.inv(b2w)
        else:
            b2w, B = poses[k]
        rect = _box_pixel_rect(b, w2c, K, width, height, b2w)
        if rect is None:
            continue
        y0, y1, x0, x1 = rect
        # the rays of at least two columns (a one-row matrix product rounds otherwise than the image's)
        a0 = x0 if x1 - x0 >= 2 or x0 + 2 <= width else x1 - 2
        a1 = max(x1, a0 + 2)
        u, v = np.meshgrid(np.arange(a0, a1) + 0.5, np.arange(y0, y1) + 0.5)
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ T[:3, :3].T
        ol = B[:3, :3] @ o + B[:3, 3]
        dl = np.ascontiguousarray(d[:, x0 - a0:x1 - a0]) @ B[:3, :3].T
        half = b.size / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - ol) / dl
            t2 = (half - ol) / dl
        lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
        # the NaN-ignoring max / min over the three axes (np.nanmax / np.nanmin's result)
        tn = np.fmax(np.fmax(lo[..., 0], lo[..., 1]), lo[..., 2])
        tf = np.fmin(np.fmin(hi[..., 0], hi[..., 1]), hi[..., 2])
        yield b, rect, (tn <= tf) & (tf > 0)


def box_hit_masks(cam, cam_to_world: np.ndarray, boxes, width: int, height: int):
    """For each box that projects into the image, ``(box, mask [height, width] bool)``: the
    pixels whose ray (through the pixel centre, from camera ``cam`` at pose ``cam_to_world``)
    hits the box (a slab test in the box's frame, inside its projected rectangle only)."""
    for b, (y0, y1, x0, x1), hit in _box_hits(cam, cam_to_world, boxes, width, height):
        m = np.zeros((height, width), bool)
        m[y0:y1, x0:x1] = hit
        yield b, m


def box_hit_counts(cam, cam_to_world: np.ndarray, boxes, width: int, height: int,
                   poses=None) -> list[tuple[object, int]]:
    """``[(box, pixels)]`` for each box that projects into the image: how many pixels of
    :func:`box_hit_masks`' mask for it are set (the same slab test, counted inside the box's
    projected rectangle without building a full-image mask). ``poses``: per box ``(box_to_world,
    world_to_box)`` when the caller has them (one frame's boxes seen by several cameras)."""
    return [(b, int(np.count_nonzero(hit)))
            for b, _, hit in _box_hits(cam, cam_to_world, boxes, width, height, poses)]


def foreground_mask(seq: DrivingSequence, frame: int, cameras: list[str],
                    tracks: set[int] | None = None) -> np.ndarray:
    """``[C, H, W]`` bool: pixels of the tracked objects ``tracks`` (None: every track) at
    ``frame`` (instance masks when the data has them, else pixels whose ray hits the box)."""
    f = seq.frames[frame]
    boxes = [b for b in f.boxes if tracks is None or b.track_id in tracks]
    out = []
    for c in cameras:
        cam = seq.camera(c)
        if c in f.instances:
            inst = f.instances[c]
            out.append(inst > 0 if tracks is None else np.isin(inst, sorted(tracks)))
            continue
        m = np.zeros((cam.height, cam.width), bool)
        if boxes:
            T = seq.cam_to_world(frame, c)
            for _, hit in box_hit_masks(cam, T, boxes, cam.width, cam.height):
                m |= hit
        out.append(m)
    return np.stack(out)
