"""Backward kernels on the stiff and extreme catalogue (DESIGN.md §5).

kernels/composite_bwd.cl, kernels/reduce.cl, kernels/project_bwd.cl and kernels/sh_bwd.cl are
exercised through rasterization(): every category yields finite gradients within a stated
bound of the float64 reference, or a clear ValueError for invalid input. The two ways of
recovering transmittance (replay, divide) are compared on opaque stacks and the clamp.
"""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import reference as ref

F64 = torch.float64
W = H = 32
K = torch.tensor([[[30.0, 0, 16], [0, 30, 16], [0, 0, 1]]], dtype=F64)
VM = torch.eye(4, dtype=F64)[None]


def gaussians(n: int, seed: int = 0, depth=2.0, spread=0.3, scale=(0.2, 0.1, 0.15), opacity=0.7):
    g = torch.Generator().manual_seed(seed)
    means = torch.zeros(n, 3, dtype=F64)
    means[:, :2] = (torch.rand(n, 2, generator=g, dtype=F64) - 0.5) * spread
    means[:, 2] = depth + torch.arange(n, dtype=F64) * 0.01
    quats = torch.tensor([[1.0, 0.3, 0.2, 0.1]], dtype=F64).repeat(n, 1)
    quats = quats + 0.1 * torch.randn(n, 4, generator=g, dtype=F64)
    scales = torch.tensor([scale], dtype=F64).repeat(n, 1)
    opac = torch.full((n,), opacity, dtype=F64)
    colors = torch.rand(n, 3, generator=g, dtype=F64)
    return [means, quats, scales, opac, colors]


def grads(fn, xs, dtype=F64, **kw):
    xs = [x.to(dtype).clone().requires_grad_() for x in xs]
    r, a, _ = fn(*xs, VM.to(dtype), K.to(dtype), W, H, **kw)
    w = torch.linspace(0.5, 1.5, r.numel(), dtype=dtype).reshape(r.shape)
    ((r * w).sum() + a.sum()).backward()
    return [x.grad.double() for x in xs]


def rel_err(a, b):
    """Largest relative L2 error over the gradient tensors (a tensor whose true gradient is
    zero, e.g. quats of an isotropic Gaussian, is measured against 1e-12 instead)."""
    return max(((x - y).norm() / y.norm().clamp_min(1e-12)).item() for x, y in zip(a, b))


def check(xs, bound32: float, **kw):
    """float64 kernels match the reference to 1e-9, float32 within ``bound32``, all finite."""
    g_ref = grads(ref.rasterization, xs, **kw)
    g64 = grads(clsplat.rasterization, xs, **kw)
    g32 = grads(clsplat.rasterization, xs, torch.float32, **kw)
    for g in (g64, g32):
        assert all(bool(torch.isfinite(x).all()) for x in g)
    assert rel_err(g64, g_ref) < 1e-9
    err32 = rel_err(g32, g_ref)
    assert err32 < bound32, err32
    return err32


@pytest.mark.parametrize("divide", [False, True])
@pytest.mark.parametrize("opacity", [0.999, 0.99, 0.5])
def test_opaque_stack(opacity, divide):
    """300 Gaussians on one pixel: the pixel stops at T_MIN after a few samples; both ways
    of recovering T give float32 gradients within 1e-5 (measured ~1.2e-6 for both)."""
    check(gaussians(300, spread=0.02, opacity=opacity), 1e-5, bwd_divide=divide)


def test_near_clamp():
    """Opacities straddling ALPHA_MAX: the clamp passes no gradient, and the reference
    (torch clamp_max) agrees."""
    xs = gaussians(40, spread=0.3)
    xs[3] = torch.linspace(0.9985, 0.9995, 40, dtype=F64)  # around gsplat's ALPHA_MAX 0.999
    check(xs, 1e-5)


@pytest.mark.parametrize("ratio", [1e4, 1e6])
def test_needle(ratio):
    """Needles: a 1e6 axis ratio makes the 2D covariance eps2d-dominated along one axis;
    float32 rounding of the long axis costs about 1e-4 relative."""
    xs = gaussians(20, scale=(0.3, 0.3 / ratio, 0.3 / ratio))
    check(xs, 1e-3)


def test_zero_scales_and_sub_pixel():
    """Zero scales: eps2d alone makes the footprint; gradients to scales still exist
    (d cov / d s = 0 at s = 0 gives exactly zero) and are finite."""
    xs = gaussians(20, scale=(0.0, 0.0, 0.0))
    g = grads(clsplat.rasterization, xs)
    assert all(bool(torch.isfinite(x).all()) for x in g)
    assert g[2].abs().max() == 0  # zero scale: derivative of s^2 vanishes
    check(gaussians(20, scale=(1e-4, 2e-4, 1e-4)), 1e-4)


def test_near_plane_and_off_axis():
    """Means just beyond the near plane produce huge, clamped-Jacobian footprints; far
    off-axis means clamp the Jacobian (no gradient through the clamped coordinate)."""
    xs = gaussians(10, depth=0.0105, spread=0.001, scale=(0.002, 0.001, 0.001))
    check(xs, 1e-3, near_plane=0.01)
    xs = gaussians(10, depth=2.0, spread=0.2)
    xs[0][0, 0] = 1.6  # x/z = 0.8 beyond the widened frustum (0.69): clamped Jacobian,
    xs[2][0] = 0.5     # and large enough to still reach into the image
    check(xs, 1e-4)


def test_huge_gaussians():
    check(gaussians(10, scale=(50.0, 40.0, 30.0), opacity=0.3), 1e-4)


def test_denormal_opacities_and_colours():
    """Denormal inputs are flushed by -cl-denorms-are-zero: those samples fall below
    ALPHA_MIN and get no gradient; nothing is NaN, and the time does not explode."""
    xs = gaussians(30)
    xs[3][:10] = 1e-40
    xs[4][10:20] = 1e-40
    g = grads(clsplat.rasterization, xs, torch.float32)
    assert all(bool(torch.isfinite(x).all()) for x in g)
    assert g[3][:10].abs().max() == 0


def test_zero_quaternion_is_rejected():
    xs = gaussians(5)
    xs[1][2] = 0
    with pytest.raises(ValueError, match="quats"):
        grads(clsplat.rasterization, xs)


def test_sh_backward_far_and_near_views():
    """SH gradients to means through the view direction stay finite for views from very far
    (direction nearly constant) and very near (direction changes fast)."""
    for depth in (1e3, 0.05):
        xs = gaussians(8, depth=depth, spread=0.01 * depth, scale=(0.01 * depth, 0.007 * depth, 0.012 * depth))
        g = torch.Generator().manual_seed(1)
        xs[4] = torch.randn(8, 16, 3, generator=g, dtype=F64) * 0.3
        check(xs, 1e-3, sh_degree=3, near_plane=0.01)
