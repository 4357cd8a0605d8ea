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
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from ..common.backbones import ResNet18
from ..common.geometry import se3_exp
from .depth import MultiLevelReduce, he_init, normalise_image
from .fusion import VolumetricFusion, scale_intrinsics

__all__ = ["PoseDecoder", "PoseNetwork", "carry_pose", "ego_motion"]


def ego_motion(T0: Tensor, E0: Tensor) -> Tensor:
    """Ego-frame motion ``[4, 4]`` from the reference camera's motion ``T0 [4, 4]`` and its
    cam_to_ego ``E0 [4, 4]``: ``M = E0 T0 E0^-1`` (maps ego coordinates at the earlier instant to
    ego coordinates at the later one)."""
    return E0 @ T0 @ torch.linalg.inv(E0)


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
        he_init(self.reduce, self.fusion, self.decoder, skip=(self.decoder.pose_2,))   # see depth.he_init
        if preset.pose_zero_init:     # no motion, exactly, until the photometric terms say otherwise
            nn.init.zeros_(self.decoder.pose_2.weight)
            nn.init.zeros_(self.decoder.pose_2.bias)
        if preset.pose_translation_init is not None:
            # the decoder's output is a spatial mean of a 1x1 conv, so its bias is the output's
            # offset: start at the given translation (bench/RESULTS.md, issue 17)
            with torch.no_grad():
                t = torch.tensor(preset.pose_translation_init, dtype=self.decoder.pose_2.bias.dtype)
                self.decoder.pose_2.bias[3:] = t / preset.pose_scale

    def forward(self, earlier: Tensor, later: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> Tensor:
        """Motion of camera 0 between two instants.

        Args:
            earlier, later: ``[V, 3, H, W]`` images in [0, 1]; Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``.
        Returns:
            ``T0 [4, 4]`` with ``p_later = T0 p_earlier`` in camera 0's frame.
        """
        x = normalise_image(torch.cat([earlier, later], 1))
        f = self.encoder.forward_features(x)
        feat8 = self.reduce(f[2:5])
        bev = self.fusion(feat8, scale_intrinsics(Ks, 1.0 / 8), cam_to_ego)
        out = self.decoder(bev) * self.preset.pose_scale
        m = self.preset.max_translation
        return se3_exp(out[:3], out[3:].clamp(-m, m))
