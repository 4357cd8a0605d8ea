"""The front door: :func:`rasterization`, gsplat's interface on the OpenCL engine.

It takes gsplat 1.6's arguments in gsplat's order, checks them, moves tensors from any torch
device to the host, splits leading batch dimensions into independent renders, chains the
autograd Functions of :mod:`clsplat.autograd` (project, SH, rasterize; each runs the stage
drivers of :mod:`clsplat.stages`) per batch element, adds the background, and assembles
gsplat's return values (packed or unpacked ``meta``, via :mod:`clsplat.packed`) on the
inputs' device and dtype.
"""
from __future__ import annotations

import math
from dataclasses import replace
from enum import Enum
from typing import Optional

import torch

from .autograd import ProjectFn, RasterizeFn, Settings, ShFn
from .config import RenderConfig
from .packed import AbsgradSink, LazyMeta, PackedMeans2d, SparseRowsGrad, intersection_meta, pack_pairs
from .plan import check_pixel_memory, pixel_plan
from .runtime import Runtime, get_runtime
from .validate import check_options, check_rasterization_inputs, check_screen_extent, rescale_large_quats

__all__ = ["rasterization", "RollingShutterType", "DEFAULT_TILE_SIZE"]

DEFAULT_TILE_SIZE = 16  # what gsplat uses for tile_size=None
#: the default config per precision, made once (immutable): no RenderConfig is made and checked
#: per call without a config
_DEFAULT_CONFIGS = {p: RenderConfig(precision=p) for p in ("float32", "float64")}


class RollingShutterType(Enum):
    """gsplat's shutter types (same names and values); clsplat renders GLOBAL only."""

    ROLLING_TOP_TO_BOTTOM = 0
    ROLLING_LEFT_TO_RIGHT = 1
    ROLLING_BOTTOM_TO_TOP = 2
    ROLLING_RIGHT_TO_LEFT = 3
    GLOBAL = 4


def _channels(render_mode: str, D: int) -> tuple[int, int]:
    """(colour channels, depth column or -1) composited for a render mode."""
    if render_mode in ("D", "ED"):
        return 0, 0
    if render_mode in ("RGB+D", "RGB+ED"):
        return D, D
    return D, -1


def _check_not_implemented(distributed, camera_model, covars, with_ut, with_eval3d,
                           radial_coeffs, tangential_coeffs, thin_prism_coeffs, ftheta_coeffs,
                           rolling_shutter, viewmats_rs) -> None:
    """gsplat features clsplat does not implement are accepted only at gsplat's defaults."""
    if distributed is not False:
        raise ValueError(f"distributed: multi-process rendering is not implemented; only "
                         f"distributed=False is accepted, got {distributed!r}")
    if camera_model != "pinhole":
        raise ValueError(f"camera_model: only 'pinhole' is implemented ('ortho', 'fisheye' and "
                         f"'ftheta' are not), got {camera_model!r}")
    if covars is not None:
        raise ValueError("covars: explicit covariances are not implemented; pass quats and scales")
    for name, v in (("with_ut", with_ut), ("with_eval3d", with_eval3d)):
        if v is not False:
            raise ValueError(f"{name}: the unscented transform / 3D evaluation is not "
                             f"implemented; only {name}=False is accepted, got {v!r}")
    for name, v in (("radial_coeffs", radial_coeffs), ("tangential_coeffs", tangential_coeffs),
                    ("thin_prism_coeffs", thin_prism_coeffs), ("ftheta_coeffs", ftheta_coeffs),
                    ("viewmats_rs", viewmats_rs)):
        if v is not None:
            raise ValueError(f"{name}: lens distortion and rolling shutter are not implemented; "
                             "only None is accepted")
    if rolling_shutter is not None and getattr(rolling_shutter, "name", rolling_shutter) != "GLOBAL":
        raise ValueError(f"rolling_shutter: only RollingShutterType.GLOBAL is implemented, got "
                         f"{rolling_shutter!r}")


