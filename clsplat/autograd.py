"""torch.autograd Functions between :func:`clsplat.rasterization` and the stage drivers.

Three Functions, as in gsplat, so that ``meta["means2d"]`` is a real graph node that accepts
``retain_grad()``:

* :class:`ProjectFn`: (means, quats, scales, opacities, viewmats) -> means2d, conics, depths,
  compositing opacities (+ non-differentiable radii and tile rectangles);
* :class:`ShFn`: (SH coefficients, means) -> colours [C,N,3];
* :class:`RasterizeFn`: (means2d, conics, opacities, features) -> composited features, T and
  the alphas 1 - T [C,H,W,1] (features [C,N,CH], or [N,CH] for one camera: the same memory).

Each forward keeps the device buffers its backward needs rather than recomputing them, and
each backward is specialised on ``ctx.needs_input_grad``: gradients nobody asked for are
neither computed nor stored.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from . import plan, stages
from .config import RenderConfig
from .packed import PackedMeans2d, gather_pairs, pack_pairs
from .runtime import DeviceArray, Runtime, read_back
from .validate import all_finite

__all__ = ["Settings", "ProjectFn", "ShFn", "RasterizeFn"]


@dataclass
class Settings:
    """Non-tensor arguments shared by the Functions of one rasterization call."""

    rt: Runtime
    cfg: RenderConfig
    width: int
    height: int
    tile_size: int
    near_plane: float
    far_plane: float
    eps2d: float
    radius_clip: float
    antialiased: bool
    absgrad: bool = False
    sh_degree: int | None = None
    bwd_divide: bool = False
    events: list | None = None
    isect: tuple | None = None  # (tile offsets, sorted keys) of the forward, for ``meta``
    absgrad_sink: object = None  # callable(absgrad [C,N,2]); default: set means2d.absgrad
    pixel_reserve: int = 0  # bytes of pixel buffers still to come (clsplat.plan)
    # data_ptr -> the device array of a projection output of this call, which the later
    # Functions pass to their kernels instead of making a new buffer (_array): on the copying
    # path (GPUs) that is an upload of what was just read back (bench/notes/engine_gpu.md). The
    # outputs returned are detached aliases of these arrays' tensors, so no array refers to an
    # output or its grad_fn: holding them makes no reference cycle through autograd's graph
    # (tests/test_autograd.py, test_renders_free_their_buffers).
    arrays: dict | None = None
    # rects' data_ptr -> stages.EarlyTiles: a small call's tile lists, launched by ProjectFn
    # right behind the projection (one wait for both), for RasterizeFn to take
    early: dict | None = None
    # rects' data_ptr -> the projection's tiles [C,N] (stages.Projection), for RasterizeFn's counts
    tiles: dict | None = None
    # ProjectFn (one batch element, packed): also outputs the packed meta["means2d"] [nnz, 2],
    # its pairs' route set as packed_route (no gathering node between them)
    pack: bool = False
    # (packed.PackedMeans2d, means2d [C,N,2]): RasterizeFn's means2d input is the packed
    # meta["means2d"] [nnz, 2] of this route, which it composites with these values (one batch
    # element: no unpacking node between them)
    packed_route: tuple | None = None


def _array(s: Settings, t: torch.Tensor, read_only: bool = False) -> DeviceArray:
    """``t`` on the device: the projection's own array where ``t`` is one of its outputs as
    returned (see :attr:`Settings.arrays`), else :meth:`Runtime.array`'s."""
    a = s.arrays.get(t.data_ptr()) if s.arrays else None
    if (a is not None and a.tensor.shape == t.shape and a.tensor.dtype == t.dtype
            and a.tensor.stride() == t.stride()):
        return a
    return s.rt.array(t, read_only)


def _finite_grad(name: str, g: torch.Tensor | None) -> None:
    if g is not None and not all_finite(g.detach().numpy()):
        raise ValueError(f"grad_output ({name}): contains NaN or Inf; the loss or its "
                         "gradient is not finite")


class ProjectFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, s: Settings):
        rt, arr = s.rt, s.rt.array
        # (kept for the next call: parameters and cameras are passed again)
        inputs = {n: arr(t, keep=True) for n, t in zip(
            ("means", "quats", "scales", "opacities", "viewmats", "Ks"),
            (means, quats, scales, opacities, viewmats, Ks))}
        p = stages.project(rt, s.cfg, *inputs.values(), s.width, s.height, s.tile_size,
                           near_plane=s.near_plane, far_plane=s.far_plane, eps2d=s.eps2d,
                           radius_clip=s.radius_clip, antialiased=s.antialiased, events=s.events)
        # a small call's tile lists, queued behind the projection: read back with it
        early = stages.early_tile_lists(rt, s.cfg, p.rects, p.depths, s.width, s.height,
                                        s.tile_size, events=s.events)
        # (aliases: autograd sets its node on the tensors returned, never on a pooled array's own)
        outs = [t.detach() for t in read_back(p.means2d, p.conics, p.depths, p.opacities, p.radii,
                                                p.rects, p.extents, *((p.tiles,) if p.tiles is not None else ()),
                                                *((early.offsets,) if early else ()))[:7]]
        p.rects.read_only = True  # no later command writes the rectangles: read without a wait
        if s.arrays is None:
            s.arrays = {}
        s.arrays.update((a.tensor.data_ptr(), a) for a in (p.means2d, p.conics, p.depths, p.opacities,
                                                           p.radii, p.rects, p.extents)
                        if a.tensor.numel())
        if early is not None:
            if s.early is None:
                s.early = {}
            s.early[p.rects.tensor.data_ptr()] = early
        if p.tiles is not None:
            p.tiles.read_only = True  # (as the rectangles)
            if s.tiles is None:
                s.tiles = {}
            s.tiles[p.rects.tensor.data_ptr()] = p.tiles
        ctx.mark_non_differentiable(*outs[4:])
        ctx.route = None
        if s.pack:  # the packed meta["means2d"] of the visible pairs, on the loss path
            ctx.route = PackedMeans2d(pack_pairs(outs[4].unsqueeze(0)))
            s.packed_route = (ctx.route, outs[0].detach())  # (detached: no cycle via grad_fn)
            outs.append(gather_pairs(outs[0], ctx.route.pairs.flat))
        # gradients of unused outputs (depths in most calls) come as None, not zeros torch made:
        # the backward stages None as a kept zero array (Runtime.staged)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means, quats, scales, opacities, viewmats, Ks, outs[4])
        ctx.s = s
        # The inputs' device arrays, for the backward (autograd refuses a backward after an
        # in-place change of a saved input, so their data stay the inputs'): not made again.
        ctx.arrays = inputs
        return tuple(outs)

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, v_opac, _v_radii, _v_rects, _v_ext,
                 v_packed=None):
        s = ctx.s
        means, quats, scales, opacities, viewmats, Ks, radii = ctx.saved_tensors
        C, N = radii.shape[:2]
        if v_packed is not None:  # the packed node's gradient, to the pairs it was gathered from
            full = ctx.route.packed_grad_to_full(v_packed).view(C, N, 2)
            v_means2d = full if v_means2d is None else v_means2d + full
        dt = s.cfg.dtype
        rt = s.rt
        grads = {"v_means2d": rt.staged(v_means2d, (C, N, 2), dt),
                 "v_conics": rt.staged(v_conics, (C, N, 3), dt),
                 "v_depths": rt.staged(v_depths, (C, N), dt),
                 "v_opacities": rt.staged(v_opac, (C, N), dt)}
        inputs = ctx.arrays
        ctx.arrays = None  # (a second backward needs retain_graph, and finds them gone: remade)
        if inputs is None:
            inputs = {n: rt.array(t.detach()) for n, t in zip(
                ("means", "quats", "scales", "opacities", "viewmats", "Ks"),
                (means, quats, scales, opacities, viewmats, Ks))}
        out = stages.project_bwd(rt, s.cfg, inputs, _array(s, radii), grads, s.width, s.height,
                                 eps2d=s.eps2d, antialiased=s.antialiased,
                                 viewmat_grad=ctx.needs_input_grad[4], events=s.events)
        need = ctx.needs_input_grad
        names = [k for i, k in enumerate(("v_means", "v_quats", "v_scales", "v_opacities")) if need[i]]
        back = dict(zip(names, read_back(*(out[k] for k in names))))
        res = [back.get(k) for k in ("v_means", "v_quats", "v_scales", "v_opacities")]
        res.append(out["v_viewmats"] if need[4] else None)
        return (*res, None, None)


