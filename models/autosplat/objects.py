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
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import nn

from clsplat.data.scene import DrivingSequence, invert_transform

from .init import project_to_pixels

__all__ = ["car_template", "box_surface_template", "sh_mirror_signs", "mirror_means", "mirror_quats",
           "mirror_sh", "ResidualSH", "object_points_and_colours"]


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
