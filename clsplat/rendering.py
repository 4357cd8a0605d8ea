"""The front door: :func:`rasterization`, gsplat's interface on the OpenCL engine.

It validates input, chooses the channels to composite (colour, depth or both, by render
mode), chains the autograd Functions of :mod:`clsplat.autograd` (project, SH, rasterize;
each runs the stage drivers of :mod:`clsplat.stages`), adds the background and assembles
gsplat's return values.
"""
from __future__ import annotations

from typing import Optional

import torch

from .autograd import ProjectFn, RasterizeFn, Settings, ShFn
from .config import RenderConfig
from .runtime import Runtime, get_runtime
from .validate import check_options, check_rasterization_inputs, check_screen_extent, rescale_large_quats

__all__ = ["rasterization"]


def _channels(render_mode: str, D: int) -> tuple[int, int]:
    """(colour channels, depth column or -1) composited for a render mode."""
    if render_mode in ("D", "ED"):
        return 0, 0
    if render_mode in ("RGB+D", "RGB+ED"):
        return D, D
    return D, -1


def rasterization(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                  opacities: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor,
                  Ks: torch.Tensor, width: int, height: int, near_plane: float = 0.01,
                  far_plane: float = 1e10, radius_clip: float = 0.0, eps2d: float = 0.3,
                  sh_degree: Optional[int] = None, packed: bool = True, tile_size: int = 16,
                  backgrounds: Optional[torch.Tensor] = None, render_mode: str = "RGB",
                  sparse_grad: bool = False, absgrad: bool = False,
                  rasterize_mode: str = "classic", channel_chunk: int = 32,
                  distributed: bool = False, camera_model: str = "pinhole",
                  covars: Optional[torch.Tensor] = None, *, device: str | Runtime | None = None,
                  precision: Optional[str] = None, config: Optional[RenderConfig] = None,
                  bwd_divide: bool = False, events: Optional[list] = None,
                  ) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Rasterise 3D Gaussians into C images, with gsplat's arguments and return values.

    Args:
        means: [N, 3] centres in world space.
        quats: [N, 4] rotations, wxyz, need not be normalised.
        scales: [N, 3] post-activation scales.
        opacities: [N] post-activation opacities in [0, 1].
        colors: [N, D] or [C, N, D] features, or SH coefficients [N, K, 3] with ``sh_degree``.
        viewmats: [C, 4, 4] world-to-camera matrices (OpenCV: x right, y down, z forward).
        Ks: [C, 3, 3] pinhole intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: Gaussians with camera depth outside [near, far] are culled.
        radius_clip: Gaussians whose screen radius is <= this (pixels) are culled.
        eps2d: added to the diagonal of every 2D covariance.
        sh_degree: SH degree to evaluate (0-3), or None when ``colors`` are plain features.
        packed, sparse_grad, channel_chunk: accepted for gsplat compatibility; ``meta`` always
            has gsplat's unpacked layout and the images are the same either way.
        tile_size: tile side in pixels (4, 8, 16 or 32).
        backgrounds: [C, D] colour behind the Gaussians (colour channels only).
        render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED"; D is accumulated camera depth,
            ED is D divided by alpha.
        rasterize_mode: "classic" or "antialiased" (opacity scaled by the eps2d compensation).
        device: OpenCL device (see :mod:`clsplat.runtime`), default ``CLSPLAT_DEVICE``.
        precision: "float32" or "float64"; default: float64 for float64 means, else float32.
        config: accuracy knobs (:class:`RenderConfig`); ``precision`` overrides its precision.
        absgrad: after backward, ``meta["means2d"].absgrad`` holds the per-pair sum of
            absolute screen-space gradients (gsplat's densification criterion).
        bwd_divide: recover transmittance in backward by division instead of forward replay
            (see kernels/composite_bwd.cl for the trade-off).
        events: a list that receives ``(stage, pyopencl.Event)`` for every kernel launched,
            forward and (later) backward, for profiling.

    Differentiable with respect to means, quats, scales, opacities, colors (or SH),
    backgrounds and viewmats; ``meta["means2d"]`` accepts ``retain_grad()``.

    Returns:
        render_colors [C, H, W, X] (X = D, 1 or D+1 by mode), render_alphas [C, H, W, 1], and
        ``meta`` with means2d [C,N,2], radii [C,N,2], depths [C,N], conics [C,N,3],
        opacities [C,N], tiles_per_gauss [C,N], isect_offsets [C,th,tw], flatten_ids [M],
        tile_width, tile_height, tile_size, width, height, n_cameras. Outputs have the dtype
        of ``means``.
    """
    info = check_rasterization_inputs(means, quats, scales, opacities, colors, viewmats, Ks,
                                      width, height, near_plane, far_plane, radius_clip, eps2d,
                                      sh_degree, tile_size, backgrounds, render_mode)
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode: expected 'classic' or 'antialiased', got {rasterize_mode!r}")
    if camera_model != "pinhole":
        raise ValueError(f"camera_model: only 'pinhole' is supported, got {camera_model!r}")
    if covars is not None:
        raise ValueError("covars: explicit covariances are not supported; pass quats and scales")
    if distributed:
        raise ValueError("distributed: multi-process rendering is not supported")
    check_options(config, events)
    if precision is None:
        precision = (config.precision if config is not None else None) or (
            "float64" if means.dtype == torch.float64 else "float32")
    cfg = (config or RenderConfig()).with_(precision=precision)
    rt = get_runtime(device)
    if cfg.precision == "float64" and not rt.has_fp64:
        raise ValueError(f"precision: float64 needs cl_khr_fp64, which {rt.name} lacks")
    quats = rescale_large_quats(quats)
    check_screen_extent(means, scales, viewmats, Ks, float(near_plane), float(far_plane), cfg.precision)
    C, N, D = info["C"], info["N"], info["D"]
    n_col, depth_col = _channels(render_mode, D)
    CH = n_col + (depth_col >= 0)
    nbytes = C * height * width * CH * (8 if cfg.precision == "float64" else 4)
    if nbytes > rt.device.max_mem_alloc_size:
        raise ValueError(f"width, height: a {C}x{height}x{width}x{CH} image needs {nbytes >> 20} MiB, "
                         f"over the device's {rt.device.max_mem_alloc_size >> 20} MiB allocation limit")

    dt = cfg.dtype
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    st = Settings(rt, cfg, width, height, tile_size, float(near_plane), float(far_plane),
                  float(eps2d), float(radius_clip), rasterize_mode == "antialiased",
                  absgrad=absgrad, sh_degree=sh_degree, bwd_divide=bwd_divide, events=events)
    cast = lambda x: x.to(dt).contiguous()  # noqa: E731  (differentiable: grads come back cast)
    means_r, viewmats_r = cast(means), cast(viewmats)
    means2d, conics, depths, opac, radii, rects, extents = ProjectFn.apply(
        means_r, cast(quats), cast(scales), cast(opacities), viewmats_r, cast(Ks).detach(), st)
    parts = []
    if n_col:
        if sh_degree is not None:
            parts.append(ShFn.apply(cast(colors), means_r, viewmats_r, radii, st))
        else:
            c = cast(colors)
            parts.append(c.expand(C, N, D) if c.dim() == 2 else c)
    if depth_col >= 0:
        parts.append(depths[..., None])
    feats = parts[0] if len(parts) == 1 else torch.cat(parts, -1)
    if N == 0:
        render = torch.zeros((C, height, width, CH), dtype=dt)
        T = torch.ones((C, height, width), dtype=dt)
        isect_offsets = torch.zeros((C * tiles_y * tiles_x + 1,), dtype=torch.int32)
        keys = torch.zeros((0,), dtype=torch.int64)
    else:
        render, T = RasterizeFn.apply(means2d, conics, opac, feats.contiguous(), rects, extents,
                                      depths.detach(), st)
        isect_offsets, keys = st.isect

    alphas = (1 - T).unsqueeze(-1)
    if backgrounds is not None and n_col:
        bg = cast(backgrounds)[:, None, None, :]
        render = torch.cat([render[..., :n_col] + T.unsqueeze(-1) * bg, render[..., n_col:]], -1)
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp_min(1e-10)], -1)
    meta = {
        "means2d": means2d, "radii": radii, "depths": depths, "conics": conics, "opacities": opac,
        "tiles_per_gauss": ((rects[..., 2] - rects[..., 0]) * (rects[..., 3] - rects[..., 1])).to(torch.int32),
        "isect_offsets": isect_offsets[:-1].reshape(C, tiles_y, tiles_x),
        "flatten_ids": (keys & 0xFFFFFFFF).to(torch.int32),
        "tile_width": tiles_x, "tile_height": tiles_y, "tile_size": tile_size,
        "width": width, "height": height, "n_cameras": C,
        "gaussian_ids": None, "camera_ids": None,
    }
    out_dt = means.dtype
    return render.to(out_dt), alphas.to(out_dt), meta
