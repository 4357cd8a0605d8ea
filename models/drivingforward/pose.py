"""The pose network: ego motion between two instants from the surround cameras.

Each camera's two images (earlier, later) are stacked on channels into a 6-channel ResNet-18;
levels 2-4 are reduced to 256 channels at 1/8, fused over the cameras in the voxel grid in pose
mode (averaged where several cameras see a voxel) into a bird's-eye map, and decoded by
convolutions (1x1 to 256, two stride-2 3x3, 1x1 to 6, spatial mean; the release's decoder, which
the paper's text calls a two-layer MLP). The six outputs are multiplied by 0.01 and read as an
axis-angle rotation and a translation clamped to +-4 m: the motion ``T_0`` of the *reference*
camera (the first camera given, CAM_FRONT on a full rig) from the earlier to the later instant,
i.e. ``p_later = T_0 p_earlier`` in that camera's frame. :func:`carry_pose` gives every other
camera's motion through the rig extrinsics, ``T_c = E_c^-1 E_0 T_0 E_0^-1 E_c`` (E = cam_to_ego),
and :func:`ego_motion` the ego frame's, ``M = E_0 T_0 E_0^-1``.

Issue 32 departures, each a preset field, off unless set:

* ``pose_corr_radius`` > 0: a motion cue the network does not have to learn to see.
  :func:`local_correlation` compares every pixel's 3x3 patch of the earlier image (zero-mean,
  unit-norm, i.e. normalised cross-correlation) with the later image's patches displaced by up to
  ``r`` pixels, at 1/``pose_corr_level`` resolution: ``(2r+1)^2`` scores per pixel, plus their
  soft-argmax (a flow estimate, 2 channels). ``pose_corr_mode`` "bev": the cue, pooled to 1/8 and
  taken to the fused width by a 1x1 conv, is added to the 1/8 feature before the bird's-eye fusion;
  "camera": :class:`CameraOdometryHead` reads each camera's cue with shared weights as that
  camera's own translation (a side camera sees forward motion as its own lateral motion, so one
  head serves every camera), rotated into camera 0's frame and averaged over the cameras, and added
  to the decoder's translation; "camera_only": that average is the translation, and the decoder
  gives the rotation alone. ``pose_corr_head`` "conv": that head is two convs on the whole cue;
  "flow": a linear map of six statistics of the soft-argmax flow (:func:`flow_statistics`).
* ``pose_translation_scale``: the translation outputs' own multiplier (the rotation keeps
  ``pose_scale``). With Adam, a parameter moves about ``lr`` per step whatever its gradient's size,
  so the output moves about ``lr x scale`` per unit of input: at the paper's 0.01 and 1e-4, the
  decoder's bias moves the translation 1e-6 m per step.
* ``pose_sign_test``: the translation output is multiplied by a sign buffer (+1 at the start,
  saved in the checkpoint) that :meth:`PoseNetwork.sign_test_decide` flips when the pose's own
  objective, summed over a window of steps, was lower with the translations negated
  (:func:`negate_translation`; the model computes the difference). With the sign outside the
  parameters, Adam's update (odd in its first moment, even in its second) runs the mirrored
  trajectory of negating the weights and the first moments, so nothing in the optimiser changes.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..common.backbones import ResNet18
from ..common.geometry import se3_exp
from .depth import MultiLevelReduce, he_init, normalise_image
from .fusion import VolumetricFusion, scale_intrinsics

import torch.nn.functional as F

__all__ = ["PoseDecoder", "PoseNetwork", "CameraOdometryHead", "FlowStatsHead", "flow_statistics", "carry_pose", "ego_motion",
           "local_correlation", "negate_translation"]


def ego_motion(T0: Tensor, E0: Tensor) -> Tensor:
    """Ego-frame motion ``[4, 4]`` from the reference camera's motion ``T0 [4, 4]`` and its
    cam_to_ego ``E0 [4, 4]``: ``M = E0 T0 E0^-1`` (maps ego coordinates at the earlier instant to
    ego coordinates at the later one)."""
    return E0 @ T0 @ torch.linalg.inv(E0)


def negate_translation(T: Tensor) -> Tensor:
    """``[..., 4, 4]`` rigid transforms with the same rotation and the translation negated: what
    the pose network outputs with its translation sign flipped (the output is ``se3_exp(rot, t)``
    with t taken as the matrix's translation, clamped symmetrically)."""
    out = T.clone()
    out[..., :3, 3] = -T[..., :3, 3]
    return out


def carry_pose(T0: Tensor, cam_to_ego: Tensor) -> Tensor:
    """Every camera's motion from the reference camera's.

    Args:
        T0: ``[4, 4]`` motion of camera 0 (``p_later = T0 p_earlier`` in its frame).
        cam_to_ego: ``[V, 4, 4]``, camera 0 first.
    Returns:
        ``[V, 4, 4]`` ``T_c = E_c^-1 E_0 T_0 E_0^-1 E_c``.
    """
    M = ego_motion(T0, cam_to_ego[0])
    return torch.linalg.inv(cam_to_ego) @ M @ cam_to_ego


def _unit_patches(x: Tensor) -> Tensor:
    """``[V, C, h, w] -> [V, 9C, h, w]``: each pixel's 3x3 patch (replicate padding), zero-mean, unit norm."""
    V, C, h, w = x.shape
    p = F.unfold(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3).reshape(V, C * 9, h, w)
    p = p - p.mean(dim=1, keepdim=True)
    return p / p.norm(dim=1, keepdim=True).clamp_min(1e-3)


def local_correlation(earlier: Tensor, later: Tensor, radius: int, level: int, temperature: float = 0.1) -> Tensor:
    """Normalised cross-correlation of the two instants' images over a window of displacements.

    Args:
        earlier, later: ``[V, 3, H, W]`` images of the same cameras; radius: the largest
            displacement (pixels at the cue's resolution); level: the images are averaged over
            ``level x level`` blocks first (H and W divisible by it).
        temperature: of the soft-argmax over the scores.
    Returns:
        ``[V, (2r+1)^2 + 2, H/level, W/level]``: the scores of displacements (dy, dx) in row-major
        order from (-r, -r), in [-1, 1] (the earlier pixel's patch against the later image's patch
        at the displaced position; outside the image: 0), then the soft-argmax displacement
        (dx, dy) in pixels of that resolution.
    """
    a = F.avg_pool2d(earlier, level) if level > 1 else earlier
    b = F.avg_pool2d(later, level) if level > 1 else later
    pa, pb = _unit_patches(a), _unit_patches(b)
    h, w = a.shape[-2:]
    r = radius
    pb = F.pad(pb, (r, r, r, r))
    scores = [(pa * pb[..., r + dy:r + dy + h, r + dx:r + dx + w]).sum(1)
              for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    corr = torch.stack(scores, 1)
    d = torch.arange(-r, r + 1, dtype=corr.dtype, device=corr.device)
    dy, dx = torch.meshgrid(d, d, indexing="ij")
    wts = torch.softmax(corr / temperature, dim=1)
    flow = torch.stack([(wts * dx.reshape(1, -1, 1, 1)).sum(1), (wts * dy.reshape(1, -1, 1, 1)).sum(1)], 1)
    return torch.cat([corr, flow], 1)


class CameraOdometryHead(nn.Module):
    """Each camera's correlation cue -> that camera's translation (its own frame), one set of
    weights for every camera: ``[V, D, h, w] -> [V, 3]`` (two stride-2 3x3 convs, spatial mean,
    linear; the linear layer starts at zero, so the head adds no motion until trained)."""

    def __init__(self, in_channels: int, channels: int = 64) -> None:
        super().__init__()
        self.conv_0 = nn.Conv2d(in_channels, channels, 3, 2, 1)
        self.conv_1 = nn.Conv2d(channels, channels, 3, 2, 1)
        self.out = nn.Linear(channels, 3)
        self.relu = nn.ReLU(inplace=True)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, cue: Tensor) -> Tensor:
        x = self.relu(self.conv_0(cue))
        x = self.relu(self.conv_1(x))
        return self.out(x.mean(dim=(2, 3)))


def flow_statistics(flow: Tensor, Ks: Tensor) -> Tensor:
    """Six numbers per camera from a flow field: the mean flow (dx, dy) and the mean expansion
    ``x dx + y dy`` (x, y: the pixel's normalised image coordinates, (u - cx)/fx, (v - cy)/fy),
    over the lower and the upper half of the image.

    Args:
        flow: ``[V, 2, h, w]`` displacements in pixels at that resolution; Ks ``[V, 3, 3]`` at it.
    Returns:
        ``[V, 6]``: lower half (dx, dy, expansion), upper half (dx, dy, expansion).
    """
    V, _, h, w = flow.shape
    u = torch.arange(w, dtype=flow.dtype, device=flow.device) + 0.5
    v = torch.arange(h, dtype=flow.dtype, device=flow.device) + 0.5
    x = (u.reshape(1, 1, w) - Ks[:, 0, 2].reshape(V, 1, 1)) / Ks[:, 0, 0].reshape(V, 1, 1)
    y = (v.reshape(1, h, 1) - Ks[:, 1, 2].reshape(V, 1, 1)) / Ks[:, 1, 1].reshape(V, 1, 1)
    expansion = x * flow[:, 0] + y * flow[:, 1]
    f = torch.stack([flow[:, 0], flow[:, 1], expansion], 1)          # [V, 3, h, w]
    return torch.cat([f[:, :, h // 2:].mean(dim=(2, 3)), f[:, :, :h // 2].mean(dim=(2, 3))], 1)


class FlowStatsHead(nn.Module):
    """Each camera's :func:`flow_statistics` -> its own translation by one linear map shared by
    every camera, ``[V, 6] -> [V, 3]``, starting at zero (18 weights and 3 biases: few enough for
    the photometric terms to set in a few hundred steps)."""

    def __init__(self) -> None:
        super().__init__()
        self.out = nn.Linear(6, 3)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, cue: Tensor, Ks: Tensor) -> Tensor:
        return self.out(flow_statistics(cue[:, -2:], Ks))


class PoseDecoder(nn.Module):
    """Conv pose decoder: ``[1, C, X, Y] -> [6]`` (1x1 -> 256, two stride-2 3x3, 1x1 -> 6, mean)."""

    def __init__(self, in_channels: int = 128, channels: int = 256) -> None:
        super().__init__()
        self.squeeze = nn.Conv2d(in_channels, channels, 1)
        self.pose_0 = nn.Conv2d(channels, channels, 3, 2, 1)
        self.pose_1 = nn.Conv2d(channels, channels, 3, 2, 1)
        self.pose_2 = nn.Conv2d(channels, 6, 1)
        self.relu = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        x = self.relu(self.squeeze(x))
        x = self.relu(self.pose_0(x))
        x = self.relu(self.pose_1(x))
        return self.pose_2(x).mean(dim=(2, 3)).reshape(6)


class PoseNetwork(nn.Module):
    """Two-image ResNet-18 + pose-mode fusion + conv decoder.

    Args:
        preset: a :class:`~.presets.DFPreset`.
    """

    def __init__(self, preset) -> None:
        super().__init__()
        self.preset = preset
        self.encoder = ResNet18(in_channels=6)
        self.reduce = MultiLevelReduce((128, 256, 512), preset.fusion_channels)
        self.fusion = VolumetricFusion(preset.fusion_channels, "pose", preset.voxel_origin, preset.voxel_size,
                                       preset.voxel_shape, out_channels=preset.pose_bev_channels)
        self.decoder = PoseDecoder(preset.pose_bev_channels[1], preset.pose_decoder_channels)
        self.corr_proj = self.odometry = None
        if preset.pose_corr_radius > 0:
            cue = (2 * preset.pose_corr_radius + 1) ** 2 + 2
            if preset.pose_corr_mode == "bev":
                self.corr_proj = nn.Conv2d(cue, preset.fusion_channels, 1)
            elif preset.pose_corr_head == "flow":
                self.odometry = FlowStatsHead()
            else:
                self.odometry = CameraOdometryHead(cue)
        he_init(self.reduce, self.fusion, self.decoder, *(m for m in (self.corr_proj,) if m is not None),
                skip=(self.decoder.pose_2,))   # see depth.he_init
        if isinstance(self.odometry, CameraOdometryHead):
            he_init(self.odometry, skip=(self.odometry.out,))
        if preset.pose_zero_init:     # no motion, exactly, until the photometric terms say otherwise
            nn.init.zeros_(self.decoder.pose_2.weight)
            nn.init.zeros_(self.decoder.pose_2.bias)
        if preset.pose_translation_init is not None:
            # the decoder's output is a spatial mean of a 1x1 conv, so its bias is the output's
            # offset: start at the given translation (bench/RESULTS.md, issue 17)
            with torch.no_grad():
                t = torch.tensor(preset.pose_translation_init, dtype=self.decoder.pose_2.bias.dtype)
                self.decoder.pose_2.bias[3:] = t / self.translation_scale
        if preset.pose_sign_test is not None:
            # the translation's sign, and the sign test's running sum and last decided step
            self.register_buffer("translation_sign", torch.ones((), dtype=torch.float64))
            self.register_buffer("sign_test_sum", torch.zeros((), dtype=torch.float64))
            self.register_buffer("sign_test_last", torch.zeros((), dtype=torch.int64))

    def sign_test_accumulate(self, delta: float) -> None:
        """Add one sample's ``L(t) - L(-t)`` (the pose objective with the translations as predicted
        minus with them negated; > 0: the negated branch is lower) to the window's sum."""
        self.sign_test_sum += float(delta)

    @torch.no_grad()
    def sign_test_decide(self, step: int) -> bool:
        """At the first call of a step ``0 < step <= pose_sign_test`` that ends a window of
        ``pose_sign_test_window`` steps: flip the translation's sign if the window's summed
        difference is above 0 (the negated branch had the lower loss), and start a new window.
        Returns whether it flipped. With several processes (torchrun) the windows' sums are added
        over the processes first, so every process makes the same decision on all the samples."""
        p = self.preset
        w = p.pose_sign_test_window
        if step <= 0 or step > p.pose_sign_test or step % w or int(self.sign_test_last) == step:
            return False
        self.sign_test_last.fill_(step)
        if torch.distributed.is_available() and torch.distributed.is_initialized() \
                and torch.distributed.get_world_size() > 1:
            torch.distributed.all_reduce(self.sign_test_sum)   # one decision, the same everywhere
        flip = bool(self.sign_test_sum > 0)
        if flip:
            self.translation_sign.neg_()
        self.sign_test_sum.zero_()
        return flip

    @property
    def translation_scale(self) -> float:
        """The translation outputs' multiplier: ``pose_translation_scale``, else ``pose_scale``."""
        p = self.preset
        return p.pose_scale if p.pose_translation_scale is None else p.pose_translation_scale

    def forward(self, earlier: Tensor, later: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> Tensor:
        """Motion of camera 0 between two instants.

        Args:
            earlier, later: ``[V, 3, H, W]`` images in [0, 1]; Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``.
        Returns:
            ``T0 [4, 4]`` with ``p_later = T0 p_earlier`` in camera 0's frame.
        """
        p = self.preset
        x = normalise_image(torch.cat([earlier, later], 1))
        f = self.encoder.forward_features(x)
        feat8 = self.reduce(f[2:5])
        cue = None
        if p.pose_corr_radius > 0:
            cue = local_correlation(earlier, later, p.pose_corr_radius, p.pose_corr_level)
        if self.corr_proj is not None:
            feat8 = feat8 + self.corr_proj(F.adaptive_avg_pool2d(cue, feat8.shape[-2:]))
        bev = self.fusion(feat8, scale_intrinsics(Ks, 1.0 / 8), cam_to_ego)
        raw = self.decoder(bev)
        rot = raw[:3] * p.pose_scale
        t = raw[3:] if p.pose_corr_mode != "camera_only" else torch.zeros_like(raw[3:])
        if self.odometry is not None:
            # each camera's own translation, into camera 0's frame: t_0 = R_0^T R_c t_c
            R = cam_to_ego[:, :3, :3].to(cue.dtype)
            if isinstance(self.odometry, FlowStatsHead):
                t_c = self.odometry(cue, scale_intrinsics(Ks, 1.0 / p.pose_corr_level).to(cue.dtype))
            else:
                t_c = self.odometry(cue)
            t = t + (R[0].T @ (R @ t_c.unsqueeze(-1)).squeeze(-1).T).T.mean(0)
        t = t * self.translation_scale
        if p.pose_sign_test is not None:
            t = t * float(self.translation_sign)
        m = p.max_translation
        return se3_exp(rot, t.clamp(-m, m))
