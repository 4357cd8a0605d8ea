"""Decoder and per-pixel heads: from matched 1/8 features to one Gaussian's parameters per pixel.

* :class:`Decoder`: residual blocks merging the matched 1/8 features (plus u0) with the encoder's
  1/4 and 1/2 skips, ``decoder_channels`` wide, up to full resolution; then
  [last + image 3 + upsampled u0 1] -> 3x3 conv -> ``head_channels`` (GPS-Gaussian's layout).
* :class:`DepthResidualHead`: GPS-Gaussian+'s refinement u = u0 + 0.5·tanh(r), in normalised
  inverse depth (so 0.5 is half the scene's depth range), clamped to [0, 1]; its last conv starts
  at zero, so an untrained head returns u0.
* :class:`GaussianHeads`: the parameter heads (rotation, scale, opacity, colour), each
  3x3 conv -> ReLU -> 1x1 conv. Raw outputs only; :func:`activate` turns them into metric
  Gaussian parameters in the camera frame. EcoSplat's stage 2 copies this module.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clsplat.models.common.backbones import ResidualBlock

__all__ = ["Decoder", "DepthResidualHead", "GaussianHeads", "RawGaussians", "activate"]


def _head(in_ch: int, out_ch: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(in_ch, in_ch, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(in_ch, out_ch, 1))


class Decoder(nn.Module):
    """U-Net decoder: 1/8 -> 1/4 -> 1/2 -> full resolution.

    forward(matched [V, C8, h, w], u0 [V, h, w], skips (f2 [V, c0, H/2, W/2], f4 [V, c1, H/4, W/4]),
    images [V, 3, H, W], u0_full [V, H, W]) -> [V, head_channels, H, W].
    """

    def __init__(self, enc_channels: tuple[int, int, int], dec_channels: tuple[int, int, int],
                 head_channels: int, norm: str = "group") -> None:
        super().__init__()
        c0, c1, c2 = enc_channels
        d8, d4, d2 = dec_channels
        self.up8 = ResidualBlock(c2 + 1, d8, 1, norm)
        self.up4 = ResidualBlock(d8 + c1, d4, 1, norm)
        self.up2 = ResidualBlock(d4 + c0, d2, 1, norm)
        self.out = nn.Sequential(nn.Conv2d(d2 + 4, head_channels, 3, padding=1), nn.ReLU(inplace=True))
        #: each stage's input channels (in :attr:`STAGES` order)
        self.in_channels = (c2 + 1, d8 + c1, d4 + c0, d2 + 4)

    @staticmethod
    def _up(x: Tensor, like: Tensor) -> Tensor:
        return F.interpolate(x, size=like.shape[-2:], mode="bilinear", align_corners=False)

    #: the stages in order (1/8, 1/4, 1/2, full resolution); the budget stage may copy the last few
    STAGES = ("up8", "up4", "up2", "out")

    def stage_input(self, i: int, prev: Tensor | None, matched: Tensor, u0: Tensor, f2: Tensor, f4: Tensor,
                    images: Tensor, u0_full: Tensor) -> Tensor:
        """The input of stage ``i`` (see :attr:`STAGES`): the previous stage's output ``prev``
        (None for stage 0) upsampled to the stage's resolution and joined with its skip."""
        if i == 0:
            return torch.cat([matched, u0[:, None]], 1)
        if i == 1:
            return torch.cat([self._up(prev, f4), f4], 1)
        if i == 2:
            return torch.cat([self._up(prev, f2), f2], 1)
        return torch.cat([self._up(prev, images), images, u0_full[:, None]], 1)

    def levels(self, matched: Tensor, u0: Tensor, f2: Tensor, f4: Tensor, images: Tensor, u0_full: Tensor
               ) -> list[Tensor]:
        """Every stage's output, [1/8, 1/4, 1/2, full] (the last is :meth:`forward`'s)."""
        outs: list[Tensor] = []
        x = None
        for i, name in enumerate(self.STAGES):
            x = getattr(self, name)(self.stage_input(i, x, matched, u0, f2, f4, images, u0_full))
            outs.append(x)
        return outs

    def forward(self, matched: Tensor, u0: Tensor, f2: Tensor, f4: Tensor, images: Tensor, u0_full: Tensor) -> Tensor:
        return self.levels(matched, u0, f2, f4, images, u0_full)[-1]


