"""Dense float64 PyTorch reference of the engine's semantics: the accuracy baseline.

Every stage is written vectorised over all (camera, Gaussian, pixel) triples, with no tiling
shortcuts beyond the tile-membership rule the engine itself applies. It is differentiable
with torch.autograd, so its gradients are the baseline for the backward kernels too.
Memory grows as C * H * W * N: use it on small scenes only.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from . import constants as K
from .config import RenderConfig
from .validate import check_rasterization_inputs

__all__ = ["project", "sh_colors", "composite", "rasterization", "SH_C"]

F64 = torch.float64


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[..., 4] wxyz (any norm) -> [..., 3, 3]."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(*q.shape[:-1], 3, 3)


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
    det_orig = a * d - b * b
    a, d = a + eps2d, d + eps2d
    det = a * d - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([d / det_safe, -b / det_safe, a / det_safe], -1)
    op = opacities[None].expand_as(z)
    if antialiased:
        op = op * (det_orig / det_safe).clamp_min(0).sqrt()
    if cfg.radius_rule == "opacity":
        extent = torch.sqrt(2 * torch.log((op / cfg.alpha_min).clamp_min(1.0)))
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


SH_C = (0.2820947917738781, 0.48860251190292, 1.092548430592079, 0.3153915652525201,
        0.5462742152960395, 2.285228997322329, 0.4570457994644658, 1.445305721320277,
        1.865881662950577, 1.119528997770346, 0.5900435899266435, 0.9461746957575601)


def sh_basis(d: torch.Tensor, degree: int) -> torch.Tensor:
    """[..., 3] unit directions -> [..., (degree+1)^2] real SH basis (gsplat's convention)."""
    x, y, z = d.unbind(-1)
    b = [torch.full_like(x, SH_C[0])]
    if degree >= 1:
        b += [-SH_C[1] * y, SH_C[1] * z, -SH_C[1] * x]
    if degree >= 2:
        z2, c1, s1 = z * z, x * x - y * y, 2 * x * y
        b += [SH_C[4] * s1, -SH_C[2] * z * y, SH_C[11] * z2 - SH_C[3], -SH_C[2] * z * x, SH_C[4] * c1]
    if degree >= 3:
        t0 = -SH_C[5] * z2 + SH_C[6]
        t1 = SH_C[7] * z
        c2, s2 = x * c1 - y * s1, x * s1 + y * c1
        b += [-SH_C[10] * s2, t1 * s1, t0 * y, z * (SH_C[8] * z2 - SH_C[9]), t0 * x, t1 * c1, -SH_C[10] * c2]
    return torch.stack(b, -1)


def sh_colors(coeffs: torch.Tensor, means: torch.Tensor, viewmats: torch.Tensor, degree: int) -> torch.Tensor:
    """coeffs [N,K,3], means [N,3], viewmats [C,4,4] -> colours [C,N,3] = max(SH + 0.5, 0)."""
    R, t = viewmats[:, :3, :3], viewmats[:, :3, 3]
    campos = -(R.transpose(-1, -2) @ t[..., None])[..., 0]              # [C,3]
    d = means[None] - campos[:, None]
    d = d / d.norm(dim=-1, keepdim=True)
    basis = sh_basis(d, degree)                                          # [C,N,B]
    return ((basis[..., None] * coeffs[None, :, : basis.shape[-1]]).sum(-2) + 0.5).clamp_min(0)


def composite(proj: dict, feats: torch.Tensor, width: int, height: int, tile_size: int = 16,
              cfg: RenderConfig = RenderConfig(), margin: float = 0.0):
    """Dense front-to-back compositing with the engine's rules.

    feats [C,N,CH] -> (out [C,H,W,CH], T [C,H,W], ambiguous [C,H,W] bool). A pixel is
    ambiguous when one of its decisions (alpha >= alpha_min, next T <= t_min) lies within a
    relative ``margin`` of its threshold, where a float32 pass may legitimately decide
    otherwise.
    """
    C, N = proj["depths"].shape
    ys, xs = torch.meshgrid(torch.arange(height, dtype=F64), torch.arange(width, dtype=F64), indexing="ij")
    px, py = (xs + K.PIXEL_CENTRE).reshape(-1), (ys + K.PIXEL_CENTRE).reshape(-1)
    tx, ty = (xs.reshape(-1) // tile_size).long(), (ys.reshape(-1) // tile_size).long()
    outs, Ts, ambs = [], [], []
    for c in range(C):
        vis = proj["visible"][c].nonzero()[:, 0]
        if len(vis) == 0:
            outs.append(torch.zeros(height * width, feats.shape[-1], dtype=feats.dtype))
            Ts.append(torch.ones(height * width, dtype=feats.dtype))
            ambs.append(torch.zeros(height * width, dtype=torch.bool))
            continue
        depth32 = proj["depths"][c, vis].detach().to(torch.float32).numpy()
        order = torch.from_numpy(np.lexsort((vis.numpy(), depth32)))   # (float32 depth, id)
        g = vis[order]
        r = proj["rects"][c, g].long()
        inside = ((tx[:, None] >= r[None, :, 0]) & (tx[:, None] < r[None, :, 2]) &
                  (ty[:, None] >= r[None, :, 1]) & (ty[:, None] < r[None, :, 3]))
        xy, co = proj["means2d"][c, g], proj["conics"][c, g]
        dx, dy = xy[None, :, 0] - px[:, None], xy[None, :, 1] - py[:, None]
        sigma = 0.5 * (co[None, :, 0] * dx * dx + co[None, :, 2] * dy * dy) + co[None, :, 1] * dx * dy
        raw = proj["opacities"][c, g][None] * torch.exp(-sigma)
        alpha = raw.clamp_max(K.ALPHA_MAX)
        valid = inside & (sigma >= 0) & (alpha >= cfg.alpha_min)
        a = torch.where(valid, alpha, torch.zeros_like(alpha))
        one_minus = 1 - a
        T_excl = torch.cumprod(torch.cat([torch.ones_like(a[:, :1]), one_minus[:, :-1]], 1), 1)
        next_T = T_excl * one_minus
        stop = valid & (next_T <= cfg.t_min)
        keep = valid & (torch.cumsum(stop.int(), 1) == 0)
        w = torch.where(keep, a * T_excl, torch.zeros_like(a))
        outs.append(w @ feats[c, g])
        Ts.append(torch.where(keep, one_minus, torch.ones_like(a)).prod(1))
        with torch.no_grad():
            live = inside & (torch.cumsum(stop.int(), 1) - stop.int() == 0)  # reached by the pixel
            near_a = live & ((raw - cfg.alpha_min).abs() <= margin * cfg.alpha_min)
            near_t = live & valid & ((next_T - cfg.t_min).abs() <= margin * cfg.t_min)
            ambs.append((near_a | near_t).any(1))
    return (torch.stack(outs).reshape(C, height, width, -1), torch.stack(Ts).reshape(C, height, width),
            torch.stack(ambs).reshape(C, height, width))


def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width: int, height: int,
                  near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0,
                  eps2d: float = K.EPS2D, sh_degree: Optional[int] = None, tile_size: int = 16,
                  backgrounds=None, render_mode: str = "RGB", rasterize_mode: str = "classic",
                  config: RenderConfig = RenderConfig(), margin: float = 0.0, **_ignored):
    """Same arguments and results as :func:`clsplat.rasterization`, computed densely in float64.

    ``meta`` additionally holds ``ambiguous`` [C,H,W]: pixels with a threshold decision within
    relative ``margin`` of flipping (see :func:`composite`).
    """
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
    meta.update({"ambiguous": amb, "width": width, "height": height, "n_cameras": C, "tile_size": tile_size})
    return out, alphas, meta