def _centre_viewmats(viewmats: torch.Tensor) -> torch.Tensor:
    """[C,4,4] -> [C,4,4] translations whose centre -R^T t (what the SH kernels read) is
    gsplat's camera centre torch.inverse(viewmats)[:, :3, 3]."""
    vm = torch.eye(4, dtype=viewmats.dtype).repeat(viewmats.shape[0], 1, 1)
    vm[:, :3, 3] = -torch.inverse(viewmats)[:, :3, 3]
    return vm.contiguous()


class ShFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs, means, viewmats, radii, s: Settings):
        rt, arr = s.rt, s.rt.array
        ctx.orig_viewmats = viewmats.detach()
        viewmats = _centre_viewmats(ctx.orig_viewmats)
        colors = stages.sh_colors(rt, s.cfg, arr(means, keep=True), arr(viewmats), arr(coeffs, keep=True),
                                  _array(s, radii),
                                  s.sh_degree, events=s.events).host().detach()  # (an alias: see ProjectFn)
        ctx.save_for_backward(coeffs, means, viewmats, radii, colors)
        ctx.s = s
        return colors

    @staticmethod
    def backward(ctx, v_colors):
        s = ctx.s
        coeffs, means, viewmats, radii, colors = ctx.saved_tensors
        need_coeffs, need_means, need_view = ctx.needs_input_grad[:3]
        if not (need_coeffs or need_means or need_view):
            return None, None, None, None, None
        rt, arr = s.rt, s.rt.array
        v_coeffs, v_means, v_dirs = stages.sh_colors_bwd(
            rt, s.cfg, arr(means.detach(), keep=True), arr(viewmats.detach()),
            arr(coeffs.detach(), keep=True),
            _array(s, radii), arr(colors), rt.staged(v_colors, tuple(colors.shape), colors.dtype),
            s.sh_degree, need_means, need_view,
            events=s.events)
        v_view = None
        if need_view:  # direction = mean - centre, centre = inverse(viewmats)[:3, 3] as in
            # gsplat (so every entry of the matrix gets its gradient): a [C]-sized torch backward
            with torch.enable_grad():
                vm = ctx.orig_viewmats.clone().requires_grad_()
                centre = torch.inverse(vm)[:, :3, 3]
                v_view, = torch.autograd.grad(centre, vm, -v_dirs.host().sum(1))
        return (v_coeffs.host() if need_coeffs else None,
                v_means.host() if need_means else None, v_view, None, None)


class RasterizeFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, rects, extents, depths, s: Settings):
        rt, cfg, arr = s.rt, s.cfg, s.rt.array
        ctx.route, full = s.packed_route or (None, means2d)  # (packed: see Settings.packed_route)
        a = {"means2d": _array(s, full), "conics": _array(s, conics),  # (the projection's own)
             "opacities": _array(s, opacities), "feats": arr(feats, keep=True),
             "rects": _array(s, rects, read_only=True), "extents": _array(s, extents)}
        want_grad = any(ctx.needs_input_grad[:4])  # False under no_grad or for constants
        per_isect = plan.intersection_bytes(feats.shape[-1], feats.element_size(), grad=want_grad,
                                            absgrad=s.absgrad)
        d = _array(s, depths)
        early = s.early.pop(rects.data_ptr(), None) if s.early else None
        if early is not None and (early.rects is not a["rects"] or early.depths is not d):
            early = None  # (not this projection's: the lists are built here)
        pair_tiles = [] if want_grad else None  # (for the backward's slot offsets)
        tiles = s.tiles.pop(rects.data_ptr(), None) if s.tiles else None
        if tiles is not None and tiles.tensor.shape != rects.shape[:-1]:
            tiles = None  # (not this projection's: counted from the rectangles)
        offsets, keys = stages.tile_lists(rt, cfg, a["rects"], d, s.width,
                                          s.height, s.tile_size, events=s.events,
                                          per_intersection=per_isect, reserve=s.pixel_reserve,
                                          early=early, pair_tiles=pair_tiles, tiles=tiles)
        out, T, last = stages.composite(rt, cfg, a["means2d"], a["conics"], a["opacities"],
                                        a["extents"], a["feats"], offsets, keys, s.width, s.height,
                                        s.tile_size, save_last=want_grad, events=s.events)
        out_t, T_t, off_t, keys_t = read_back(out, T, offsets, keys)
        out_t, T_t = out_t.detach(), T_t.detach()  # (aliases: see ProjectFn)
        ctx.s = s
        # The outputs are saved tensors, never held in ctx.fwd: out.tensor is out_t, and
        # output -> grad_fn -> ctx -> array -> output would be a cycle the GC cannot free.
        ctx.fwd = dict(a, offsets=offsets, keys=keys, last=last,
                       pair_tiles=pair_tiles[0]) if want_grad else None
        if want_grad:
            ctx.save_for_backward(out_t, T_t)
        ctx.means2d = means2d  # receives .absgrad, as gsplat's densification expects
        ctx.feats_shape = feats.shape  # ([N, CH] for one camera: its gradient is given that shape)
        s.isect = (off_t, keys_t)  # read back: not shared memory on GPUs
        # the alphas gsplat returns, made here rather than by two recorded ops (and two
        # backward nodes) per call; T's gradient takes theirs negated (backward)
        ctx.set_materialize_grads(False)
        return out_t, T_t, (1 - T_t).unsqueeze(-1)

    @staticmethod
    def backward(ctx, v_out, v_T, v_alpha):
        s = ctx.s
        if v_alpha is not None:  # alpha = 1 - T
            v_a = v_alpha.squeeze(-1)
            # (checked below as T's, once staged: a NaN or Inf in either term leaves one in
            # the difference)
            v_T = -v_a if v_T is None else v_T - v_a
        need = ctx.needs_input_grad
        geom, color = any(need[:3]), need[3]
        fwd = ctx.fwd
        if fwd is None or not (geom or color):
            _finite_grad("render_colors", v_out)
            _finite_grad("render_alphas", v_T)
            return (None,) * 8
        rt, cfg = s.rt, s.cfg
        out_t, T_t = ctx.saved_tensors
        fwd = dict(fwd, out=rt.array(out_t), T=rt.array(T_t))
        given = v_out is not None, v_T is not None
        v_out = rt.staged(v_out, tuple(out_t.shape), out_t.dtype)
        v_T = rt.staged(v_T, tuple(T_t.shape), T_t.dtype)
        # checked once staged: contiguous copies, where the incoming gradients are often
        # expanded (a sum's backward), which numpy walks element by element (~3x the time)
        if given[0]:
            _finite_grad("render_colors", v_out.tensor)
        if given[1]:
            _finite_grad("render_alphas", v_T.tensor)
        absgrad = s.absgrad and geom
        with rt.scratch() as alloc:  # the slots live only until the reduce is read back
            r = stages.composite_bwd_reduced(rt, cfg, fwd, v_out, v_T, s.width, s.height,
                                             s.tile_size, geom=geom, color=color, absgrad=absgrad,
                                             divide=s.bwd_divide, events=s.events, alloc=alloc)
            g = dict(zip(r, read_back(*r.values())))
        if absgrad:
            if s.absgrad_sink is not None:
                s.absgrad_sink(g["absgrad"])
            else:
                ctx.means2d.absgrad = g["absgrad"]
        v_m2d = g["v_means2d"] if need[0] else None
        if v_m2d is not None and ctx.route is not None:  # the packed node's gather
            v_m2d = ctx.route.render_grad_to_packed(v_m2d)
        return (v_m2d, g["v_conics"] if need[1] else None,
                g["v_opacities"] if need[2] else None,
                g["v_feats"].view(ctx.feats_shape) if color else None,
                None, None, None, None)
