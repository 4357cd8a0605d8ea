"""Volumetric feature fusion (VFDepth), the surround-view glue of the depth and pose networks.

Image -> voxel: every voxel centre of an ego-frame grid is projected into every camera; where it
is in front of the camera and inside its image it samples that camera's 1/8-resolution feature
bilinearly, plus one channel holding the camera depth / 100 (C + 1 channels).

* depth mode: a voxel seen by exactly one camera gets ``Conv1x1(C+1 -> 64)`` of that sample, one
  seen by exactly two (an overlap) gets ``Conv1x1(2(C+1) -> 64)`` of both samples concatenated in
  rig order; voxels seen by none or by three or more stay zero. Voxel -> image: every 1/8 pixel
  samples the grid trilinearly at ``depth_bins`` z-depths from ``bin_near`` to ``bin_far`` along
  its ray; the ``depth_bins * 64`` channels are reduced by 3x3 convs (256, then 128), giving the
  fused feature that replaces the 1/8 image feature.
* pose mode: the samples are averaged over the cameras that see a voxel, the volume is flattened
  to a bird's-eye map (channels x height bins) and reduced by two stride-2 3x3 convs (256, 128).

Everything is vectorised: the (camera, voxel) pairs that see each other are gathered at once
(bilinear weights by index arithmetic, no grid over invisible voxels), the volume is sampled with
one ``grid_sample``. No self-occlusion mask is applied (the synthetic rig sees no ego body; real
rigs with a visible bonnet would need one per camera).
"""
from __future__ import annotations

import torch
from torch import Tensor, nn
import torch.nn.functional as F

__all__ = ["VolumetricFusion", "scale_intrinsics", "sample_pairs"]


def scale_intrinsics(K: Tensor, factor: float) -> Tensor:
    """Intrinsics ``[..., 3, 3]`` of an image resized by ``factor`` (pixel-centre convention:
    continuous pixel coordinates scale exactly)."""
    S = torch.diag(torch.tensor([factor, factor, 1.0], dtype=K.dtype, device=K.device))
    return S @ K


def _conv(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    """Conv (reflection padding for 3x3) followed by LeakyReLU(0.1)."""
    pad = k // 2
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, pad, padding_mode="reflect" if pad else "zeros"),
                         nn.LeakyReLU(0.1, inplace=True))


