"""The Gaussian network (GPS-Gaussian design): one 3D Gaussian per input pixel.

Inputs per camera: the image, the metric depth map and the depth network's features (1/2, 1/4
and the fused 1/8). A residual U-Net encoder (``clsplat.models.common.backbones``; 32, 48, 96
channels at 1/2, 1/4, 1/8, GroupNorm) encodes the depth map (as normalised inverse depth in [0, 1]);
the fusion decoder merges depth and image features level by level with residual blocks (96, 64,
48 channels), upsamples to full resolution and maps [48 + image 3 + depth 1] to 32 channels. Four
heads (3x3 conv 32 -> 32, ReLU, 1x1 conv) give:

* rotation: 4 channels, L2-normalised (wxyz, camera frame);
* scale: 3 channels, Softplus(beta=100), capped at ``preset.scale_cap`` metres;
* opacity: sigmoid;
* SH: 3 (L+1)^2 channels; degree l >= 1 multiplied by 0.1 * 0.25^l. The DC term is a residual on
  the pixel's own colour (``rgb_to_sh(image)`` added), so an untrained head already paints the
  pixel; the network learns the correction.

:func:`pixels_to_gaussians` lifts every pixel centre with its depth (``E K^-1 [u+0.5, v+0.5, 1] D``)
and rotates quaternions and SH from the camera into the ego frame (``rotate_sh``).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
import torch.nn.functional as F

from ..common.backbones import ResidualBlock, ResidualUNetEncoder
from ..common.gaussians import GaussianSet, rgb_to_sh, rotate_sh
from ..common.geometry import matrix_to_quat, quat_multiply, unproject

__all__ = ["GaussianHead", "GaussianNetwork", "pixels_to_gaussians", "depth_code"]


def depth_code(depth: Tensor, min_depth: float, max_depth: float) -> Tensor:
    """Normalised inverse depth in [0, 1] (1 at ``min_depth``), the depth encoder's input."""
    inv = 1.0 / depth.clamp(min_depth, max_depth * 10)
    return ((inv - 1.0 / (max_depth * 10)) / (1.0 / min_depth - 1.0 / (max_depth * 10))).clamp(0, 1)


