"""Cross-view matching at 1/8 resolution along the epipolar geometry the poses give.

Driving source views are not rectified pairs (forward motion puts the epipole inside the image),
so both matchers look at the other views' features where each pixel's ray lands at ``D`` depth
hypotheses, uniform in normalised inverse depth u in [0, 1] over [near, far]
(:func:`depth_hypotheses`, :func:`sample_along_rays`). Sampled at the same points, they differ in
what they do with the samples:

* :class:`PlaneSweepMatcher`: a plane-sweep cost volume (scaled dot-product correlation per
  hypothesis, averaged over the other views where valid), regularised by 2D residual blocks over
  [cost, feature], softmax over hypotheses -> coarse u0 = Σ p_k u_k.
* :class:`EpipolarAttentionMatcher`: GPS-Gaussian+'s cross-view attention (``attn_layers`` layers,
  ``attn_heads`` heads) with each pixel's query attending to the other views' features sampled
  along its epipolar line (plus a hypothesis embedding); u0 is the attention-weighted
  hypothesis of the last layer.

Both return (matched features [V, C, h, w], hypothesis probabilities [V, D, h, w], u0 [V, h, w]).
Which one the presets use, and why, is measured in ``bench/pgt_matching.py``.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clsplat.models.common.backbones import ResidualBlock
from clsplat.models.common.geometry import invert_rigid, project, unproject

__all__ = ["depth_hypotheses", "u_to_depth", "depth_to_u", "sample_along_rays", "PlaneSweepMatcher",
           "EpipolarAttentionMatcher", "make_matcher"]


def u_to_depth(u: Tensor, near: float, far: float) -> Tensor:
    """Normalised inverse depth u in [0, 1] -> z-depth in [near, far] (u = 1 at near)."""
    return 1.0 / (u * (1.0 / near - 1.0 / far) + 1.0 / far)


def depth_to_u(depth: Tensor, near: float, far: float) -> Tensor:
    """z-depth -> normalised inverse depth, clamped to [0, 1] (inf, i.e. sky -> 0)."""
    return ((1.0 / depth - 1.0 / far) / (1.0 / near - 1.0 / far)).clamp(0.0, 1.0)


def depth_hypotheses(num: int, device=None, dtype=torch.float32) -> Tensor:
    """[D] hypotheses uniform in u, from 0 (far) to 1 (near)."""
    return torch.linspace(0.0, 1.0, num, device=device, dtype=dtype)


def sample_along_rays(feats: Tensor, Ks: Tensor, cam_to_world: Tensor, u_hyp: Tensor, near: float,
                      far: float) -> tuple[Tensor, Tensor]:
    """For every view i, every other view j and every hypothesis k: view j's feature where pixel
    (x, y) of view i, lifted to depth ``u_to_depth(u_hyp[k])``, projects.

    Args:
        feats: [V, C, h, w] features (the grid the intrinsics ``Ks`` describe).
        Ks: [V, 3, 3] intrinsics of that grid.
        cam_to_world: [V, 4, 4].
        u_hyp: [D] hypotheses.
    Returns:
        samples [V, V-1, D, C, h, w] (zeros where invalid) and valid [V, V-1, D, h, w] (float:
        in front of view j and inside its image). Others are ordered j = 0..V-1 without i.
    """
    V, C, h, w = feats.shape
    D = u_hyp.shape[0]
    depth = u_to_depth(u_hyp, near, far).to(feats.dtype)[None, :, None, None].expand(V, D, h, w)
    pts = unproject(depth.reshape(V * D, h, w), Ks.repeat_interleave(D, 0),
                    cam_to_world.repeat_interleave(D, 0)).reshape(V, D * h * w, 3)
    w2c = invert_rigid(cam_to_world)
    samples, valid = [], []
    for i in range(V):
        others = [j for j in range(V) if j != i]
        uv, z = project(pts[i].expand(len(others), -1, -1), Ks[others], w2c[others])  # [V-1, D*h*w, ...]
        grid = torch.stack([2 * uv[..., 0] / w - 1, 2 * uv[..., 1] / h - 1], -1)
        ok = (z > 1e-3) & (grid.abs() <= 1).all(-1)
        grid = torch.where(ok[..., None], grid, torch.full_like(grid, 2.0))
        # border padding: a valid point within half a pixel of the edge is not blended with zeros
        s = F.grid_sample(feats[others], grid.reshape(len(others), D, h * w, 2), mode="bilinear",
                          padding_mode="border", align_corners=False)  # [V-1, C, D, h*w]
        s = s * ok.reshape(len(others), 1, D, h * w).to(s.dtype)
        samples.append(s.reshape(len(others), C, D, h, w).permute(0, 2, 1, 3, 4))
        valid.append(ok.reshape(len(others), D, h, w).to(feats.dtype))
    return torch.stack(samples), torch.stack(valid)


class PlaneSweepMatcher(nn.Module):
    """Plane-sweep cost volume + 2D regularisation.

    cost[i, k] = mean over valid j of <f_i, f_j(k)> / sqrt(C); [cost (D) + f_i (C)] -> 3x3 conv
    to ``cost_channels`` -> 2 residual blocks -> 3x3 conv to D logits. Matched feature:
    [f_i, regularised] -> 1x1 conv -> C.
    """

    def __init__(self, channels: int, num_depths: int, cost_channels: int, near: float, far: float,
                 norm: str = "group") -> None:
        super().__init__()
        self.num_depths, self.min_depth, self.max_depth = num_depths, near, far
        self.stem = nn.Sequential(nn.Conv2d(num_depths + channels, cost_channels, 3, padding=1), nn.ReLU(inplace=True))
        self.blocks = nn.Sequential(ResidualBlock(cost_channels, cost_channels, 1, norm),
                                    ResidualBlock(cost_channels, cost_channels, 1, norm))
        self.logits = nn.Conv2d(cost_channels, num_depths, 3, padding=1)
        self.fuse = nn.Conv2d(channels + cost_channels, channels, 1)

    def forward(self, feats: Tensor, Ks: Tensor, cam_to_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """feats [V, C, h, w], Ks [V, 3, 3] (of the 1/8 grid), cam_to_world [V, 4, 4]
        -> (matched [V, C, h, w], prob [V, D, h, w], u0 [V, h, w])."""
        V, C = feats.shape[:2]
        u_hyp = depth_hypotheses(self.num_depths, feats.device, feats.dtype)
        samples, valid = sample_along_rays(feats, Ks, cam_to_world, u_hyp, self.min_depth, self.max_depth)
        corr = (samples * feats[:, None, None]).sum(3) / math.sqrt(C)  # [V, V-1, D, h, w]
        cost = (corr * valid).sum(1) / valid.sum(1).clamp_min(1.0)
        x = self.blocks(self.stem(torch.cat([cost, feats], 1)))
        prob = self.logits(x).softmax(1)
        u0 = (prob * u_hyp[None, :, None, None]).sum(1)
        return self.fuse(torch.cat([feats, x], 1)), prob, u0


class _EpipolarLayer(nn.Module):
    """One pre-norm cross-attention layer: each pixel's query attends to its [S] epipolar samples."""

    def __init__(self, channels: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm_q, self.norm_kv, self.norm_mlp = (nn.LayerNorm(channels) for _ in range(3))
        self.q, self.k, self.v, self.o = (nn.Linear(channels, channels) for _ in range(4))
        self.mlp = nn.Sequential(nn.Linear(channels, 2 * channels), nn.GELU(), nn.Linear(2 * channels, channels))

    def forward(self, x: Tensor, kv: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        """x [P, C] queries, kv [P, S, C], mask [P, S] (bool) -> (x [P, C], attn [P, heads, S])."""
        P, S, C = kv.shape
        hd = C // self.heads
        q = self.q(self.norm_q(x)).reshape(P, self.heads, 1, hd)
        kvn = self.norm_kv(kv)
        k = self.k(kvn).reshape(P, S, self.heads, hd).transpose(1, 2)
        v = self.v(kvn).reshape(P, S, self.heads, hd).transpose(1, 2)
        logits = (q @ k.transpose(-1, -2)).squeeze(2) / math.sqrt(hd)  # [P, heads, S]
        logits = logits.masked_fill(~mask[:, None], -1e4)
        attn = logits.softmax(-1)
        x = x + self.o((attn[..., None, :] @ v).reshape(P, C))
        return x + self.mlp(self.norm_mlp(x)), attn


class EpipolarAttentionMatcher(nn.Module):
    """Cross-view attention along epipolar lines (``layers`` x ``heads``, ``channels`` wide).

    Keys/values: the other views' features at the D hypotheses of each pixel's ray (all other
    views concatenated, S = (V-1)·D samples) plus a learned embedding of the hypothesis index.
    u0 = Σ_s attn_s u_s with the last layer's attention averaged over heads.
    """

    def __init__(self, channels: int, num_depths: int, layers: int, heads: int, near: float, far: float) -> None:
        super().__init__()
        self.num_depths, self.min_depth, self.max_depth = num_depths, near, far
        self.hyp_embed = nn.Parameter(torch.zeros(num_depths, channels))
        nn.init.normal_(self.hyp_embed, std=0.02)
        self.layers = nn.ModuleList(_EpipolarLayer(channels, heads) for _ in range(layers))

    def forward(self, feats: Tensor, Ks: Tensor, cam_to_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """As :meth:`PlaneSweepMatcher.forward`."""
        V, C, h, w = feats.shape
        D = self.num_depths
        u_hyp = depth_hypotheses(D, feats.device, feats.dtype)
        samples, valid = sample_along_rays(feats, Ks, cam_to_world, u_hyp, self.min_depth, self.max_depth)
        # [V, V-1, D, C, h, w] -> [V*h*w, (V-1)*D, C]
        kv = samples.permute(0, 4, 5, 1, 2, 3).reshape(V * h * w, (V - 1) * D, C)
        kv = kv + self.hyp_embed.repeat(V - 1, 1)[None]
        mask = valid.permute(0, 3, 4, 1, 2).reshape(V * h * w, (V - 1) * D) > 0
        mask = mask | ~mask.any(1, keepdim=True)  # a pixel that sees nothing attends uniformly
        x = feats.permute(0, 2, 3, 1).reshape(V * h * w, C)
        attn = None
        for layer in self.layers:
            x, attn = layer(x, kv, mask)
        prob = attn.mean(1).reshape(V * h * w, V - 1, D).sum(1)  # marginal over the other views
        prob = prob.reshape(V, h, w, D).permute(0, 3, 1, 2)
        u0 = (prob * u_hyp[None, :, None, None]).sum(1)
        return x.reshape(V, h, w, C).permute(0, 3, 1, 2), prob, u0


def make_matcher(preset) -> nn.Module:
    """The matcher a :class:`~clsplat.models.pgt.presets.PGTPreset` names."""
    c = preset.channels[2]
    if preset.matching == "plane_sweep":
        return PlaneSweepMatcher(c, preset.num_depths, preset.cost_channels, preset.min_depth, preset.max_depth, preset.norm)
    return EpipolarAttentionMatcher(c, preset.num_depths, preset.attn_layers, preset.attn_heads, preset.min_depth, preset.max_depth)