def _host(name: str, x):
    """A torch tensor on any device -> the same values on the CPU (differentiably)."""
    if not isinstance(x, torch.Tensor) or x.device.type == "cpu":
        return x
    if x.device.type == "meta":
        raise ValueError(f"{name}: a tensor on the 'meta' device holds no data")
    return x.to("cpu")


def _check_batch(batch: tuple, **tensors) -> None:
    """Each tensor's leading dimensions must be the batch dimensions of ``means``."""
    nb = len(batch)
    for name, x in tensors.items():
        if x is None and name == "backgrounds":
            continue
        if not isinstance(x, torch.Tensor):
            raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
        if x.layout != torch.strided:
            raise ValueError(f"{name}: expected a dense (strided) tensor, got layout {x.layout}; "
                             "call .to_dense() first")
        if tuple(x.shape[:nb]) != batch or x.dim() <= nb:
            raise ValueError(f"{name}: expected the batch dimensions {list(batch)} of means "
                             f"[..., N, 3] in front, got shape {list(x.shape)}")


def rasterization(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                  opacities: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor,
                  Ks: torch.Tensor, width: int, height: int, near_plane: float = 0.01,
                  far_plane: float = 1e10, radius_clip: float = 0.0, eps2d: float = 0.3,
                  sh_degree: Optional[int] = None, packed: bool = True,
                  tile_size: Optional[int] = None, backgrounds: Optional[torch.Tensor] = None,
                  render_mode: str = "RGB", sparse_grad: bool = False, absgrad: bool = False,
                  rasterize_mode: str = "classic", channel_chunk: int = 32,
                  distributed: bool = False, camera_model: str = "pinhole",
                  segmented: bool = False, covars: Optional[torch.Tensor] = None,
                  with_ut: bool = False, with_eval3d: bool = False,
                  radial_coeffs: Optional[torch.Tensor] = None,
                  tangential_coeffs: Optional[torch.Tensor] = None,
                  thin_prism_coeffs: Optional[torch.Tensor] = None,
                  ftheta_coeffs=None, rolling_shutter=RollingShutterType.GLOBAL,
                  viewmats_rs: Optional[torch.Tensor] = None, *,
                  device: str | Runtime | None = None, precision: Optional[str] = None,
                  config: Optional[RenderConfig] = None, bwd_divide: bool = False,
                  events: Optional[list] = None,
                  ) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Rasterise 3D Gaussians into images, with gsplat's arguments and return values.

    Args:
        means: [..., N, 3] centres in world space; ``...`` are batch dimensions.
        quats: [..., N, 4] rotations, wxyz, need not be normalised.
        scales: [..., N, 3] post-activation scales of either sign (the covariance uses s^2).
        opacities: [..., N] post-activation opacities in [0, 1].
        colors: [..., N, D] or [..., C, N, D] features, or SH coefficients [..., N, K, 3] or
            [..., C, N, K, 3] with ``sh_degree``.
        viewmats: [..., C, 4, 4] world-to-camera matrices (OpenCV: x right, y down, z forward).
        Ks: [..., C, 3, 3] pinhole intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: Gaussians with camera depth outside [near, far] are culled.
        radius_clip: Gaussians whose screen radius is <= this (pixels) are culled.
        eps2d: added to the diagonal of every 2D covariance.
        sh_degree: SH degree to evaluate (0-4), or None when ``colors`` are plain features.
        packed: True: per-pair ``meta`` entries are packed [nnz, ...] over the visible
            (camera, Gaussian) pairs, with ``batch_ids``, ``camera_ids``, ``gaussian_ids``;
            False: [..., C, N, ...]. Images are the same either way.
        tile_size: tile side in pixels (4, 8, 16 or 32); None: 16.
        backgrounds: [..., C, D] colour behind the Gaussians (colour channels only).
        render_mode: "RGB", "D", "ED", "RGB+D" or "RGB+ED"; D is accumulated camera depth,
            ED is D divided by alpha.
        sparse_grad: with ``packed`` and no batch dimensions, the gradients of means, quats
            and scales are sparse COO tensors over the Gaussians visible in some camera.
        absgrad: after backward, ``meta["means2d"].absgrad`` holds the per-pair sum of
            absolute screen-space gradients (gsplat's densification criterion).
        rasterize_mode: "classic" or "antialiased" (opacity scaled by the eps2d compensation).
        channel_chunk: accepted for gsplat compatibility (clsplat composites all channels in
            one pass); must be a positive int.
        segmented: accepted for gsplat compatibility; clsplat always sorts once by depth, then
            places the Gaussians into their tiles in order (kernels/order.cl).
        distributed, camera_model, covars, with_ut, with_eval3d, radial_coeffs,
            tangential_coeffs, thin_prism_coeffs, ftheta_coeffs, rolling_shutter, viewmats_rs:
            gsplat features clsplat does not implement: accepted at gsplat's defaults only,
            a ValueError naming the argument otherwise.
        device: OpenCL device (see :mod:`clsplat.runtime`), default ``CLSPLAT_DEVICE``. Input
            tensors may live on any torch device; results and gradients return to it.
        precision: "float32" or "float64"; default: float64 for float64 means, else float32.
        config: accuracy knobs (:class:`RenderConfig`); ``precision`` overrides its precision.
        bwd_divide: recover transmittance in backward by division instead of forward replay.
        events: a list that receives ``(stage, pyopencl.Event)`` for every kernel launched.

    Differentiable with respect to means, quats, scales, opacities, colors (or SH),
    backgrounds and viewmats; ``meta["means2d"]`` accepts ``retain_grad()``.

    Returns:
        render_colors [..., C, H, W, X] (X = D, 1 or D+1 by mode), render_alphas
        [..., C, H, W, 1], and ``meta`` as gsplat's: batch_ids, camera_ids, gaussian_ids
        ([nnz] int64 when packed, else None), radii [..., C, N, 2] / [nnz, 2] int32, means2d,
        depths, conics, opacities (per pair), tiles_per_gauss, isect_ids [M] int64,
        flatten_ids [M] int32, isect_offsets [..., C, th, tw] int32, tile_width, tile_height,
        tile_size, width, height, n_batches, n_cameras. Results have the dtype and device of
        ``means``.
    """
    _check_not_implemented(distributed, camera_model, covars, with_ut, with_eval3d, radial_coeffs,
                           tangential_coeffs, thin_prism_coeffs, ftheta_coeffs, rolling_shutter,
                           viewmats_rs)
    if rasterize_mode not in ("classic", "antialiased"):
        raise ValueError(f"rasterize_mode: expected 'classic' or 'antialiased', got {rasterize_mode!r}")
    check_options(config, events)
    if isinstance(channel_chunk, bool) or not isinstance(channel_chunk, int) or channel_chunk < 1:
        raise ValueError(f"channel_chunk: expected a positive int, got {channel_chunk!r}")
    for name, v in (("packed", packed), ("sparse_grad", sparse_grad), ("absgrad", absgrad),
                    ("segmented", segmented)):
        if not isinstance(v, bool):
            raise ValueError(f"{name}: expected a bool, got {type(v).__name__}")
    if tile_size is None:
        tile_size = DEFAULT_TILE_SIZE
    if not isinstance(means, torch.Tensor):
        raise ValueError(f"means: expected a torch.Tensor, got {type(means).__name__}")
    if means.dim() < 2:
        raise ValueError(f"means: expected shape [..., N, 3], got {list(means.shape)}")
    out_device, out_dtype = means.device, means.dtype
    batch = tuple(means.shape[:-2])
    B, N = math.prod(batch), means.shape[-2]
    t = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
             viewmats=viewmats, Ks=Ks, backgrounds=backgrounds)
    _check_batch(batch, **t)
    if sparse_grad and not packed:
        raise ValueError("sparse_grad: needs packed=True (as in gsplat)")
    if sparse_grad and batch:
        raise ValueError(f"sparse_grad: not supported with batch dimensions {list(batch)} (as in gsplat)")
    sparse = SparseRowsGrad() if sparse_grad else None
    if sparse is not None:  # on the leaves' device, nearest them: they receive sparse gradients
        t.update({k: sparse.wrap(t[k]) for k in ("means", "quats", "scales")})
    t = {k: _host(k, v) for k, v in t.items()}

    if B == 0:
        raise ValueError(f"means: batch dimensions {list(batch)} hold no elements")
    # One validated single-batch set of tensors per batch element (without batch dimensions,
    # the tensors themselves: no view or select nodes in the graph of the common call).
    if batch:
        flat = {k: (None if v is None else v.reshape((B,) + tuple(v.shape[len(batch):])))
                for k, v in t.items()}
        per = [{k: (None if v is None else v[b]) for k, v in flat.items()} for b in range(B)]
    else:
        per = [t]
    infos = [check_rasterization_inputs(
        *(e[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")),
        width, height, near_plane, far_plane, radius_clip, eps2d, sh_degree, tile_size,
        e["backgrounds"], render_mode) for e in per]
    C, D = infos[0]["C"], infos[0]["D"]

    if precision is None:
        precision = (config.precision if config is not None else None) or (
            "float64" if out_dtype == torch.float64 else "float32")
    # (a config already of this precision, or the default one made once: RenderConfig's checks
    # ran when it was made; a config made here goes through them, a bad precision fails them)
    if config is None:
        cfg = _DEFAULT_CONFIGS.get(precision) or RenderConfig(precision=precision)
    else:
        cfg = config if config.precision == precision else config.with_(precision=precision)
    rt = get_runtime(device)
    if cfg.precision == "float64" and not rt.has_fp64:
        raise ValueError(f"precision: float64 needs cl_khr_fp64, which {rt.name} lacks")
    n_col, depth_col = _channels(render_mode, D)
    CH = n_col + (depth_col >= 0)
    real_bytes = 8 if cfg.precision == "float64" else 4
    # The plan knows its memory: the pixel buffers are checked before any work, the
    # intersections (RasterizeFn, stages.tile_lists) once their count is known.
    want_grad = torch.is_grad_enabled() and any(
        isinstance(v, torch.Tensor) and v.requires_grad for v in t.values())
    pixels = pixel_plan(B, C, height, width, n_col, depth_col >= 0, real_bytes, grad=want_grad,
                        background=backgrounds is not None,
                        expected_depth=render_mode in ("ED", "RGB+ED"))
    check_pixel_memory(rt, pixels)
    for e in per:
        e["quats"] = rescale_large_quats(e["quats"])
        check_screen_extent(e["means"], e["scales"], e["viewmats"], e["Ks"],
                            float(near_plane), float(far_plane), cfg.precision)
    nbytes = C * height * width * CH * real_bytes
    if nbytes > rt.device.max_mem_alloc_size:
        raise ValueError(f"width, height: a {C}x{height}x{width}x{CH} image needs {nbytes >> 20} MiB, "
                         f"over the device's {rt.device.max_mem_alloc_size >> 20} MiB allocation limit")

    dt = cfg.dtype
    # (differentiable: grads come back cast; a tensor already of dtype dt is not dispatched)
    cast = lambda x: (x if x.dtype == dt else x.to(dt)).contiguous()  # noqa: E731
    st0 = Settings(rt, cfg, width, height, tile_size, float(near_plane), float(far_plane),
                   float(eps2d), float(radius_clip), rasterize_mode == "antialiased",
                   absgrad=absgrad, sh_degree=sh_degree, bwd_divide=bwd_divide, events=events)
    # Project every batch element, then gather the per-pair tensors gsplat exposes (one packed
    # element: the projection gathers the packed means2d itself, Settings.pack).
    st0.pack = packed and B == 1
    proj = [ProjectFn.apply(cast(e["means"]), cast(e["quats"]), cast(e["scales"]), cast(e["opacities"]),
                            cast(e["viewmats"]), cast(e["Ks"]).detach(), st0) for e in per]
    # [B, C, N, ...]; for one batch element the projection's own [C, N, ...] outputs, which
    # batched() views as [1, C, N, ...] only where that shape is needed (no view nodes on the
    # loss path, none made per call for meta entries nobody reads)
    means2d, conics, depths, opac, radii, rects, extents = (
        proj[0][:7] if B == 1 else [torch.stack([p[i] for p in proj]) for i in range(7)])
    batched = (lambda x: x.unsqueeze(0)) if B == 1 else (lambda x: x)  # noqa: E731
    if sparse is not None:
        sparse.set_visible((batched(radii)[0] > 0).all(-1).any(0))
    if st0.pack:  # (the projection's packed output and its route, Settings.packed_route)
        route = st0.packed_route[0]
        pairs, m2d_meta = route.pairs, proj[0][7]
    else:
        pairs = pack_pairs(batched(radii)) if packed else None
        route = PackedMeans2d(pairs) if packed else None
        # (without batch dimensions the projection's own output: no view nodes on the loss path)
        m2d_meta = (route.pack(means2d) if packed else
                    proj[0][0] if not batch else batched(means2d).reshape(batch + (C, N, 2)))
    m2d_user = m2d_meta
    if out_device.type != "cpu" or out_dtype != dt:  # the user's node must lie on the loss path
        m2d_user = m2d_meta.to(device=out_device, dtype=out_dtype)
        m2d_meta = m2d_user.to(device="cpu", dtype=dt)
    if st0.pack:  # the compositor takes the packed node and the projection's values itself
        m2d_used = [m2d_meta]
    else:
        m2d_used = route.unpack(m2d_meta, means2d) if packed else m2d_meta
        # per batch element without select nodes (their backward zero-fills all of [B, C, N, 2])
        m2d_used = ([m2d_used if m2d_used.shape == (C, N, 2) else m2d_used.reshape(C, N, 2)]
                    if B == 1 else m2d_used.reshape(B, C, N, 2).unbind(0))
    sink = AbsgradSink(m2d_user, (B, C, N, 2), dt, pairs) if absgrad else None

    renders, alphas_b, isects = [], [], []
    for b in range(B):
        if B == 1 and sink is None:  # (the call's own settings: no copy)
            st = st0
            st.pixel_reserve = pixels.nbytes
        else:
            st = replace(st0, absgrad_sink=None if sink is None else sink.for_batch(b),
                         pixel_reserve=pixels.nbytes * (B - b) // B)
        _, conics_b, depths_b, opac_b, radii_b, rects_b, extents_b = proj[b][:7]  # no select nodes
        parts = []
        if n_col:
            c = per[b]["colors"]
            if sh_degree is not None:
                vm_b = cast(per[b]["viewmats"])
                if c.dim() == 4:  # per-view SH coefficients [C, N, K, 3]
                    parts.append(torch.cat([ShFn.apply(cast(c[i]), cast(per[b]["means"]), vm_b[i:i + 1],
                                                       radii_b[i:i + 1], st) for i in range(C)]))
                else:
                    parts.append(ShFn.apply(cast(c), cast(per[b]["means"]), vm_b, radii_b, st))
            else:
                c = cast(c)
                if c.dim() == 2:  # shared by the cameras; for one, [N, D] is [1, N, D]'s memory
                    # and the compositor takes it as it is (no expand, whose backward sums)
                    c = c if C == 1 and depth_col < 0 else c.unsqueeze(0) if C == 1 else c.expand(C, N, D)
                parts.append(c)
        if depth_col >= 0:
            parts.append(depths_b[..., None])
        feats = parts[0] if len(parts) == 1 else torch.cat(parts, -1)
        if N == 0:
            render = torch.zeros((C, height, width, CH), dtype=dt)
            T = torch.ones((C, height, width), dtype=dt)
            alpha = torch.zeros((C, height, width, 1), dtype=dt)
            tiles = C * (-(-width // tile_size)) * (-(-height // tile_size))
            isects.append((torch.zeros((tiles + 1,), dtype=torch.int32), torch.zeros((0,), dtype=torch.int64)))
        else:
            render, T, alpha = RasterizeFn.apply(m2d_used[b], conics_b, opac_b, feats.contiguous(),
                                                 rects_b, extents_b, depths_b.detach(), st)
            isects.append(st.isect)
        if per[b]["backgrounds"] is not None and n_col:
            bg = cast(per[b]["backgrounds"])[:, None, None, :]
            render = torch.cat([render[..., :n_col] + T.unsqueeze(-1) * bg, render[..., n_col:]], -1)
        renders.append(render)
        alphas_b.append(alpha)
    # (no batch dimensions: the images as they are; one batch element: a view, not a copy)
    render, alphas = ((renders[0], alphas_b[0]) if not batch else
                      (renders[0].unsqueeze(0), alphas_b[0].unsqueeze(0)) if B == 1
                      else (torch.stack(renders), torch.stack(alphas_b)))
    if render_mode in ("ED", "RGB+ED"):
        render = torch.cat([render[..., :-1], render[..., -1:] / alphas.clamp_min(1e-10)], -1)

    # gsplat's meta. Entries that cost a pass over every pair or intersection are built when
    # first read (LazyMeta), in the grad mode of this call: most training steps read few.
    grad_mode = torch.is_grad_enabled()
    tw, th = -(-width // tile_size), -(-height // tile_size)

    def isect_entries() -> dict:
        with torch.set_grad_enabled(grad_mode):
            m = intersection_meta(isects, batched(rects), batched(depths), C, N, width, height,
                                  tile_size, pairs)
        tpg = m["tiles_per_gauss"] if packed else m["tiles_per_gauss"].reshape(batch + (C, N))
        return {"tiles_per_gauss": tpg.to(out_device), "isect_ids": m["isect_ids"].to(out_device),
                "flatten_ids": m["flatten_ids"].to(out_device),
                "isect_offsets": m["isect_offsets"].reshape(batch + (C, th, tw)).to(out_device)}

    pending = dict.fromkeys(("tiles_per_gauss", "isect_ids", "flatten_ids", "isect_offsets"),
                            isect_entries)
    meta = {"tile_width": tw, "tile_height": th, "tile_size": tile_size, "width": width,
            "height": height, "n_cameras": C, "means2d": m2d_user, "n_batches": B}
    if packed:
        def pair_entries() -> dict:
            sel = pairs.flat
            with torch.set_grad_enabled(grad_mode):
                vals = {"radii": radii.reshape(-1, 2)[sel], "depths": depths.reshape(-1)[sel],
                        "conics": conics.reshape(-1, 3)[sel], "opacities": opac.reshape(-1)[sel]}
                return {k: _to_user(v, out_device, out_dtype) for k, v in vals.items()}

        def id_entries() -> dict:
            return {k: getattr(pairs, k).to(out_device)
                    for k in ("batch_ids", "camera_ids", "gaussian_ids")}

        pending.update(dict.fromkeys(("radii", "depths", "conics", "opacities"), pair_entries))
        pending.update(dict.fromkeys(("batch_ids", "camera_ids", "gaussian_ids"), id_entries))
    else:
        # [B, C, N, ...] -> [..., C, N, ...] (B = 1 without batch dimensions: as they are)
        unbatch = lambda x: x if not batch else batched(x).reshape(batch + tuple(batched(x).shape[1:]))  # noqa: E731
        meta.update(batch_ids=None, camera_ids=None, gaussian_ids=None)
        meta.update({k: _to_user(unbatch(v), out_device, out_dtype) for k, v in
                     (("radii", radii), ("depths", depths), ("conics", conics),
                      ("opacities", opac))})
    meta = LazyMeta(meta, pending)
    shape = batch + (C, height, width)
    if batch:
        render, alphas = render.reshape(shape + (render.shape[-1],)), alphas.reshape(shape + (1,))
    return _to_user(render, out_device, out_dtype), _to_user(alphas, out_device, out_dtype), meta


def _to_user(x: torch.Tensor, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    if x.device == device and (x.dtype == dtype or not x.is_floating_point()):
        return x  # (what .to returns then: no dispatch)
    if x.is_floating_point():
        return x.to(device=device, dtype=dtype)
    return x.to(device=device)
