"""models/common/gaussians.py: GaussianSet operations, SH rotation, .ply round trip, rendering."""
from __future__ import annotations

import math

import pytest
import torch

from clsplat.models.common import geometry as G
from clsplat.models.common.gaussians import GaussianSet, rotate_sh
from clsplat.sh import sh_basis

F64 = torch.float64


def make_set(n: int = 40, degree: int = 2, seed: int = 0, dtype=F64) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=dtype)  # noqa: E731
    return GaussianSet(means=(r(n, 3) - 0.5) * 2, quats=torch.randn(n, 4, generator=g, dtype=dtype),
                       scales=0.05 + 0.15 * r(n, 3), opacities=0.3 + 0.6 * r(n),
                       sh=0.3 * torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=dtype))


def camera(eye=(0.0, -0.5, -4.0)) -> tuple[torch.Tensor, torch.Tensor]:
    """world-to-camera looking at the origin along +z from ``eye`` (no rotation), and K."""
    vm = torch.eye(4, dtype=F64)
    vm[:3, 3] = -torch.tensor(eye, dtype=F64)
    K = torch.tensor([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]], dtype=F64)
    return vm[None], K[None]


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_rotate_sh_rotates_the_colour_function(degree):
    torch.manual_seed(degree)
    R = G.axis_angle_to_matrix(torch.randn(3, dtype=F64))
    sh = torch.randn(6, (degree + 1) ** 2, 3, dtype=F64)
    v = torch.nn.functional.normalize(torch.randn(50, 3, dtype=F64), dim=-1)
    before = torch.einsum("vk,nkc->nvc", sh_basis(v, degree), sh)
    after = torch.einsum("vk,nkc->nvc", sh_basis(v @ R.T, degree), rotate_sh(sh, R))
    assert (before - after).abs().max() < 1e-12
    assert torch.equal(rotate_sh(sh, R)[:, 0], sh[:, 0])


def test_rotate_sh_per_gaussian_and_differentiable():
    aa = torch.randn(4, 3, dtype=F64, requires_grad=True)
    sh = torch.randn(4, 9, 3, dtype=F64)
    out = rotate_sh(sh, G.axis_angle_to_matrix(aa))
    for i in range(4):
        assert torch.allclose(out[i], rotate_sh(sh[i:i + 1], G.axis_angle_to_matrix(aa[i]))[0], atol=1e-12)
    out.sum().backward()
    assert aa.grad is not None and torch.isfinite(aa.grad).all() and aa.grad.abs().sum() > 0
    assert torch.autograd.gradcheck(lambda a: rotate_sh(sh[:1], G.axis_angle_to_matrix(a)), (aa[:1].detach().requires_grad_(),))


def test_cat_index_and_degree_padding():
    a, b = make_set(5, 0, 1), make_set(7, 2, 2)
    c = GaussianSet.cat([a, b])
    assert len(c) == 12 and c.sh_degree == 2
    assert torch.equal(c.sh[:5, 1:], torch.zeros(5, 8, 3, dtype=F64))
    assert torch.equal(c[torch.arange(5, 12)].means, b.means)
    mask = torch.zeros(12, dtype=torch.bool)
    mask[3] = True
    assert len(c.index(mask)) == 1
    assert c.with_sh_degree(1).sh.shape == (12, 4, 3)


def test_transform_moves_gaussians_with_the_camera():
    """Moving the Gaussians by T and the camera by T renders the same image (means, rotations
    and view-dependent SH all follow)."""
    gs = make_set(60, 3)
    vm, K = camera()
    T = G.se3_exp(torch.tensor([0.3, -0.5, 0.8], dtype=F64), torch.tensor([1.0, 2.0, -0.5], dtype=F64))
    img0, a0, _ = gs.render(vm, K, 64, 48)
    img1, a1, _ = gs.transform(T).render(vm @ G.invert_rigid(T), K, 64, 48)
    assert a0.sum() > 50
    assert (img0 - img1).abs().max() < 1e-9 and (a0 - a1).abs().max() < 1e-9


def test_ply_round_trip(tmp_path):
    gs = make_set(30, 3, dtype=torch.float32)
    gs.save_ply(tmp_path / "s.ply")
    back = GaussianSet.load_ply(tmp_path / "s.ply")
    assert torch.allclose(back.means, gs.means) and torch.allclose(back.sh, gs.sh)
    assert torch.allclose(back.scales, gs.scales, rtol=1e-5) and torch.allclose(back.opacities, gs.opacities, atol=1e-6)


def test_render_is_differentiable():
    gs = make_set(30, 1)
    gs.means.requires_grad_(True)
    gs.sh.requires_grad_(True)
    vm, K = camera()
    img, _, _ = gs.render(vm, K, 64, 48)
    img.sum().backward()
    assert gs.means.grad.abs().sum() > 0 and gs.sh.grad.abs().sum() > 0


@pytest.mark.parametrize("field,value,match", [
    ("means", torch.zeros(3, 2), "GaussianSet.means"),
    ("quats", torch.zeros(4, 3), "GaussianSet.quats"),
    ("sh", torch.zeros(4, 5, 3), "GaussianSet.sh"),
    ("opacities", torch.zeros(4, dtype=torch.int64), "GaussianSet.opacities"),
    ("scales", torch.zeros(4, 3, dtype=F64), "GaussianSet.scales"),
])
def test_bad_fields_are_named(field, value, match):
    kw = dict(means=torch.zeros(4, 3), quats=torch.zeros(4, 4), scales=torch.ones(4, 3),
              opacities=torch.ones(4), sh=torch.zeros(4, 1, 3))
    kw[field] = value
    with pytest.raises(ValueError, match=match):
        GaussianSet(**kw)


def test_validate_values():
    gs = make_set(4)
    gs.means[1, 0] = math.nan
    with pytest.raises(ValueError, match="GaussianSet.means: contains NaN"):
        gs.validate()
    gs = make_set(4)
    gs.opacities[0] = 1.5
    with pytest.raises(ValueError, match="opacities"):
        gs.validate()
    with pytest.raises(ValueError, match="T: not a rigid"):
        make_set(4).transform(torch.diag(torch.tensor([2.0, 1, 1, 1], dtype=F64)))
