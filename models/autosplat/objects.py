"""Foreground objects: templates, the reflection (mirror) maps and the residual-SH MLP.

Each tracked object is a Gaussian set in its **object frame** (the box frame: origin at the box
centre, x forward, y left, z up). It starts from a template: a car shape (body box plus a
narrower cabin box, scaled to the track's box) for vehicles, or the box surface otherwise; LiDAR
points that fell inside the box over the training frames are added in the object frame.

Reflected-Gaussian consistency (MODELS.md §3): the object's symmetry plane is y = 0 in the
object frame. The mirror maps a Gaussian to (x, -y, z), quaternion (w, x, y, z) -> (w, -x, y, -z),
scales unchanged, SH coefficient of order m multiplied by -1 where m < 0 (3DGS order m = -l..l).
Every map is an involution.

Dynamic appearance: :class:`ResidualSH` maps (Fourier time embedding, Fourier position
embedding in box-normalised coordinates) to per-Gaussian SH residuals ``[M, K, 3]``; the last
layer starts at zero, so residuals start at zero; an L1 penalty keeps them sparse.

The object budget (issue 36): :func:`track_box_pixels` counts, per decomposed track and training
frame, the pixels whose rays hit the track's **box** (what a user gives: tracked boxes, not instance
masks), and :func:`object_budget` turns the counts and the preset's budget fields into the
foreground stage's iterations and each track's initial points and Gaussian cap
(:class:`ObjectBudget`); with the budget fields at their defaults it is today's fixed budget and
counts nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import nn

from clsplat.data.scene import DrivingSequence, invert_transform

from .init import project_to_pixels

__all__ = ["car_template", "box_surface_template", "sh_mirror_signs", "mirror_means", "mirror_quats",
           "mirror_sh", "ResidualSH", "object_points_and_colours", "track_box_pixels", "ObjectBudget",
           "object_budget", "fixed_object_budget", "budget_scales"]


def _box_surface(n: int, centre, half, rng: np.random.Generator, skip_bottom: bool = True) -> np.ndarray:
    """``n`` points uniformly on the surface of an axis-aligned box (bottom face left out)."""
    half = np.asarray(half, np.float64)
    faces = []
    for ax in range(3):
        for sgn in (-1.0, 1.0):
            if skip_bottom and ax == 2 and sgn < 0:
                continue
            o = [a for a in range(3) if a != ax]
            faces.append((ax, sgn, o, 4 * half[o[0]] * half[o[1]]))
    areas = np.array([f[3] for f in faces])
    counts = np.floor(n * areas / areas.sum()).astype(int)
    counts[np.argmax(areas)] += n - counts.sum()
    pts = []
    for (ax, sgn, o, _), m in zip(faces, counts):
        p = np.zeros((m, 3))
        p[:, ax] = sgn * half[ax]
        p[:, o[0]] = rng.uniform(-half[o[0]], half[o[0]], m)
        p[:, o[1]] = rng.uniform(-half[o[1]], half[o[1]], m)
        pts.append(p)
    return np.concatenate(pts) + np.asarray(centre)


def car_template(size: Sequence[float], n: int, rng: np.random.Generator) -> np.ndarray:
    """``[n, 3]`` points on a car shape filling a box of ``size`` (L, W, H), object frame.

    Body: full length and width, from 0.15 H above the ground to 0.6 H; cabin: 0.55 L long,
    centred 0.06 L behind the middle, 0.9 W wide, up to the roof. Symmetric in y.
    """
    L, W, H = (float(s) for s in size)
    n_body = int(round(n * 0.6))
    body_half = [L / 2, W / 2, 0.225 * H]
    body = _box_surface(n_body, [0, 0, -H / 2 + 0.15 * H + body_half[2]], body_half, rng)
    cab_half = [0.275 * L, 0.45 * W, 0.2 * H]
    cabin = _box_surface(n - n_body, [-0.06 * L, 0, H / 2 - cab_half[2]], cab_half, rng)
    return np.concatenate([body, cabin])


def box_surface_template(size: Sequence[float], n: int, rng: np.random.Generator) -> np.ndarray:
    """``[n, 3]`` points on the surface of the box of ``size``, object frame."""
    return _box_surface(n, [0, 0, 0], np.asarray(size, np.float64) / 2, rng, skip_bottom=False)


def sh_mirror_signs(num_coeffs: int, dtype=torch.float32) -> torch.Tensor:
    """``[K]`` signs of the y -> -y reflection in 3DGS real-SH order: -1 where m < 0."""
    signs = []
    l = 0
    while len(signs) < num_coeffs:
        signs.extend(-1.0 if m < 0 else 1.0 for m in range(-l, l + 1))
        l += 1
    if len(signs) != num_coeffs:
        raise ValueError(f"num_coeffs must be (d+1)^2, got {num_coeffs}")
    return torch.tensor(signs, dtype=dtype)


def mirror_means(means: torch.Tensor) -> torch.Tensor:
    """Reflect ``[N, 3]`` object-frame means across y = 0."""
    return means * means.new_tensor([1.0, -1.0, 1.0])


def mirror_quats(quats: torch.Tensor) -> torch.Tensor:
    """Reflect ``[N, 4]`` wxyz rotations: (w, x, y, z) -> (w, -x, y, -z)."""
    return quats * quats.new_tensor([1.0, -1.0, 1.0, -1.0])


def mirror_sh(sh: torch.Tensor) -> torch.Tensor:
    """Reflect object-frame SH ``[..., K, 3]``: coefficient of order m < 0 changes sign."""
    return sh * sh_mirror_signs(sh.shape[-2], sh.dtype)[:, None]


def _fourier(x: torch.Tensor, n: int) -> torch.Tensor:
    """``[..., D] -> [..., D (1 + 2n)]``: x, sin(2^k pi x), cos(2^k pi x)."""
    if n == 0:
        return x
    f = (2.0 ** torch.arange(n, dtype=x.dtype)) * math.pi
    xf = x[..., None] * f
    return torch.cat([x, xf.sin().flatten(-2), xf.cos().flatten(-2)], -1)


class ResidualSH(nn.Module):
    """Per-Gaussian, per-time SH residuals of one dynamic object.

    Args:
        num_coeffs: K = (d+1)^2 SH coefficients per colour channel.
        width: hidden width; two hidden layers with ReLU.
        time_frequencies, position_frequencies: Fourier bands of the embeddings.
    forward(positions [M,3] box-normalised (about -0.5..0.5), t scalar in [0, 1]) -> [M, K, 3].
    """

    def __init__(self, num_coeffs: int, width: int = 64, time_frequencies: int = 4,
                 position_frequencies: int = 2) -> None:
        super().__init__()
        self.num_coeffs = num_coeffs
        self.time_frequencies = time_frequencies
        self.position_frequencies = position_frequencies
        d_in = (1 + 2 * time_frequencies) + 3 * (1 + 2 * position_frequencies)
        self.mlp = nn.Sequential(nn.Linear(d_in, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(),
                                 nn.Linear(width, num_coeffs * 3))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, positions: torch.Tensor, t: float) -> torch.Tensor:
        te = _fourier(positions.new_full((1, 1), float(t)), self.time_frequencies).expand(positions.shape[0], -1)
        pe = _fourier(positions, self.position_frequencies)
        return self.mlp(torch.cat([te, pe], -1)).view(-1, self.num_coeffs, 3)


def object_points_and_colours(seq: DrivingSequence, track_id: int, frame_ids: Sequence[int],
                              cameras: Sequence[str], template: str, n_template: int,
                              rng: np.random.Generator):
    """Initial object-frame points ``[M, 3]`` and colours ``[M, 3]`` of one track.

    Template points plus the LiDAR points inside the box over ``frame_ids``; each point's colour is
    the mean over the (frame, camera) pairs where it projects inside the image onto this track's
    instance pixels (or anywhere, without instance masks); grey when never seen.
    """
    boxes = {i: b for i in frame_ids for b in seq.frames[i].boxes if b.track_id == track_id}
    if not boxes:
        raise ValueError(f"track {track_id} has no box in the training frames")
    first = boxes[min(boxes)]
    use_car = template == "car" and any(k in first.label.lower() for k in ("car", "vehicle", "truck", "van", "bus"))
    pts = car_template(first.size, n_template, rng) if use_car else box_surface_template(first.size, n_template, rng)
    lidar = []
    for i, b in boxes.items():
        f = seq.frames[i]
        if f.lidar is None:
            continue
        pw = f.lidar.to_world(f.ego_to_world).points.astype(np.float64)
        inside = b.contains(pw)
        if inside.any():
            T = invert_transform(b.box_to_world)
            lidar.append(pw[inside] @ T[:3, :3].T + T[:3, 3])
    if lidar:
        lp = np.concatenate(lidar)
        if len(lp) > n_template:
            lp = lp[rng.choice(len(lp), n_template, replace=False)]
        pts = np.concatenate([pts, lp])
    acc = np.zeros((len(pts), 3))
    cnt = np.zeros(len(pts))
    for i, b in boxes.items():
        f = seq.frames[i]
        pw = pts @ b.box_to_world[:3, :3].T + b.box_to_world[:3, 3]
        for c in cameras:
            vis, lin, _, _, _ = project_to_pixels(seq, i, c, pw, 0.1)
            inst = f.instances.get(c)
            if inst is not None:
                vis &= inst.reshape(-1)[lin] == track_id
            acc[vis] += f.images[c].reshape(-1, 3)[lin[vis]]
            cnt[vis] += 1
    colours = np.where(cnt[:, None] > 0, acc / np.maximum(cnt, 1)[:, None], 0.5)
    return pts.astype(np.float32), colours.astype(np.float32)


def track_box_pixels(seq: DrivingSequence, track_ids: Sequence[int], frame_ids: Sequence[int],
                     cameras: Sequence[str]) -> np.ndarray:
    """``[T, F, C]`` int64: how many pixels of camera ``cameras[c]`` at frame ``frame_ids[f]`` have a
    centre ray that hits track ``track_ids[t]``'s box (:func:`.background.box_hit_counts`: the pixels of
    :func:`.background.box_hit_masks`' masks, counted inside each box's projected rectangle, at the
    cameras' own resolution; 0 where the track has no box or its box is out of view). Boxes only,
    never instance masks: the count is what a user's tracked boxes say, also when the data carries
    masks; occlusion is not taken into account."""
    from .background import box_hit_counts
    row = {int(t): k for k, t in enumerate(track_ids)}
    out = np.zeros((len(track_ids), len(frame_ids), len(cameras)), np.int64)
    if not row:
        return out
    for j, i in enumerate(frame_ids):
        boxes = [b for b in seq.frames[i].boxes if b.track_id in row]
        if not boxes:
            continue
        poses = [(T, np.linalg.inv(T)) for T in (b.box_to_world for b in boxes)]  # once per frame, not per camera
        for c, name in enumerate(cameras):
            cam = seq.camera(name)
            for b, n in box_hit_counts(cam, seq.cam_to_world(i, name), boxes, cam.width, cam.height, poses):
                out[row[b.track_id], j, c] = n
    return out


@dataclass(frozen=True)
class ObjectBudget:
    """The foreground budget of one run (:func:`object_budget`).

    fg_steps: the foreground stage's iterations. object_points ``[T]``: each track's template points
    (and at most as many LiDAR points) at initialisation. object_caps ``[T]``: the Gaussians each
    track's set may grow to. visible_tracks: tracks whose box covers at least one pixel of a
    training view (None when nothing was counted: the budget fields are off). object_area: the box
    pixels of every track summed over the training views, in images (a sum of ``H * W``); None when
    nothing was counted. seconds: the time the count took.
    """

    fg_steps: int
    object_points: tuple[int, ...]
    object_caps: tuple[int, ...]
    visible_tracks: int | None = None
    object_area: float | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {"fg_steps": self.fg_steps, "object_points": list(self.object_points),
                "object_caps": list(self.object_caps), "visible_tracks": self.visible_tracks,
                "object_area": self.object_area, "seconds": self.seconds}


def budget_scales(preset) -> bool:
    """Whether ``preset`` scales the object budget with the scene (any budget field on)."""
    return bool(preset.fg_steps_per_track or preset.fg_steps_per_area or preset.object_points_per_pixel)


def object_budget(preset, pixels: np.ndarray, image_pixels: int) -> ObjectBudget:
    """The scaled foreground budget (the preset's budget fields on, :func:`budget_scales`; else
    :func:`fixed_object_budget`) from the tracks' box pixels ``pixels [T, F, C]`` over the training
    views (:func:`track_box_pixels`) and the pixels of one image ``image_pixels`` (``H * W``).

    With ``n`` the tracks visible in a training view and ``A`` their box pixels summed over
    the training views in images, the foreground stage gets
    ``fg_steps + ceil(fg_steps_per_track * n + fg_steps_per_area * A)`` iterations, at most
    ``fg_steps_max`` (a cap on the added part: never fewer than ``fg_steps``), and 0 when ``n == 0``
    (an empty street pays nothing). With ``object_points_per_pixel`` > 0, track
    ``t`` starts from ``clip(ceil(object_points_per_pixel * P_t), object_points_min, object_points)``
    template points, ``P_t`` the most pixels its box covers in one training view, and may grow to
    four times that (a pedestrian far away gets few Gaussians, a truck beside the ego the preset's
    full count); otherwise every track gets ``object_points`` as before.
    """
    p = preset
    T = pixels.shape[0]
    per_view = pixels.reshape(T, int(np.prod(pixels.shape[1:])))
    visible = int((per_view.max(1, initial=0) > 0).sum())
    area = float(per_view.sum()) / float(image_pixels)
    if visible == 0:
        fg = 0
    else:
        extra = math.ceil(p.fg_steps_per_track * visible + p.fg_steps_per_area * area - 1e-9)
        fg = max(p.fg_steps, min(p.fg_steps_max, p.fg_steps + max(extra, 0)))
    if p.object_points_per_pixel > 0:
        most = per_view.max(1, initial=0)
        pts = [int(min(p.object_points, max(p.object_points_min, math.ceil(p.object_points_per_pixel * m))))
               for m in most]
    else:
        pts = [p.object_points] * T
    return ObjectBudget(fg, tuple(pts), tuple(4 * n for n in pts), visible, area)


def fixed_object_budget(preset, n_tracks: int) -> ObjectBudget:
    """The budget before issue 36 (the budget fields off): ``fg_steps`` iterations when there is a
    track, every track ``object_points`` points and ``4 * object_points`` Gaussians."""
    p = preset
    return ObjectBudget(p.fg_steps if n_tracks else 0, (p.object_points,) * n_tracks,
                        (4 * p.object_points,) * n_tracks)
