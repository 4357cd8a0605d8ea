"""The front door: :func:`rasterization`, gsplat's interface on the OpenCL engine.

It validates input, chooses the channels to composite (colour, depth or both, by render
mode), runs the stage drivers of :mod:`clsplat.stages` and assembles gsplat's return values.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from . import stages
from .config import RenderConfig
from .runtime import DeviceArray, Runtime, get_runtime
from .validate import check_rasterization_inputs

__all__ = ["rasterization", "ForwardState", "forward_pipeline"]


@dataclass
class ForwardState:
    """What a forward pass leaves on the device for the backward pass and for ``meta``."""

    rt: Runtime
    cfg: RenderConfig
    proj: stages.Projection
    feats: DeviceArray
    offsets: DeviceArray
    keys: DeviceArray
    out_feats: DeviceArray
    out_T: DeviceArray
    last: Optional[DeviceArray]
    tile_size: int
    width: int
    height: int


def _channels(render_mode: str, D: int) -> tuple[int, int]:
    """(colour channels, depth column or -1) composited for a render mode."""
    if render_mode in ("D", "ED"):
        return 0, 0
    if render_mode in ("RGB+D", "RGB+ED"):
        return D, D
    return D, -1


def forward_pipeline(rt: Runtime, cfg: RenderConfig, means, quats, scales, opacities, colors,
                     viewmats, Ks, width: int, height: int, *, near_plane: float, far_plane: float,
                     radius_clip: float, eps2d: float, sh_degree: Optional[int], tile_size: int,
                     render_mode: str, antialiased: bool, save_last: bool,
                     events: list | None = None) -> ForwardState:
    """Run project, sh, bin, sort and composite on validated tensors of dtype ``cfg.dtype``.

    colors: [N,D] or [C,N,D], or SH [N,K,3] when ``sh_degree`` is set.
    Returns the :class:`ForwardState`; ``out_feats`` is [C,H,W,CH] with the colour channels
    first and the depth column (if the mode has one) last, without background.
    """
    C, N = viewmats.shape[0], means.shape[0]
    D = 3 if sh_degree is not None else colors.shape[-1]
    n_col, depth_col = _channels(render_mode, D)
    CH = n_col + (depth_col >= 0)
    feats_t = torch.zeros((C, N, CH), dtype=cfg.dtype)
    if n_col and sh_degree is None:
        feats_t[..., :n_col] = colors
    feats = rt.array(feats_t)
    arr = rt.array
    means_a, viewmats_a = arr(means), arr(viewmats)
    proj = stages.project(rt, cfg, means_a, arr(quats), arr(scales), arr(opacities), viewmats_a,
                          arr(Ks), width, height, tile_size, near_plane=near_plane,
                          far_plane=far_plane, eps2d=eps2d, radius_clip=radius_clip,
                          antialiased=antialiased, feats=feats, depth_channel=depth_col,
                          channels=CH, events=events)
    if n_col and sh_degree is not None:
        stages.sh_colors(rt, cfg, means_a, viewmats_a, arr(colors), proj.radii, feats, sh_degree,
                         CH, events=events)
    offsets, keys = stages.bin_tiles(rt, cfg, proj, width, height, tile_size, events=events)
    stages.sort_segments(rt, cfg, keys, offsets, events=events)
    out, T, last = stages.composite(rt, cfg, proj, feats, offsets, keys, width, height, tile_size,
                                    save_last, events=events)
    return ForwardState(rt, cfg, proj, feats, offsets, keys, out, T, last, tile_size, width, height)


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
    if precision is None:
        precision = config.precision if config is not None else (
            "float64" if means.dtype == torch.float64 else "float32")
    cfg = (config or RenderConfig()).with_(precision=precision)
    rt = get_runtime(device)
    if cfg.precision == "float64" and not rt.has_fp64:
        raise ValueError(f"precision: float64 needs cl_khr_fp64, which {rt.name} lacks")
    C, N, D = info["C"], info["N"], info["D"]
    n_col, depth_col = _channels(render_mode, D)
    CH = n_col + (depth_col >= 0)
    nbytes = C * height * width * CH * (8 if cfg.precision == "float64" else 4)
    if nbytes > rt.device.max_mem_alloc_size:
        raise ValueError(f"width, height: a {C}x{height}x{width}x{CH} image needs {nbytes >> 20} MiB, "
                         f"over the device's {rt.device.max_mem_alloc_size >> 20} MiB allocation limit")

    dt = cfg.dtype
    cast = lambda x: x.detach().to(dt).contiguous()  # noqa: E731  (autograd arrives in the Function)
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    if N == 0:
        render = torch.zeros((C, height, width, CH), dtype=dt)
        T = torch.ones((C, height, width), dtype=dt)
        meta_extra = {"isect_offsets": torch.zeros((C, tiles_y, tiles_x), dtype=torch.int32),
                      "flatten_ids": torch.zeros((0,), dtype=torch.int32)}
        proj_t = {"means2d": torch.zeros((C, 0, 2), dtype=dt), "radii": torch.zeros((C, 0, 2), dtype=torch.int32),
                  "depths": torch.zeros((C, 0), dtype=dt), "conics": torch.zeros((C, 0, 3), dtype=dt),
                  "opacities": torch.zeros((C, 0), dtype=dt), "rects": torch.zeros((C, 0, 4), dtype=torch.int32)}
    else:
        st = forward_pipeline(rt, cfg, cast(means), cast(quats), cast(scales), cast(opacities),
                              cast(colors), cast(viewmats), cast(Ks), width, height,
                              near_plane=near_plane, far_plane=far_plane, radius_clip=radius_clip,
                              eps2d=eps2d, sh_degree=sh_degree, tile_size=tile_size,
                              render_mode=render_mode, antialiased=rasterize_mode == "antialiased",
                              save_last=False)
        render, T = st.out_feats.host().clone(), st.out_T.host()
        keys = st.keys.host()
        meta_extra = {"isect_offsets": st.offsets.host()[:-1].reshape(C, tiles_y, tiles_x).clone(),
                      "flatten_ids": (keys & 0xFFFFFFFF).to(torch.int32)}
        p = st.proj
        proj_t = {k: getattr(p, k).host() for k in ("means2d", "radii", "depths", "conics", "opacities", "rects")}

    alphas = (1 - T).unsqueeze(-1)
    if backgrounds is not None and n_col:
        render[..., :n_col] += T.unsqueeze(-1) * backgrounds.detach().to(dt)[:, None, None, :]
    if render_mode in ("ED", "RGB+ED"):
        render[..., -1:] = render[..., -1:] / alphas.clamp_min(1e-10)
    rects = proj_t.pop("rects")
    meta = dict(proj_t)
    meta.update(meta_extra)
    meta.update({
        "tiles_per_gauss": ((rects[..., 2] - rects[..., 0]) * (rects[..., 3] - rects[..., 1])).to(torch.int32),
        "tile_width": tiles_x, "tile_height": tiles_y, "tile_size": tile_size,
        "width": width, "height": height, "n_cameras": C,
        "gaussian_ids": None, "camera_ids": None,
    })
    out_dt = means.dtype
    return render.to(out_dt), alphas.to(out_dt), meta
