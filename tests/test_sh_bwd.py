"""kernels/sh_bwd.cl via clsplat.autograd.ShFn against torch autograd of
clsplat.reference.sh_colors: to the coefficients, the means and the view matrices."""
from __future__ import annotations

import pytest
import torch

import clsplat
from clsplat import reference as ref
from clsplat.autograd import ShFn, Settings
from clsplat.config import RenderConfig

F64 = torch.float64


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_sh_bwd_matches_reference(make_scene, degree, dtype):
    scene = make_scene(seed=degree, N=120, C=2, sh_degree=degree, K_extra=2)
    C, N = 2, 120
    coeffs, means, vm = (scene[k].to(dtype).clone().requires_grad_() for k in ("colors", "means", "viewmats"))
    radii = torch.ones((C, N, 2), dtype=torch.int32)  # all visible
    st = Settings(clsplat.get_runtime(), RenderConfig(precision="float64" if dtype == F64 else "float32"),
                  64, 48, 16, 0.01, 1e10, 0.3, 0.0, False, sh_degree=degree)
    cols = ShFn.apply(coeffs, means, vm, radii, st)
    w = torch.randn(cols.shape, generator=torch.Generator().manual_seed(1), dtype=F64).to(dtype)
    (cols * w).sum().backward()
    x = [t.detach().double().requires_grad_() for t in (scene["colors"], scene["means"], scene["viewmats"])]
    ref_cols = ref.sh_colors(x[0], x[1], x[2], degree)
    (ref_cols * w.double()).sum().backward()
    tol = 1e-10 if dtype == F64 else 1e-4  # float32: ~1e-6 per term, summed over 16 bands
    assert torch.allclose(cols.double(), ref_cols, atol=tol)
    for name, a, b in zip(("coeffs", "means", "viewmats"), (coeffs, means, vm), x):
        if degree == 0 and name != "coeffs":
            assert a.grad.abs().max() < tol  # a constant band does not depend on the direction
            continue
        err = ((a.grad.double() - b.grad).norm() / b.grad.norm().clamp_min(1e-12)).item()
        assert err < tol, (name, err)
    # coefficients beyond the degree get exactly zero gradient
    assert coeffs.grad[:, (degree + 1) ** 2:].abs().max() == 0


@pytest.mark.parametrize("degree", [1, 3])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_sh_bwd_culled_pairs_give_no_gradient(make_scene, degree, dtype):
    """Pairs with radii 0 (culled in that camera) contribute nothing: the gradient equals the
    reference's over the visible pairs only, and a Gaussian culled in every camera gets zero."""
    C, N = 2, 60
    scene = make_scene(seed=7 + degree, N=N, C=C, sh_degree=degree, K_extra=0)
    coeffs, means, vm = (scene[k].to(dtype).clone().requires_grad_() for k in ("colors", "means", "viewmats"))
    vis = torch.rand((C, N), generator=torch.Generator().manual_seed(2)) > 0.4
    vis[:, :5] = False                                   # culled everywhere
    radii = vis[..., None].expand(C, N, 2).to(torch.int32)
    st = Settings(clsplat.get_runtime(), RenderConfig(precision="float64" if dtype == F64 else "float32"),
                  64, 48, 16, 0.01, 1e10, 0.3, 0.0, False, sh_degree=degree)
    cols = ShFn.apply(coeffs, means, vm, radii, st)
    w = torch.randn(cols.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    (cols * w.to(dtype)).sum().backward()
    x = [t.detach().double().requires_grad_() for t in (scene["colors"], scene["means"], scene["viewmats"])]
    (ref.sh_colors(x[0], x[1], x[2], degree) * w * vis[..., None]).sum().backward()
    tol = 1e-10 if dtype == F64 else 1e-4
    for name, a, b in zip(("coeffs", "means", "viewmats"), (coeffs, means, vm), x):
        err = ((a.grad.double() - b.grad).norm() / b.grad.norm().clamp_min(1e-12)).item()
        assert err < tol, (name, err)
    assert coeffs.grad[:5].abs().max() == 0 and means.grad[:5].abs().max() == 0
