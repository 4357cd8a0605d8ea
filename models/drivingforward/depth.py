"""The depth network: ResNet-18 encoder, volumetric fusion, ELU decoder, metric depth mapping.

Per image, a ResNet-18 (``clsplat.models.common.backbones``) gives features at 1/2 .. 1/32;
levels 2-4 (128 + 256 + 512 channels) are resized to 1/8 and reduced to 256 by a 1x1 conv
(:class:`MultiLevelReduce`). The surround cameras of one instant are fused in the voxel grid
(:class:`~.fusion.VolumetricFusion`, depth mode), giving a 128-channel 1/8 feature per camera.
The decoder (16, 32, 64, 128, 256 channels, ELU, no skips) upsamples it to full resolution and
ends in one sigmoid ``sigma``; depth = 1 / (1/max + (1/min - 1/max) sigma) * fx / focal_ref.
Input images are normalised as (x - 0.45) / 0.225.

Initialisation: the layers after the encoder (reduction, fusion, decoder) have no normalisation,
and with PyTorch's default init (variance 1/(3 fan_in)) the signal shrinks by about sqrt(3) per
layer: from a randomly initialised encoder the fused feature is ~0.02 and the decoder's output
is constant over the image. Adam then grows the weights until the sigmoid saturates (sigma ~ 0,
every pixel at the far limit, no gradient left), which is what a first small-preset run did
within 30 steps. :func:`he_init` gives those layers He initialisation (bias 0), which keeps unit
activations through the stack; the paper starts from ImageNet weights and does not say.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
import torch.nn.functional as F

from ..common.backbones import ResNet18
from .fusion import VolumetricFusion, scale_intrinsics

__all__ = ["MultiLevelReduce", "DepthDecoder", "DepthNetwork", "sigma_to_depth", "depth_to_sigma", "ground_prior_depth",
           "normalise_image", "he_init"]


def normalise_image(x: Tensor) -> Tensor:
    """(x - 0.45) / 0.225, the input normalisation of both ResNet encoders."""
    return (x - 0.45) / 0.225


def he_init(*modules: nn.Module, skip: tuple[nn.Module, ...] = ()) -> None:
    """He (fan-in, LeakyReLU 0.1) initialisation of every Conv2d / Linear in ``modules``, biases 0;
    modules in ``skip`` keep their initialisation (e.g. an output layer before a sigmoid)."""
    skipped = {id(m) for m in skip}
    for root in modules:
        for m in root.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)) and id(m) not in skipped:
                nn.init.kaiming_normal_(m.weight, a=0.1, mode="fan_in", nonlinearity="leaky_relu")
                if m.bias is not None:
                    nn.init.zeros_(m.bias)


class MultiLevelReduce(nn.Module):
    """ResNet levels 2-4 resized to 1/8 and reduced by a 1x1 conv: ``[B, 896, h, w] -> [B, out, h, w]``."""

    def __init__(self, in_channels: tuple[int, ...] = (128, 256, 512), out_channels: int = 256) -> None:
        super().__init__()
        self.conv = nn.Conv2d(sum(in_channels), out_channels, 1)

    def forward(self, levels: list[Tensor]) -> Tensor:
        size = levels[0].shape[-2:]
        up = [levels[0]] + [F.interpolate(f, size=size, mode="bilinear", align_corners=False) for f in levels[1:]]
        return self.conv(torch.cat(up, 1))


def _conv3(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1, padding_mode="reflect"), nn.ELU(inplace=True))


class DepthDecoder(nn.Module):
    """ELU decoder from a 1/8 feature to a full-resolution sigmoid; without skips (the paper) or with
    monodepth2's skips from the encoder at 1/4 and 1/2 resolution.

    Five stages, widest first (256, 128, 64, 32, 16); each is conv3x3 + ELU, (x2 nearest upsampling
    for the last three, which take 1/8 to full resolution), conv3x3 + ELU. Then conv3x3 -> 1, sigmoid.
    With ``skip_channels`` = (c4, c2), the 1/4 and 1/2 encoder features are concatenated after the
    first two upsamplings, as monodepth2 does (it has no skip at full resolution either).

    Args:
        in_channels: the fused feature's channels (128).
        channels: decoder widths, full resolution first: (16, 32, 64, 128, 256).
        skip_channels: channels of the 1/4 and 1/2 features to concatenate; None: no skips.
    """

    def __init__(self, in_channels: int = 128, channels: tuple[int, ...] = (16, 32, 64, 128, 256),
                 skip_channels: tuple[int, int] | None = None) -> None:
        super().__init__()
        widths = list(reversed(channels))                       # 256, 128, 64, 32, 16
        n = len(widths)
        # stage i upsamples when i >= n - 3; the skips join after the upsamplings to 1/4 and 1/2
        skips = {n - 3: skip_channels[0], n - 2: skip_channels[1]} if skip_channels else {}
        self.stages = nn.ModuleList()
        self.upsample = []
        self.skip_at: list[bool] = []
        cin = in_channels
        for i, c in enumerate(widths):
            self.stages.append(nn.ModuleDict({"upconv_0": _conv3(cin, c), "upconv_1": _conv3(c + skips.get(i, 0), c)}))
            self.upsample.append(i >= n - 3)
            self.skip_at.append(i in skips)
            cin = c
        self.dispconv = nn.Conv2d(cin, 1, 3, 1, 1, padding_mode="reflect")

    def forward(self, x: Tensor, skips: tuple[Tensor, Tensor] | None = None, logit_offset: Tensor | None = None) -> Tensor:
        """``[B, in, h, w] -> sigma [B, 1, 8h, 8w]`` in (0, 1); ``skips`` = (``[B, c4, 2h, 2w]``,
        ``[B, c2, 4h, 4w]``) when built with ``skip_channels``; ``logit_offset`` ``[B, 1, 8h, 8w]``
        is added before the sigmoid (a depth prior; None: none, the paper)."""
        if any(self.skip_at) and skips is None:
            raise ValueError("skips: this decoder was built with skip_channels; pass the 1/4 and 1/2 features")
        pending = list(skips) if any(self.skip_at) else []
        for stage, up, join in zip(self.stages, self.upsample, self.skip_at):
            x = stage["upconv_0"](x)
            if up:
                x = F.interpolate(x, scale_factor=2, mode="nearest")
            if join:
                x = torch.cat([x, pending.pop(0)], dim=1)
            x = stage["upconv_1"](x)
        logits = self.dispconv(x)
        return torch.sigmoid(logits if logit_offset is None else logits + logit_offset)


def sigma_to_depth(sigma: Tensor, fx: Tensor, min_depth: float, max_depth: float, focal_ref: float) -> Tensor:
    """Metric depth from the decoder's sigmoid.

    Args:
        sigma: ``[V, 1, H, W]`` in (0, 1); fx: ``[V]`` focal length (pixels) of the input images.
    Returns:
        ``[V, 1, H, W]`` depth = 1 / (1/max + (1/min - 1/max) sigma) * fx / focal_ref.
    """
    inv = 1.0 / max_depth + (1.0 / min_depth - 1.0 / max_depth) * sigma
    return (1.0 / inv) * (fx / focal_ref).view(-1, 1, 1, 1)


def ground_prior_depth(Ks: Tensor, cam_to_ego: Tensor, height: int, width: int, cap: float) -> Tensor:
    """Depth (along each camera's axis) at which every pixel's ray meets the ground plane z = 0 of
    the ego frame, ``cap`` where it meets it farther or not at all (above the horizon).

    Ks: ``[V, 3, 3]``; cam_to_ego: ``[V, 4, 4]`` -> ``[V, 1, height, width]`` metres. The ego
    frame must stand on the ground (z up, z = 0 the road: the synthetic rig, nuScenes' ego frame,
    clsplat's PandaSet writer); a camera at or below z = 0 is a ValueError, since the prior would
    then be garbage (a real PandaSet sequence's ego frame is its roof LiDAR's).
    """
    if bool((cam_to_ego[:, 2, 3] <= 0).any()):
        heights = [round(float(h), 3) for h in cam_to_ego[:, 2, 3]]
        raise ValueError("ground_prior_cap: the ground prior needs the ego frame's z = 0 to be the ground, but "
                         f"camera heights are {heights} m; train with --set ground_prior_cap=None")
    v, u = torch.meshgrid(torch.arange(height, dtype=Ks.dtype, device=Ks.device) + 0.5,
                          torch.arange(width, dtype=Ks.dtype, device=Ks.device) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], 0).reshape(3, -1)                 # [3, HW]
    rays = torch.linalg.inv(Ks) @ pix                                              # camera frame, z = 1
    down = (cam_to_ego[:, 2:3, :3] @ rays)[:, 0]                                   # ego z per unit depth
    h = cam_to_ego[:, 2, 3:4]                                                      # camera height
    t = torch.where(down < -1e-6, h / (-down).clamp_min(1e-6), torch.full_like(down, cap))
    return t.clamp(max=cap).reshape(-1, 1, height, width)


def depth_to_sigma(depth: Tensor, fx: Tensor, min_depth: float, max_depth: float, focal_ref: float) -> Tensor:
    """The inverse of :func:`sigma_to_depth` (depth clamped into the mapped range first)."""
    lo = min_depth * fx / focal_ref
    hi = max_depth * fx / focal_ref
    d = torch.minimum(torch.maximum(depth, lo.view(-1, 1, 1, 1)), hi.view(-1, 1, 1, 1))
    inv = (1.0 / d) * (fx / focal_ref).view(-1, 1, 1, 1)
    return (inv - 1.0 / max_depth) / (1.0 / min_depth - 1.0 / max_depth)


class DepthNetwork(nn.Module):
    """ResNet-18 + volumetric fusion + ELU decoder (VFDepth), for one instant's cameras.

    Args:
        preset: a :class:`~.presets.DFPreset` (grid, bins, channels, depth range).
    """

    def __init__(self, preset) -> None:
        super().__init__()
        self.preset = preset
        self.encoder = ResNet18(in_channels=3)
        self.reduce = MultiLevelReduce((128, 256, 512), preset.fusion_channels)
        self.fusion = VolumetricFusion(preset.fusion_channels, "depth", preset.voxel_origin, preset.voxel_size,
                                       preset.voxel_shape, preset.voxel_channels, preset.proj_channels,
                                       preset.depth_bins, preset.bin_near, preset.bin_far)
        skips = (64, 64) if preset.depth_skips else None     # ResNet-18's 1/4 and 1/2 widths
        self.decoder = DepthDecoder(preset.proj_channels[1], preset.depth_decoder_channels, skips)
        he_init(self.reduce, self.fusion, self.decoder, skip=(self.decoder.dispconv,))
        if preset.depth_zero_init:       # start exactly at the prior (the decoder's zero output)
            nn.init.zeros_(self.decoder.dispconv.weight)
            nn.init.zeros_(self.decoder.dispconv.bias)

    def forward(self, images: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> dict[str, Tensor]:
        """Depth of every camera of one instant.

        Args:
            images: ``[V, 3, H, W]`` in [0, 1]; Ks: ``[V, 3, 3]`` (of the H x W images);
            cam_to_ego: ``[V, 4, 4]``.
        Returns:
            ``depth [V, 1, H, W]`` metres, ``sigma [V, 1, H, W]``, and the features the Gaussian
            network uses: ``f2 [V, 64, H/2, W/2]``, ``f4 [V, 64, H/4, W/4]``, ``f8 [V, 128, H/8, W/8]``.
        """
        f = self.encoder.forward_features(normalise_image(images))
        feat8 = self.reduce(f[2:5])
        fused = self.fusion(feat8, scale_intrinsics(Ks, 1.0 / 8), cam_to_ego)
        p = self.preset
        offset = None
        if p.ground_prior_cap is not None:
            # the decoder predicts around the ground plane's depth (or the cap above the horizon)
            prior = ground_prior_depth(Ks, cam_to_ego, images.shape[-2], images.shape[-1], p.ground_prior_cap)
            offset = torch.logit(depth_to_sigma(prior, Ks[:, 0, 0], p.min_depth, p.max_depth, p.focal_ref), eps=1e-4)
        sigma = self.decoder(fused, (f[1], f[0]) if p.depth_skips else None, offset)
        depth = sigma_to_depth(sigma, Ks[:, 0, 0], p.min_depth, p.max_depth, p.focal_ref)
        return {"depth": depth, "sigma": sigma, "f2": f[0], "f4": f[1], "f8": fused}
