"""Float64 PyTorch reference of gsplat's semantics: the accuracy baseline.

It follows gsplat (not clsplat's kernels) wherever the two could differ: covariance from
s^2 (scales of either sign), alpha clamped at ``cfg.alpha_max`` (0.999), the opacity-aware
radius min(3.33, sqrt(2 ln(o / alpha_min))) sigma, the antialiasing compensation with
gsplat's backward floor, the camera centre taken from ``torch.inverse(viewmats)``, SH up to
degree 4, batch dimensions and per-view colours or SH.

Every stage is vectorised over (camera, Gaussian) pairs; compositing takes the Gaussians in
depth-ordered chunks that stop once every pixel is done, and goes tile by tile on large
images, so memory stays bounded. It is differentiable with torch.autograd, so its
gradients are the baseline for the backward kernels too.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from . import constants as K
from .config import RenderConfig
from .quaternion import quat_to_rotmat
from .sh import SH_C, SH_C4, sh_basis  # noqa: F401  (the engine's basis; SH_C re-exported)
from .validate import check_rasterization_inputs

__all__ = ["project", "sh_colors", "composite", "rasterization", "_rasterization", "SH_C"]

F64 = torch.float64


class _Compensation(torch.autograd.Function):
    """sqrt(max(0, det(S) / det(S + eps2d I))) of a 2D covariance S = [[a, b], [b, d]], with
    gsplat's backward: d comp = d(comp^2) * 0.5 / (comp + 1e-6)."""

    @staticmethod
    def forward(ctx, a, b, d, eps2d):
        det = (a + eps2d) * (d + eps2d) - b * b
        det_safe = torch.where(det > 0, det, torch.ones_like(det))
        comp = ((a * d - b * b) / det_safe).clamp_min(0).sqrt()
        ctx.save_for_backward(a, b, d, det_safe, comp)
        ctx.eps2d = eps2d
        return comp

    @staticmethod
    def backward(ctx, g):
        a, b, d, det, comp = ctx.saved_tensors
        eps = ctx.eps2d
        v = g * 0.5 / (comp + 1e-6)
        one_m = 1 - comp * comp
        return (v * (one_m * (d + eps) / det - eps / det), v * 2 * one_m * (-b / det),
                v * (one_m * (a + eps) / det - eps / det), None)


