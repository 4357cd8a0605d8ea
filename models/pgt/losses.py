"""PGT's training losses.

* :func:`render_terms`: w_l1·L1 + w_ssim·(1 - SSIM) of the rendered target views (GPS-Gaussian+:
  0.8/0.2), plus w_mse·MSE and w_lpips·LPIPS when those weights are set (LPIPS only with
  user-given weight files).
* :func:`depth_term`: with ground-truth depth, L1 between predicted and true normalised inverse
  depth (sky = 0), for the refined u and the coarse u0 alike.
* :func:`chamfer_term`: without depth, the Chamfer distance between neighbouring source views'
  lifted point clouds (``n`` random pixels each, drawn from the sample's generator).
"""
from __future__ import annotations

import torch
from torch import Tensor

from clsplat.models.common.losses import chamfer_distance
from clsplat.models.common.metrics import ssim

from .matching import depth_to_u

__all__ = ["render_terms", "depth_term", "chamfer_term"]


def render_terms(pred: Tensor, target: Tensor, preset, lpips=None) -> dict[str, Tensor]:
    """pred, target [C, 3, H, W] -> {"l1", "ssim" (1 - SSIM), ["mse"], ["lpips"], "render"} (the
    weighted sum under "render")."""
    l1 = (pred - target).abs().mean()
    dssim = 1.0 - ssim(pred, target).mean()
    out = {"l1": l1, "dssim": dssim}
    total = preset.w_l1 * l1 + preset.w_ssim * dssim
    if preset.w_mse:
        out["mse"] = ((pred - target) ** 2).mean()
        total = total + preset.w_mse * out["mse"]
    if preset.w_lpips and lpips is not None:
        out["lpips"] = lpips(pred.clamp(0, 1), target).mean()
        total = total + preset.w_lpips * out["lpips"]
    out["render"] = total
    return out


def depth_term(u: Tensor, u0: Tensor, depth_gt: Tensor, near: float, far: float) -> Tensor:
    """mean |u - u_gt| + mean |u0 - u_gt|, all [V, H, W]; u_gt from ``depth_gt`` (inf = sky -> 0)."""
    g = depth_to_u(depth_gt, near, far)
    return (u - g).abs().mean() + (u0 - g).abs().mean()


def chamfer_term(means: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """Mean Chamfer distance between views v and v+1 of ``means`` [V, H, W, 3], ``n`` random
    points per view (all points when a view has fewer)."""
    V = means.shape[0]
    pts = means.reshape(V, -1, 3)
    P = pts.shape[1]
    k = min(n, P)
    idx = [torch.randperm(P, generator=generator)[:k].to(means.device) for _ in range(V)]
    clouds = [pts[v, idx[v]] for v in range(V)]
    terms = [chamfer_distance(clouds[v][None], clouds[v + 1][None])[0] for v in range(V - 1)]
    return torch.stack(terms).mean()
