"""Fusion: per-object, per-frame pose corrections and placing object sets in the world.

A track's pose at frame f is ``T_track(f) @ exp(delta[f])``: the correction ``delta`` (axis-angle
[3], translation [3], object frame) starts at zero and is learnt during fusion (and in the
foreground stage with the preset's ``fg_pose_correction``), since tracked boxes are noisy; with
``pose_translation_only`` its rotation is held at 0. Frames that were never trained (held-out
frames) take the correction interpolated linearly between the nearest trained frames.
"""
from __future__ import annotations

import torch
from torch import nn

from ..common.gaussians import GaussianSet, rotate_sh
from ..common.geometry import quat_multiply, quat_to_matrix

__all__ = ["axis_angle_to_quat", "PoseCorrection", "place"]


def axis_angle_to_quat(aa: torch.Tensor) -> torch.Tensor:
    """``[..., 3]`` axis-angle -> ``[..., 4]`` unit wxyz quaternion (smooth at zero)."""
    theta2 = (aa * aa).sum(-1, keepdim=True)
    theta = torch.sqrt(theta2 + 1e-24)
    half = 0.5 * theta
    small = theta2 < 1e-8
    k = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(half) / theta)
    return torch.cat([torch.cos(half), aa * k], -1)


class PoseCorrection(nn.Module):
    """Learnable corrections ``delta [T, F, 6]`` (axis-angle, translation) for T tracks and F frames.

    Args:
        num_tracks, num_frames: table size.
        trained: ``[F]`` bool, frames whose corrections are trained (others are interpolated).
        translation_only: hold the rotation part at 0 (the preset's ``pose_translation_only``).
    """

    def __init__(self, num_tracks: int, num_frames: int, trained: torch.Tensor,
                 translation_only: bool = False) -> None:
        super().__init__()
        self.delta = nn.Parameter(torch.zeros(num_tracks, num_frames, 6))
        self.register_buffer("trained", trained.to(torch.bool).clone())
        #: True: the rotation part is held at 0 (it gets no gradient), only the translation is learnt
        self.translation_only = bool(translation_only)

    def forward(self, track: int, frame: int) -> torch.Tensor:
        """``[6]`` correction of ``track`` at ``frame`` (interpolated for untrained frames)."""
        d = self._delta(track, frame)
        if self.translation_only:
            return torch.cat([torch.zeros_like(d[:3]), d[3:]])
        return d

    def _delta(self, track: int, frame: int) -> torch.Tensor:
        if bool(self.trained[frame]):
            return self.delta[track, frame]
        idx = torch.nonzero(self.trained).flatten()
        if idx.numel() == 0:
            return self.delta[track, frame].detach() * 0
        before, after = idx[idx < frame], idx[idx > frame]
        if before.numel() == 0:
            return self.delta[track, int(after[0])]
        if after.numel() == 0:
            return self.delta[track, int(before[-1])]
        a, b = int(before[-1]), int(after[0])
        w = (frame - a) / (b - a)
        return (1 - w) * self.delta[track, a] + w * self.delta[track, b]


def place(gs: GaussianSet, R: torch.Tensor, t: torch.Tensor, q: torch.Tensor,
          delta: torch.Tensor | None = None) -> GaussianSet:
    """Move an object-frame set to the world: ``T(R, t) @ exp(delta)``.

    Args:
        gs: object-frame Gaussians (SH in the object frame).
        R [3,3], t [3], q [4]: the track pose (q = wxyz of R).
        delta: optional ``[6]`` correction (axis-angle, translation), differentiable.
    """
    means, quats = gs.means, gs.quats
    if delta is not None:
        qd = axis_angle_to_quat(delta[:3])
        Rd = quat_to_matrix(qd)
        means = means @ Rd.T + delta[3:]
        quats = quat_multiply(qd.expand_as(quats), quats)
        R_all = R @ Rd
    else:
        R_all = R
    means = means @ R.T + t
    quats = quat_multiply(q.expand_as(quats), quats)
    sh = rotate_sh(gs.sh, R_all) if gs.sh.shape[1] > 1 else gs.sh
    return GaussianSet(means=means, quats=quats, scales=gs.scales, opacities=gs.opacities, sh=sh)