def project(means, quats, scales, opacities, viewmats, Ks, width: int, height: int,
            near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = K.EPS2D,
            radius_clip: float = 0.0, tile_size: int = 16, antialiased: bool = False,
            cfg: RenderConfig = RenderConfig()) -> dict:
    """Project N Gaussians into C cameras.

    means [N,3], quats [N,4], scales [N,3], opacities [N], viewmats [C,4,4], Ks [C,3,3] ->
    dict of means2d [C,N,2], conics [C,N,3], depths [C,N], radii [C,N,2] int32,
    opacities [C,N], rects [C,N,4] int32 (tile rectangle, half-open), visible [C,N] bool.
    """
    R, t = viewmats[:, None, :3, :3], viewmats[:, None, :3, 3]
    p = (R @ means[None, :, :, None])[..., 0] + t                      # [C,N,3]
    z = p[..., 2]
    M = quat_to_rotmat(quats) * scales[:, None, :]                       # [N,3,3]
    V = R @ M[None]                                                      # [C,N,3,3]
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    m = K.FRUSTUM_MARGIN
    zs = torch.where(z > 0, z, torch.ones_like(z))  # culled anyway; keeps the maths finite
    tx = zs * torch.minimum((width - cx) / fx + m * tan_x, torch.maximum(-(cx / fx + m * tan_x), p[..., 0] / zs))
    ty = zs * torch.minimum((height - cy) / fy + m * tan_y, torch.maximum(-(cy / fy + m * tan_y), p[..., 1] / zs))
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs ** 2, zero, fy / zs, -fy * ty / zs ** 2], -1).reshape(*zs.shape, 2, 3)
    T = J @ V
    cov = T @ T.transpose(-1, -2)
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    a, d = a + eps2d, d + eps2d
    det = a * d - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([d / det_safe, -b / det_safe, a / det_safe], -1)
    op = opacities[None].expand_as(z)
    if antialiased:
        op = op * _Compensation.apply(cov[..., 0, 0], b, cov[..., 1, 1], eps2d)
    if cfg.radius_rule == "opacity":
        extent = torch.sqrt(2 * torch.log((op / cfg.alpha_min).clamp_min(1.0))).clamp_max(K.RADIUS_SIGMA)
        ok_op = op >= cfg.alpha_min
    else:
        extent = torch.full_like(op, 4.0 if cfg.radius_rule == "4sigma" else K.RADIUS_SIGMA)
        ok_op = torch.ones_like(op, dtype=torch.bool)
    cap = float(1 << 30)
    with torch.no_grad():
        rx = torch.ceil(extent * a.clamp_min(0).sqrt()).clamp_max(cap)
        ry = torch.ceil(extent * d.clamp_min(0).sqrt()).clamp_max(cap)
    xy = torch.stack([fx * p[..., 0] / zs + cx, fy * p[..., 1] / zs + cy], -1)
    with torch.no_grad():
        vis = (z >= near_plane) & (z <= far_plane) & (det > 0) & ok_op
        vis &= ~((rx <= radius_clip) & (ry <= radius_clip))
        vis &= (xy[..., 0] + rx > 0) & (xy[..., 0] - rx < width) & (xy[..., 1] + ry > 0) & (xy[..., 1] - ry < height)
        txs, tys = -(-width // tile_size), -(-height // tile_size)
        gx, gy = xy[..., 0] / tile_size, xy[..., 1] / tile_size
        rtx, rty = rx / tile_size, ry / tile_size
        rects = torch.stack([
            torch.floor(gx - rtx).clamp(0, txs), torch.floor(gy - rty).clamp(0, tys),
            torch.ceil(gx + rtx).clamp(0, txs), torch.ceil(gy + rty).clamp(0, tys)], -1).to(torch.int32)
        vis &= (rects[..., 2] > rects[..., 0]) & (rects[..., 3] > rects[..., 1])
        rects = torch.where(vis[..., None], rects, torch.zeros_like(rects))
        radii = torch.where(vis[..., None], torch.stack([rx, ry], -1), torch.zeros_like(xy)).to(torch.int32)
    v3 = vis[..., None]
    return {"means2d": torch.where(v3, xy, 0 * xy), "conics": torch.where(v3, conics, 0 * conics),
            "depths": z, "radii": radii, "opacities": torch.where(vis, op, 0 * op),
            "rects": rects, "visible": vis}


def camera_centres(viewmats: torch.Tensor) -> torch.Tensor:
    """[..., 4, 4] world-to-camera -> [..., 3] centres, through torch.inverse as gsplat does."""
    return torch.inverse(viewmats)[..., :3, 3]


def sh_colors(coeffs: torch.Tensor, means: torch.Tensor, viewmats: torch.Tensor, degree: int) -> torch.Tensor:
    """coeffs [N,K,3] or per view [C,N,K,3], means [N,3], viewmats [C,4,4] -> colours [C,N,3]
    = max(SH(normalise(mean - centre)) + 0.5, 0)."""
    d = means[None] - camera_centres(viewmats)[:, None]
    d = d / d.norm(dim=-1, keepdim=True)
    basis = sh_basis(d, degree)                                          # [C,N,B]
    k = coeffs if coeffs.dim() == 4 else coeffs[None]
    return ((basis[..., None] * k[..., : basis.shape[-1], :]).sum(-2) + 0.5).clamp_min(0)


def composite(proj: dict, feats: torch.Tensor, width: int, height: int, tile_size: int = 16,
              cfg: RenderConfig = RenderConfig(), margin: float = 0.0, chunk: int = 256,
              dense_limit: int = 1 << 22):
    """Front-to-back compositing with gsplat's rules.

    feats [C,N,CH] -> (out [C,H,W,CH], T [C,H,W], ambiguous [C,H,W] bool). A pixel is
    ambiguous when one of its decisions (alpha >= alpha_min, next T <= t_min) lies within a
    relative ``margin`` of its threshold, where a float32 pass may legitimately decide
    otherwise. A sample reaches a pixel only if its tile rectangle holds the pixel's tile.
    Gaussians are taken in (float32 depth, id) order, 32 at first and doubling to ``chunk``
    at a time (early stop after few samples stays cheap); a camera whose
    pixels x visible Gaussians exceed ``dense_limit`` is done tile by tile.
    """
    C = proj["depths"].shape[0]
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    outs, Ts, ambs = [], [], []
    for c in range(C):
        vis = proj["visible"][c].nonzero()[:, 0]
        depth32 = proj["depths"][c, vis].detach().to(torch.float32).numpy()
        g = vis[torch.from_numpy(np.lexsort((vis.numpy(), depth32)))]   # (float32 depth, id)
        if height * width * max(1, len(g)) <= dense_limit:
            o, T, a = _composite_pixels(proj, c, g, feats, xs.reshape(-1), ys.reshape(-1),
                                        tile_size, cfg, margin, chunk)
            outs.append(o.reshape(height, width, -1))
            Ts.append(T.reshape(height, width))
            ambs.append(a.reshape(height, width))
            continue
        r = proj["rects"][c, g].long()
        rows_o, rows_T, amb = [], [], torch.zeros((height, width), dtype=torch.bool)
        for y0 in range(0, height, tile_size):
            row_o, row_T = [], []
            for x0 in range(0, width, tile_size):
                tx, ty = x0 // tile_size, y0 // tile_size
                gt = g[(r[:, 0] <= tx) & (r[:, 2] > tx) & (r[:, 1] <= ty) & (r[:, 3] > ty)]
                yy, xx = ys[y0:y0 + tile_size, x0:x0 + tile_size], xs[y0:y0 + tile_size, x0:x0 + tile_size]
                o, T, a = _composite_pixels(proj, c, gt, feats, xx.reshape(-1), yy.reshape(-1),
                                            tile_size, cfg, margin, chunk)
                row_o.append(o.reshape(*xx.shape, -1))
                row_T.append(T.reshape(xx.shape))
                amb[y0:y0 + tile_size, x0:x0 + tile_size] = a.reshape(xx.shape)
            rows_o.append(torch.cat(row_o, 1))
            rows_T.append(torch.cat(row_T, 1))
        outs.append(torch.cat(rows_o, 0))
        Ts.append(torch.cat(rows_T, 0))
        ambs.append(amb)
    if not C:
        return (feats.new_zeros((0, height, width, feats.shape[-1])), feats.new_ones((0, height, width)),
                torch.zeros((0, height, width), dtype=torch.bool))
    return torch.stack(outs), torch.stack(Ts), torch.stack(ambs)


def _composite_pixels(proj: dict, c: int, g: torch.Tensor, feats: torch.Tensor, xs: torch.Tensor,
                      ys: torch.Tensor, tile_size: int, cfg: RenderConfig, margin: float, chunk: int):
    """Pixels (xs, ys) [P] of camera c over the depth-ordered Gaussians ``g`` ->
    (out [P,CH], T [P], ambiguous [P])."""
    px, py = xs.to(F64) + K.PIXEL_CENTRE, ys.to(F64) + K.PIXEL_CENTRE
    tx, ty = (xs // tile_size)[:, None], (ys // tile_size)[:, None]
    P = px.numel()
    out = feats.new_zeros((P, feats.shape[-1]))
    T = feats.new_ones((P,))
    done = torch.zeros(P, dtype=torch.bool)
    amb = torch.zeros(P, dtype=torch.bool)
    s, size = 0, min(32, chunk)  # most pixels of dense scenes stop within a few dozen samples
    while s < len(g):
        gi = g[s:s + size]
        s, size = s + size, min(2 * size, chunk)
        r = proj["rects"][c, gi].long()
        inside = (tx >= r[None, :, 0]) & (tx < r[None, :, 2]) & (ty >= r[None, :, 1]) & (ty < r[None, :, 3])
        xy, co = proj["means2d"][c, gi], proj["conics"][c, gi]
        dx, dy = xy[None, :, 0] - px[:, None], xy[None, :, 1] - py[:, None]
        sigma = 0.5 * (co[None, :, 0] * dx * dx + co[None, :, 2] * dy * dy) + co[None, :, 1] * dx * dy
        # beyond sigma = 200 alpha is ~1e-87, far below alpha_min: clamping keeps exp() out of
        # the (slow) denormal range and changes no decision
        raw = proj["opacities"][c, gi][None] * torch.exp(-sigma.clamp_max(200.0))
        alpha = raw.clamp_max(cfg.alpha_max)
        live_px = inside & ~done[:, None]
        valid = live_px & (sigma >= 0) & (alpha >= cfg.alpha_min)
        a = torch.where(valid, alpha, torch.zeros_like(alpha))
        one_minus = 1 - a
        T_excl = T[:, None] * torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), one_minus[:, :-1]], 1), 1)
        next_T = T_excl * one_minus
        stop = valid & (next_T <= cfg.t_min)
        before = torch.cumsum(stop.int(), 1)
        keep = valid & (before == 0)
        out = out + torch.where(keep, a * T_excl, torch.zeros_like(a)) @ feats[c, gi]
        T = T * torch.where(keep, one_minus, torch.ones_like(a)).prod(1)
        with torch.no_grad():
            live = live_px & (before - stop.int() == 0)  # samples the pixel reaches
            near_a = live & ((raw - cfg.alpha_min).abs() <= margin * cfg.alpha_min)
            near_t = live & valid & ((next_T - cfg.t_min).abs() <= margin * cfg.t_min)
            amb |= (near_a | near_t).any(1)
            done = done | stop.any(1)
        if bool(done.all()):
            break
    return out, T, amb


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width: int, height: int,
                  near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0,
                  eps2d: float = K.EPS2D, sh_degree: Optional[int] = None, packed: bool = True,
                  tile_size: Optional[int] = None, backgrounds=None, render_mode: str = "RGB",
                  sparse_grad: bool = False, absgrad: bool = False,
                  rasterize_mode: str = "classic", config: RenderConfig = RenderConfig(),
                  margin: float = 0.0, **_ignored):
    """Same arguments and images as :func:`clsplat.rasterization`, computed in float64.

    Batch dimensions: means [..., N, 3] with viewmats [..., C, 4, 4] and colours
    [..., (C,) N, D] or [..., (C,) N, K, 3]. ``packed``, ``sparse_grad`` and ``absgrad`` do not
    change images and are ignored. ``meta`` holds the unpacked per-pair tensors
    ([..., C, N, ...]) and ``ambiguous`` [..., C, H, W]: pixels with a threshold decision
    within relative ``margin`` of flipping (see :func:`composite`).
    """
    tile_size = 16 if tile_size is None else tile_size
    batch = tuple(means.shape[:-2])
    B = int(np.prod(batch)) if batch else 1
    flat = lambda x: None if x is None else x.reshape((B,) + tuple(x.shape[len(batch):]))  # noqa: E731
    args = [flat(x) for x in (means, quats, scales, opacities, colors, viewmats, Ks)]
    bgs = flat(backgrounds)
    outs = [_render_one(*(x[b] for x in args), width, height, near_plane, far_plane, radius_clip,
                        eps2d, sh_degree, tile_size, None if bgs is None else bgs[b], render_mode,
                        rasterize_mode, config, margin) for b in range(B)]
    # Without batch dimensions, meta holds the graph's own nodes (means2d accepts retain_grad()).
    unflat = (lambda xs: xs[0]) if not batch else (  # noqa: E731
        lambda xs: torch.stack(xs).reshape(batch + tuple(xs[0].shape)))
    img = unflat([o[0] for o in outs])
    alphas = unflat([o[1] for o in outs])
    meta = {k: unflat([o[2][k] for o in outs])
            for k in ("means2d", "conics", "depths", "radii", "opacities", "ambiguous")}
    meta.update({"width": width, "height": height, "n_cameras": viewmats.shape[-3],
                 "n_batches": B, "tile_size": tile_size})
    return img, alphas, meta


