"""DrivingForward's self-supervised losses, per camera and averaged over cameras.

``L = L_reproj + w_smooth L_smooth + w_spatial L_spatial + w_st L_spatio-temporal + w_render L_render``
(weights in the preset; paper 0.001 / 0.03 / 0.1 / 0.01).

* :func:`temporal_loss` (L_reproj): frames t-1 and t+1 of the same camera warped into frame t with
  the predicted depth and the camera's motion; per pixel the minimum photometric error over the two
  frames, auto-masked as in monodepth2 (the identity error of the unwarped frames, plus a tiny
  noise, joins the minimum, so static or ego-speed pixels cost nothing). Pixels that project
  outside a source image take no part in that frame's minimum.
* :func:`spatial_loss`: the neighbouring cameras at the same instant warped through the rig
  extrinsics (this is what fixes metric scale), brightness-normalised (per channel mean/std of
  the warped neighbour matched to the target's) over the overlap; the mean error over the overlap.
* :func:`spatio_temporal_loss`: the neighbouring cameras at t-1 and t+1, through extrinsics and
  ego motion, brightness-normalised, minimum over the two frames, mean over the overlap.
* :func:`smoothness_loss`: edge-aware smoothness of the mean-normalised disparity (1 / depth).
* :func:`render_loss`: MSE of the render against the real image, + w_lpips LPIPS only when an
  LPIPS module (user-given weights) is passed.

Photometric error, warping and smoothness are the shared ones (``clsplat.models.common``).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor
import torch.nn.functional as F

from ..common.geometry import invert_rigid, warp
from ..common.losses import edge_aware_smoothness, photometric_error

__all__ = ["rig_neighbours", "temporal_loss", "spatial_loss", "spatio_temporal_loss", "smoothness_loss",
           "render_loss", "brightness_normalise"]

_INVALID = 1e4  # error given to pixels that a source view does not see (never the minimum)


def rig_neighbours(cam_to_ego: Tensor) -> list[tuple[int, int]]:
    """(target, neighbour) pairs: each camera and the cameras next to it by yaw around the rig.

    Args:
        cam_to_ego: ``[V, 4, 4]``.
    Returns:
        pairs ``(c, n)``, both directions, no duplicates; empty for one camera.
    """
    V = cam_to_ego.shape[0]
    if V < 2:
        return []
    axis = cam_to_ego[:, :3, 2].detach().cpu().double()
    yaw = [math.atan2(float(a[1]), float(a[0])) for a in axis]
    order = sorted(range(V), key=lambda i: yaw[i])
    pairs = []
    for k, c in enumerate(order):
        for n in (order[k - 1], order[(k + 1) % V]):
            if n != c and (c, n) not in pairs:
                pairs.append((c, n))
    return pairs


def brightness_normalise(warped: Tensor, target: Tensor, valid: Tensor, eps: float = 1e-4) -> Tensor:
    """Match per-channel mean/std of ``warped`` to ``target`` over ``valid``.

    Args:
        warped, target: ``[B, 3, H, W]``; valid: ``[B, 1, H, W]`` float in {0, 1}.
    Returns:
        ``[B, 3, H, W]``.
    """
    n = valid.sum(dim=(2, 3), keepdim=True).clamp_min(1.0)
    mw = (warped * valid).sum(dim=(2, 3), keepdim=True) / n
    mt = (target * valid).sum(dim=(2, 3), keepdim=True) / n
    sw = (((warped - mw) ** 2 * valid).sum(dim=(2, 3), keepdim=True) / n).add(eps).sqrt()
    st = (((target - mt) ** 2 * valid).sum(dim=(2, 3), keepdim=True) / n).add(eps).sqrt()
    return (warped - mw) / sw * st + mt


def temporal_loss(target: Tensor, sources: list[Tensor], depth: Tensor, Ks: Tensor, T_to_src: list[Tensor],
                  noise: Tensor | None = None, automask: bool = True, margin: float = 0.0,
                  mask: Tensor | None = None) -> Tensor:
    """Auto-masked minimum reprojection loss.

    Args:
        target: ``[V, 3, H, W]`` frame t; sources: frames t-1, t+1, each ``[V, 3, H, W]``.
        depth: ``[V, 1, H, W]`` predicted depth at t; Ks ``[V, 3, 3]``.
        T_to_src: per source ``[V, 4, 4]`` camera motion (p_src = T p_t).
        noise: ``[V, len(sources), H, W]`` tie-break noise for the identity errors (monodepth2 1e-5 randn).
        automask: the identity errors join the minimum (monodepth2, the paper); False: the minimum
            over the warped frames only, so every pixel a source sees gets a gradient.
        margin: added to the identity errors: the unwarped frame masks a pixel only when it beats
            every warp by more than this (0: monodepth2's mask, which also drops a pixel whose
            warp is merely no better than no warp, e.g. a wrong warp over uniform asphalt).
        mask: ``[V, 1, H, W]``: only these pixels count (None: all).
    Returns:
        scalar, mean over cameras and (masked) pixels.
    """
    reproj, ident = [], []
    for k, (src, T) in enumerate(zip(sources, T_to_src)):
        w, valid = warp(src, depth[:, 0], Ks, Ks, T)
        pe = photometric_error(w, target)
        reproj.append(torch.where(valid > 0, pe, torch.full_like(pe, _INVALID)))
        if not automask:
            continue
        idt = photometric_error(src, target)
        ident.append(idt + margin + (noise[:, k:k + 1] if noise is not None else 0.0))
    err = torch.cat(ident + reproj, 1).min(dim=1).values
    if automask and mask is None:
        return err.mean()
    # without the identity errors a pixel no source sees keeps _INVALID: it takes no part, and a
    # frame no source sees at all costs 0 (not the NaN of an empty mean)
    seen = err < _INVALID
    if mask is not None:
        seen = seen & (mask[:, 0] > 0)
    return torch.where(seen, err, torch.zeros_like(err)).sum() / seen.sum().clamp_min(1)


def _neighbour_errors(target: Tensor, sources: Tensor, depth: Tensor, Ks: Tensor, T: Tensor,
                      pairs: list[tuple[int, int]]) -> tuple[Tensor, Tensor]:
    """Brightness-normalised photometric error of each (c, n) pair: ``([P,1,H,W] error, [P,1,H,W] valid)``."""
    c = torch.tensor([p[0] for p in pairs], device=depth.device)
    n = torch.tensor([p[1] for p in pairs], device=depth.device)
    w, valid = warp(sources[n], depth[c, 0], Ks[c], Ks[n], T)
    # only pixels whose whole 3x3 SSIM window is valid: in a rig's overlap strip (a few pixels wide
    # at small sizes) the windows that reach the zero-filled outside otherwise dominate the error,
    # and its gradient pushes depth away from the true scale
    valid = -F.max_pool2d(-valid, 3, 1, 1)
    tgt = target[c]
    w = brightness_normalise(w, tgt, valid)
    return photometric_error(w, tgt), valid


def _masked_mean_per_pair(err: Tensor, valid: Tensor, pairs: list[tuple[int, int]], V: int) -> Tensor:
    """Masked mean error per pair, averaged per target camera, then over cameras with a neighbour."""
    per_pair = (err * valid).sum(dim=(1, 2, 3)) / valid.sum(dim=(1, 2, 3)).clamp_min(1.0)
    c = torch.tensor([p[0] for p in pairs], device=err.device)
    per_cam = torch.zeros(V, device=err.device, dtype=err.dtype).index_add(0, c, per_pair)
    cnt = torch.bincount(c, minlength=V).to(err.dtype)
    return (per_cam[cnt > 0] / cnt[cnt > 0]).mean()


def spatial_loss(images: Tensor, depth: Tensor, Ks: Tensor, cam_to_ego: Tensor) -> Tensor:
    """Neighbouring cameras at the same instant warped into each camera through the extrinsics.

    Args:
        images: ``[V, 3, H, W]`` at t; depth ``[V, 1, H, W]``; Ks ``[V, 3, 3]``; cam_to_ego ``[V, 4, 4]``.
    Returns:
        scalar (0 with one camera).
    """
    eye = torch.eye(4, dtype=cam_to_ego.dtype, device=cam_to_ego.device)
    return spatio_temporal_loss(images, [images], depth, Ks, cam_to_ego, [eye])   # one source: no minimum


def spatio_temporal_loss(target: Tensor, sources: list[Tensor], depth: Tensor, Ks: Tensor, cam_to_ego: Tensor,
                         ego_to_src: list[Tensor]) -> Tensor:
    """Neighbouring cameras at t-1 and t+1 warped into each camera at t, minimum over the frames
    (with one source, the frame itself and the identity motion, this is :func:`spatial_loss`).

    Args:
        target: ``[V, 3, H, W]`` at t; sources: images at t-1 and t+1; depth ``[V, 1, H, W]``;
        Ks, cam_to_ego as above; ego_to_src: per source the ego motion ``[4, 4]`` (ego_t -> ego_src).
    Returns:
        scalar (0 with one camera).
    """
    V = target.shape[0]
    pairs = rig_neighbours(cam_to_ego)
    if not pairs:
        return depth.sum() * 0.0
    c = [p[0] for p in pairs]
    n = [p[1] for p in pairs]
    errs, valids = [], []
    for src, M in zip(sources, ego_to_src):
        T = invert_rigid(cam_to_ego[n]) @ M @ cam_to_ego[c]
        err, valid = _neighbour_errors(target, src, depth, Ks, T, pairs)
        errs.append(torch.where(valid > 0, err, torch.full_like(err, _INVALID)))
        valids.append(valid)
    err = torch.cat(errs, 1).min(dim=1, keepdim=True).values
    valid = torch.stack(valids).amax(dim=0)
    return _masked_mean_per_pair(torch.where(valid > 0, err, torch.zeros_like(err)), valid, pairs, V)


def smoothness_loss(depth: Tensor, images: Tensor, order: int = 1) -> Tensor:
    """Edge-aware smoothness of disparity 1/depth (mean-normalised inside the shared function);
    ``order`` 1: first differences (the paper), 2: second differences (zero on planes)."""
    return edge_aware_smoothness(1.0 / depth, images, order)


def render_loss(render: Tensor, target: Tensor, lpips=None, w_lpips: float = 0.05) -> dict[str, Tensor]:
    """MSE (+ ``w_lpips`` LPIPS when an LPIPS module is given).

    Args:
        render, target: ``[B, 3, H, W]`` in [0, 1].
    Returns:
        ``{"render": total, "mse": ..., ["lpips": ...]}`` (no lpips key without weights).
    """
    mse = F.mse_loss(render, target)
    out = {"mse": mse}
    total = mse
    if lpips is not None:
        lp = lpips(render.clamp(0, 1), target).mean()
        out["lpips"] = lp
        total = total + w_lpips * lp
    out["render"] = total
    return out