class GaussianHead(nn.Module):
    """3x3 conv (32 -> 32), ReLU, 1x1 conv (32 -> out): ``[V, 32, H, W] -> [V, out, H, W]``."""

    def __init__(self, channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, 1, 1)
        self.relu = nn.ReLU(inplace=True)
        self.out = nn.Conv2d(channels, out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.out(self.relu(self.conv(x)))


class GaussianNetwork(nn.Module):
    """Depth encoder + fusion decoder + rotation/scale/opacity/SH heads.

    Args:
        preset: a :class:`~.presets.DFPreset` (encoder/decoder widths, SH degree and damping,
            scale cap); image features are 64 (1/2), 64 (1/4) and ``proj_channels[1]`` (1/8).
    """

    def __init__(self, preset, image_channels: tuple[int, int, int] | None = None) -> None:
        super().__init__()
        self.preset = preset
        e = preset.gs_encoder_channels
        d = preset.gs_decoder_channels
        img = image_channels or (64, 64, preset.proj_channels[1])
        hc = preset.gs_head_channels
        self.depth_encoder = ResidualUNetEncoder(1, channels=tuple(e), norm="group")
        self.decoder8 = ResidualBlock(img[2] + e[2], d[0], norm="group")
        self.decoder4 = ResidualBlock(d[0] + img[1] + e[1], d[1], norm="group")
        self.decoder2 = ResidualBlock(d[1] + img[0] + e[0], d[2], norm="group")
        self.decoder1 = nn.Sequential(nn.Conv2d(d[2] + 3 + 1, hc, 3, 1, 1), nn.ReLU(inplace=True))
        self.num_sh = (preset.sh_degree + 1) ** 2
        self.rot_head = GaussianHead(hc, 4)
        self.scale_head = GaussianHead(hc, 3)
        self.opacity_head = GaussianHead(hc, 1)
        self.sh_head = GaussianHead(hc, 3 * self.num_sh)
        damp = torch.ones(self.num_sh)
        for l in range(1, preset.sh_degree + 1):
            damp[l * l:(l + 1) * (l + 1)] = preset.sh_damping * preset.sh_damping_decay ** l
        self.register_buffer("sh_damp", damp, persistent=False)

    def forward(self, image: Tensor, depth: Tensor, f2: Tensor, f4: Tensor, f8: Tensor) -> dict[str, Tensor]:
        """Per-pixel Gaussian parameters in the camera frame.

        Args:
            image: ``[V, 3, H, W]`` in [0, 1] (the network input, possibly colour-jittered);
            depth: ``[V, 1, H, W]`` metres; f2, f4, f8: image features at 1/2, 1/4, 1/8.
        Returns:
            ``quats [V, H, W, 4]`` unit, ``scales [V, H, W, 3]`` in (0, cap], ``opacities [V, H, W]``
            in (0, 1), ``sh [V, H, W, K, 3]`` (DC without the pixel colour; see the module docstring).
        """
        p = self.preset
        code = depth_code(depth, p.min_depth, p.max_depth)
        d2, d4, d8 = self.depth_encoder(code)
        x = self.decoder8(torch.cat([f8, d8], 1))
        x = F.interpolate(x, size=f4.shape[-2:], mode="bilinear", align_corners=False)
        x = self.decoder4(torch.cat([x, f4, d4], 1))
        x = F.interpolate(x, size=f2.shape[-2:], mode="bilinear", align_corners=False)
        x = self.decoder2(torch.cat([x, f2, d2], 1))
        x = F.interpolate(x, size=image.shape[-2:], mode="bilinear", align_corners=False)
        x = self.decoder1(torch.cat([x, image, code], 1))
        V, _, H, W = x.shape
        quats = F.normalize(self.rot_head(x), dim=1).permute(0, 2, 3, 1)
        scales = F.softplus(self.scale_head(x), beta=p.scale_beta).clamp_max(p.scale_cap).permute(0, 2, 3, 1)
        opac = torch.sigmoid(self.opacity_head(x))[:, 0]
        sh = self.sh_head(x).reshape(V, self.num_sh, 3, H, W).permute(0, 3, 4, 1, 2) * self.sh_damp.view(-1, 1)
        return {"quats": quats, "scales": scales, "opacities": opac, "sh": sh}


def pixels_to_gaussians(params: dict[str, Tensor], colours: Tensor, depth: Tensor, Ks: Tensor,
                        cam_to_ego: Tensor) -> GaussianSet:
    """One Gaussian per pixel, in the ego frame.

    Args:
        params: :meth:`GaussianNetwork.forward` output for V cameras of size H x W.
        colours: ``[V, 3, H, W]`` pixel colours whose SH DC the SH head's DC refines.
        depth: ``[V, 1, H, W]``; Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``.
    Returns:
        a :class:`GaussianSet` of ``V*H*W`` Gaussians (camera-major, then row-major pixels).
    """
    V, _, H, W = depth.shape
    means = unproject(depth[:, 0], Ks, cam_to_ego).reshape(-1, 3)
    R = cam_to_ego[:, :3, :3]
    qR = matrix_to_quat(R)                                                      # [V, 4]
    quats = quat_multiply(qR[:, None, None, :].expand(V, H, W, 4), params["quats"]).reshape(-1, 4)
    dc = rgb_to_sh(colours.permute(0, 2, 3, 1).reshape(-1, 3)).reshape(V, H, W, 1, 3)
    sh = torch.cat([params["sh"][..., :1, :] + dc, params["sh"][..., 1:, :]], -2)
    K = sh.shape[-2]
    # one rotation per camera: its Wigner matrices are built once, not once per pixel
    sh = torch.cat([rotate_sh(sh[v].reshape(-1, K, 3), R[v]) for v in range(V)]) if K > 1 else sh.reshape(-1, K, 3)
    return GaussianSet(means=means, quats=quats, scales=params["scales"].reshape(-1, 3),
                       opacities=params["opacities"].reshape(-1), sh=sh)