class DepthResidualHead(nn.Module):
    """u = clamp(u0 + 0.5·tanh(r), 0, 1); r from [features, u0] (last conv zero-initialised).

    forward(feat [V, C, H, W], u0 [V, H, W]) -> u [V, H, W].
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.net = _head(channels + 1, 1)
        nn.init.zeros_(self.net[2].weight)
        nn.init.zeros_(self.net[2].bias)

    def forward(self, feat: Tensor, u0: Tensor) -> Tensor:
        r = self.net(torch.cat([feat, u0[:, None]], 1))[:, 0]
        return (u0 + 0.5 * torch.tanh(r)).clamp(0.0, 1.0)


@dataclass
class RawGaussians:
    """Raw head outputs per pixel: rotation [V, 4, H, W], scale [V, 3, H, W], opacity [V, 1, H, W],
    colour [V, 3K, H, W] or None (colour taken from the source pixel); importance [V, 1, H, W]
    logits of the budget stage's selection score when it has its own head (else None); fill
    [V, 3, H, W] the budget stage's per-axis log-multipliers of the fill widening (else None)."""

    rotation: Tensor
    scale: Tensor
    opacity: Tensor
    colour: Tensor | None
    importance: Tensor | None = None
    fill: Tensor | None = None


class GaussianHeads(nn.Module):
    """Rotation (4), scale (3), opacity (1) and, with ``sh_coeffs`` > 0, SH colour (3K) heads.

    forward(feat [V, C, H, W]) -> :class:`RawGaussians`.
    """

    def __init__(self, channels: int, sh_coeffs: int = 0) -> None:
        super().__init__()
        self.rotation = _head(channels, 4)
        self.scale = _head(channels, 3)
        self.opacity = _head(channels, 1)
        self.colour = _head(channels, 3 * sh_coeffs) if sh_coeffs else None

    def forward(self, feat: Tensor) -> RawGaussians:
        return RawGaussians(self.rotation(feat), self.scale(feat), self.opacity(feat),
                            None if self.colour is None else self.colour(feat))


def activate(raw: RawGaussians, depth: Tensor, images: Tensor, fx: Tensor, scale_cap_m: float | Tensor,
             sh_degree: int) -> dict[str, Tensor]:
    """Raw outputs -> camera-frame Gaussian parameters per pixel.

    Args:
        raw: head outputs for V views.
        depth: [V, H, W] z-depth (metres).
        images: [V, 3, H, W] source pixels in [0, 1].
        fx: [V] focal lengths (pixels).
        scale_cap_m: largest scale (metres): a number, or [V, H, W, 1] per pixel.
        sh_degree: SH degree of the colour head (0 with pixel colour).
    Returns:
        quats [V, H, W, 4] (unit, camera frame), scales [V, H, W, 3] in (0, cap] metres:
        min(softplus(s)·depth/fx, cap), i.e. in units of the pixel's footprint; opacities
        [V, H, W] = sigmoid; sh [V, H, W, K, 3] (camera frame): the pixel's colour as DC plus the
        head's output, degrees l >= 1 damped by 0.1·0.25^l as in GPS-Gaussian.
    """
    from clsplat.models.common.gaussians import rgb_to_sh
    V, _, H, W = images.shape
    quats = F.normalize(raw.rotation.permute(0, 2, 3, 1), dim=-1, eps=1e-8)
    footprint = (depth / fx[:, None, None])[..., None]
    scales = F.softplus(raw.scale.permute(0, 2, 3, 1)) * footprint
    scales = torch.minimum(scales, scale_cap_m) if isinstance(scale_cap_m, Tensor) else scales.clamp_max(scale_cap_m)
    opac = torch.sigmoid(raw.opacity[:, 0])
    K = (sh_degree + 1) ** 2
    dc = rgb_to_sh(images.permute(0, 2, 3, 1).reshape(-1, 3)).reshape(V, H, W, 1, 3)
    sh = F.pad(dc, (0, 0, 0, K - 1))
    if raw.colour is not None:
        damp = torch.tensor([1.0] + [0.1 * 0.25 ** l for l in range(1, sh_degree + 1) for _ in range(2 * l + 1)],
                            dtype=images.dtype, device=images.device)
        sh = sh + raw.colour.permute(0, 2, 3, 1).reshape(V, H, W, K, 3) * damp[:, None]
    return {"quats": quats, "scales": scales, "opacities": opac, "sh": sh}