def _rasterization(*args, **kwargs):
    """:func:`rasterization` with results in the dtype of ``means``: a stand-in for gsplat's
    ``gsplat.rendering._rasterization`` in gsplat's own tests."""
    means = kwargs["means"] if "means" in kwargs else args[0]
    img, alphas, meta = rasterization(*args, **kwargs)
    return img.to(means.dtype), alphas.to(means.dtype), meta


def _render_one(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane,
                far_plane, radius_clip, eps2d, sh_degree, tile_size, backgrounds, render_mode,
                rasterize_mode, config, margin):
    """One batch element: means [N,3], viewmats [C,4,4] -> (image, alphas, meta)."""
    check_rasterization_inputs(means, quats, scales, opacities, colors, viewmats, Ks, width,
                               height, near_plane, far_plane, radius_clip, eps2d, sh_degree,
                               tile_size, backgrounds, render_mode)
    f = lambda x: x.to(F64)  # noqa: E731
    means, quats, scales, opacities, colors, viewmats, Ks = map(f, (means, quats, scales, opacities, colors, viewmats, Ks))
    C, N = viewmats.shape[0], means.shape[0]
    proj = project(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane,
                   far_plane, eps2d, radius_clip, tile_size, rasterize_mode == "antialiased", config)
    if sh_degree is not None:
        cols = sh_colors(colors, means, viewmats, sh_degree)
    else:
        cols = colors.expand(C, N, colors.shape[-1]) if colors.dim() == 2 else colors
    depth = proj["depths"][..., None]
    feats = {"RGB": cols, "D": depth, "ED": depth}.get(render_mode)
    if feats is None:
        feats = torch.cat([cols, depth], -1)
    out, T, amb = composite(proj, feats, width, height, tile_size, config, margin)
    alphas = (1 - T)[..., None]
    n_col = 0 if render_mode in ("D", "ED") else cols.shape[-1]
    if backgrounds is not None and n_col:
        out = torch.cat([out[..., :n_col] + T[..., None] * f(backgrounds)[:, None, None], out[..., n_col:]], -1)
    if render_mode in ("ED", "RGB+ED"):
        out = torch.cat([out[..., :-1], out[..., -1:] / alphas.clamp_min(1e-10)], -1)
    meta = {k: proj[k] for k in ("means2d", "conics", "depths", "radii", "opacities")}
    meta["ambiguous"] = amb
    return out, alphas, meta