def sample_pairs(feats: Tensor, cam: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples of camera features at continuous pixel coordinates.

    Args:
        feats: ``[V, C, h, w]`` feature maps.
        cam: ``[P]`` long, camera of each sample.
        uv: ``[P, 2]`` continuous coordinates (pixel centres at +0.5), inside ``[0, w] x [0, h]``.
    Returns:
        ``[P, C]`` samples (border pixels replicated), differentiable w.r.t. ``feats``.
    """
    V, C, h, w = feats.shape
    flat = feats.permute(0, 2, 3, 1).reshape(V * h * w, C)
    x = uv[:, 0] - 0.5
    y = uv[:, 1] - 0.5
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = (x - x0).unsqueeze(1)
    fy = (y - y0).unsqueeze(1)
    x0 = x0.long()
    y0 = y0.long()
    base = cam * (h * w)

    def at(xi: Tensor, yi: Tensor) -> Tensor:
        return flat[base + yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)]

    return ((1 - fx) * (1 - fy) * at(x0, y0) + fx * (1 - fy) * at(x0 + 1, y0)
            + (1 - fx) * fy * at(x0, y0 + 1) + fx * fy * at(x0 + 1, y0 + 1))


class VolumetricFusion(nn.Module):
    """Surround-view voxel fusion in depth mode or pose mode (see the module docstring).

    Args:
        in_channels: C, channels of the 1/8 features (256 in the paper).
        mode: "depth" or "pose".
        voxel_origin, voxel_size, voxel_shape: the ego-frame grid (metres; counts x, y, z).
        voxel_channels: channels of the one-/two-camera 1x1 convs (depth mode; 64).
        out_channels: the two 3x3 reductions (depth mode: (256, 128); pose mode: (256, 128)).
        depth_bins, bin_near, bin_far: samples per ray of the voxel -> image step (depth mode).
    """

    def __init__(self, in_channels: int, mode: str, voxel_origin, voxel_size, voxel_shape,
                 voxel_channels: int = 64, out_channels: tuple[int, int] = (256, 128),
                 depth_bins: int = 50, bin_near: float = 2.0, bin_far: float = 50.0) -> None:
        super().__init__()
        if mode not in ("depth", "pose"):
            raise ValueError(f"mode must be 'depth' or 'pose', got {mode!r}")
        self.mode = mode
        self.voxel_shape = tuple(int(n) for n in voxel_shape)
        X, Y, Z = self.voxel_shape
        origin = torch.tensor(voxel_origin, dtype=torch.float32)
        size = torch.tensor(voxel_size, dtype=torch.float32)
        ix, iy, iz = torch.meshgrid(torch.arange(X), torch.arange(Y), torch.arange(Z), indexing="ij")
        centres = origin + (torch.stack([ix, iy, iz], -1).reshape(-1, 3).float() + 0.5) * size
        self.register_buffer("centres", centres, persistent=False)           # [X*Y*Z, 3], x-major
        self.register_buffer("origin", origin, persistent=False)
        self.register_buffer("extent", size * torch.tensor([X, Y, Z], dtype=torch.float32), persistent=False)
        c1 = in_channels + 1
        if mode == "depth":
            self.voxel_channels = voxel_channels
            self.one_camera = nn.Sequential(nn.Linear(c1, voxel_channels), nn.LeakyReLU(0.1, inplace=True))
            self.two_camera = nn.Sequential(nn.Linear(2 * c1, voxel_channels), nn.LeakyReLU(0.1, inplace=True))
            self.register_buffer("bins", torch.linspace(bin_near, bin_far, depth_bins), persistent=False)
            self.reduce = nn.Sequential(_conv(depth_bins * voxel_channels, out_channels[0], 3),
                                        _conv(out_channels[0], out_channels[1], 3))
        else:
            self.reduce = nn.Sequential(_conv(c1 * Z, out_channels[0], 3, stride=2),
                                        _conv(out_channels[0], out_channels[1], 3, stride=2))
        self.out_channels = out_channels[1]

    def visible_pairs(self, Ks: Tensor, cam_to_ego: Tensor, h: int, w: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(camera, voxel) pairs where the voxel centre is in front of and inside the camera.

        Args:
            Ks: ``[V, 3, 3]`` intrinsics of the ``h x w`` feature maps; cam_to_ego ``[V, 4, 4]``.
        Returns:
            ``cam [P]``, ``vox [P]`` (sorted by voxel, then camera), ``uv [P, 2]``, ``z [P]``.
        """
        R = cam_to_ego[:, :3, :3]
        t = cam_to_ego[:, :3, 3]
        p = torch.einsum("vji,vnj->vni", R, self.centres.unsqueeze(0) - t[:, None, :])   # [V, N, 3]
        z = p[..., 2]
        uvw = torch.einsum("vij,vnj->vni", Ks, p)
        uv = uvw[..., :2] / z.clamp_min(1e-6).unsqueeze(-1)
        ok = (z > 0.1) & (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
        vox, cam = torch.nonzero(ok.t(), as_tuple=True)
        return cam, vox, uv[cam, vox], z[cam, vox]

    def image_to_voxel(self, feats: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> Tensor:
        """The fused voxel volume.

        Args:
            feats: ``[V, C, h, w]``; Ks: ``[V, 3, 3]`` for the feature resolution; cam_to_ego ``[V, 4, 4]``.
        Returns:
            depth mode ``[64, Z, Y, X]``; pose mode ``[C + 1, Z, Y, X]`` (grid_sample layout).
        """
        V, C, h, w = feats.shape
        X, Y, Z = self.voxel_shape
        n = X * Y * Z
        cam, vox, uv, z = self.visible_pairs(Ks, cam_to_ego, h, w)
        samples = torch.cat([sample_pairs(feats, cam, uv), (z / 100.0).unsqueeze(1)], 1)   # [P, C+1]
        count = torch.bincount(vox, minlength=n)
        if self.mode == "pose":
            acc = feats.new_zeros(n, C + 1).index_add(0, vox, samples)
            vol = acc / count.clamp_min(1).unsqueeze(1).to(acc.dtype)
        else:
            first = torch.cumsum(count, 0) - count
            rank = torch.arange(vox.numel(), device=vox.device) - first[vox]
            k = count[vox]
            one = k == 1
            a = (k == 2) & (rank == 0)
            b = (k == 2) & (rank == 1)
            vol = feats.new_zeros(n, self.voxel_channels)
            vol = vol.index_put((vox[one],), self.one_camera(samples[one]))
            vol = vol.index_put((vox[a],), self.two_camera(torch.cat([samples[a], samples[b]], 1)))
        return vol.reshape(X, Y, Z, -1).permute(3, 2, 1, 0)

    def voxel_to_image(self, vol: Tensor, Ks: Tensor, cam_to_ego: Tensor, h: int, w: int) -> Tensor:
        """Sample the volume along every 1/8 pixel's ray: ``[V, depth_bins * 64, h, w]``."""
        V = Ks.shape[0]
        D = self.bins.numel()
        v, u = torch.meshgrid(torch.arange(h, device=Ks.device, dtype=Ks.dtype) + 0.5,
                              torch.arange(w, device=Ks.device, dtype=Ks.dtype) + 0.5, indexing="ij")
        pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(-1, 3)              # [hw, 3]
        rays = torch.einsum("vij,nj->vni", torch.linalg.inv(Ks), pix)                # [V, hw, 3], z = 1
        pts = rays.unsqueeze(2) * self.bins.view(1, 1, D, 1)                          # [V, hw, D, 3]
        pts = torch.einsum("vij,vndj->vndi", cam_to_ego[:, :3, :3], pts) + cam_to_ego[:, None, None, :3, 3]
        grid = (pts - self.origin) / self.extent * 2 - 1                             # x, y, z in [-1, 1]
        out = F.grid_sample(vol.unsqueeze(0), grid.unsqueeze(0), mode="bilinear", padding_mode="zeros",
                            align_corners=False)                                      # [1, 64, V, hw, D]
        out = out[0].permute(1, 3, 0, 2)                                              # [V, D, 64, hw]
        return out.reshape(V, D * vol.shape[0], h, w)

    def forward(self, feats: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> Tensor:
        """Fuse one instant's cameras.

        Args:
            feats: ``[V, C, h, w]`` 1/8 features; Ks: ``[V, 3, 3]`` intrinsics of the *feature* maps;
            cam_to_ego: ``[V, 4, 4]``.
        Returns:
            depth mode: ``[V, 128, h, w]`` fused per-camera features;
            pose mode: ``[1, 128, X/4, Y/4]`` bird's-eye features.
        """
        vol = self.image_to_voxel(feats, Ks, cam_to_ego)
        if self.mode == "pose":
            C1, Z, Y, X = vol.shape
            bev = vol.permute(0, 1, 3, 2).reshape(1, C1 * Z, X, Y)
            return self.reduce(bev)
        h, w = feats.shape[-2:]
        return self.reduce(self.voxel_to_image(vol, Ks, cam_to_ego, h, w))
