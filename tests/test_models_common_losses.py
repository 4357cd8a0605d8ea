"""Photometric error (3x3 box SSIM + L1), edge-aware smoothness and the Chamfer distance."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from kornia.filters import box_blur

from clsplat.models.common.losses import (
    chamfer_distance,
    edge_aware_smoothness,
    photometric_error,
    ssim_map3,
)


def numpy_box_ssim(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SSIM of one channel [H, W] over 3x3 windows of the reflection-padded images, by loops."""
    pa, pb = np.pad(a, 1, mode="reflect"), np.pad(b, 1, mode="reflect")
    out = np.zeros_like(a)
    c1, c2 = 0.01**2, 0.03**2
    for i in range(a.shape[0]):
        for j in range(a.shape[1]):
            wa, wb = pa[i : i + 3, j : j + 3], pb[i : i + 3, j : j + 3]
            ma, mb = wa.mean(), wb.mean()
            va, vb = ((wa - ma) ** 2).mean(), ((wb - mb) ** 2).mean()
            cov = ((wa - ma) * (wb - mb)).mean()
            out[i, j] = (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
    return out


def test_ssim_map3_matches_direct_computation():
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 3, 7, 9, generator=g, dtype=torch.float64)
    b = (a + 0.2 * torch.rand(2, 3, 7, 9, generator=g, dtype=torch.float64)).clamp(0, 1)
    got = ssim_map3(a, b)
    want = np.stack([[numpy_box_ssim(a[i, c].numpy(), b[i, c].numpy()) for c in range(3)] for i in range(2)])
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=1e-12)
    # the same statistics as kornia's reflect-padded box filter
    mu, sq, ab = (box_blur(x, 3, border_type="reflect") for x in (a, a * a, a * b))
    mu_b, sq_b = box_blur(b, 3, border_type="reflect"), box_blur(b * b, 3, border_type="reflect")
    num = (2 * mu * mu_b + 1e-4) * (2 * (ab - mu * mu_b) + 9e-4)
    den = (mu**2 + mu_b**2 + 1e-4) * (sq - mu**2 + sq_b - mu_b**2 + 9e-4)
    torch.testing.assert_close(got, num / den)


def test_photometric_error_zero_for_identical_and_grows_with_noise():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(2, 3, 16, 20, generator=g)
    e0 = photometric_error(img, img)
    assert e0.shape == (2, 1, 16, 20)
    assert e0.abs().max() < 1e-5
    noise = torch.randn(img.shape, generator=g)
    errs = [float(photometric_error(img, (img + s * noise).clamp(0, 1)).mean()) for s in (0.02, 0.1, 0.3)]
    assert 0 < errs[0] < errs[1] < errs[2]
    # a pure brightness offset: L1 part is exactly 0.15 * offset where SSIM's structure is unchanged
    b = img * 0.5
    e = photometric_error(b, b + 0.1)
    assert torch.all(e >= 0.15 * 0.1 - 1e-6)


def test_photometric_error_is_differentiable_and_checks_input():
    a = torch.rand(1, 3, 8, 8, requires_grad=True)
    photometric_error(a, torch.rand(1, 3, 8, 8)).mean().backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="a and b: shapes differ"):
        photometric_error(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))
    bad = torch.rand(1, 3, 8, 8)
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="b: contains NaN"):
        photometric_error(torch.rand(1, 3, 8, 8), bad)
    with pytest.raises(ValueError, match=r"a: expected shape \[B, C, H, W\]"):
        photometric_error(torch.rand(3, 8, 8), torch.rand(3, 8, 8))


def test_edge_aware_smoothness():
    img = torch.rand(2, 3, 10, 12)
    assert float(edge_aware_smoothness(torch.full((2, 1, 10, 12), 0.3), img)) == 0.0
    # mean-normalised: scaling the disparity does not change the loss
    disp = torch.rand(2, 1, 10, 12) + 0.1
    torch.testing.assert_close(edge_aware_smoothness(disp, img), edge_aware_smoothness(5 * disp, img))
    # a disparity ramp on a flat image: |dx d| = step / mean everywhere
    ramp = torch.arange(12.0).expand(1, 1, 10, 12) + 1.0
    flat = torch.zeros(1, 3, 10, 12)
    torch.testing.assert_close(edge_aware_smoothness(ramp, flat), torch.tensor(1.0 / 6.5))
    # image edges damp the penalty
    edges = torch.zeros(1, 3, 10, 12)
    edges[..., ::2] = 1.0
    assert edge_aware_smoothness(ramp, edges) < edge_aware_smoothness(ramp, flat)
    with pytest.raises(ValueError, match="disp"):
        edge_aware_smoothness(torch.rand(2, 3, 10, 12), img)
    with pytest.raises(ValueError, match="img"):
        edge_aware_smoothness(disp, torch.rand(2, 3, 10, 11))


def test_second_order_smoothness_is_zero_on_planes_and_not_on_kinks():
    """order 2 penalises curvature of the disparity: nothing on a plane's disparity (affine in the
    pixel coordinates), which order 1 does penalise; a kink costs; image edges damp it."""
    y, x = torch.meshgrid(torch.arange(10.0), torch.arange(12.0), indexing="ij")
    plane = (0.5 + 0.1 * x + 0.3 * y)[None, None]
    flat = torch.zeros(1, 3, 10, 12)
    assert float(edge_aware_smoothness(plane, flat, order=2)) == pytest.approx(0.0, abs=1e-6)
    assert float(edge_aware_smoothness(plane, flat, order=1)) > 0.1
    kink = (1.0 + (x - 6).abs())[None, None]
    # one column of |dxx| = 2 / mean among 10 second-difference columns
    torch.testing.assert_close(edge_aware_smoothness(kink, flat, order=2), 2 / kink.mean() / 10)
    edges = torch.zeros(1, 3, 10, 12)
    edges[..., 6:] = 1.0
    assert edge_aware_smoothness(kink, edges, order=2) < edge_aware_smoothness(kink, flat, order=2)
    with pytest.raises(ValueError, match="order"):
        edge_aware_smoothness(plane, flat, order=3)
    with pytest.raises(ValueError, match="disp: needs H, W >= 3"):
        edge_aware_smoothness(torch.ones(1, 1, 2, 5), torch.zeros(1, 3, 2, 5), order=2)


def test_chamfer_matches_brute_force_and_chunks():
    g = torch.Generator().manual_seed(2)
    p = torch.randn(2, 300, 3, generator=g, dtype=torch.float64) * 20 + 50  # far from the origin
    q = torch.randn(2, 170, 3, generator=g, dtype=torch.float64) * 20 + 50
    d = ((p[:, :, None] - q[:, None]) ** 2).sum(-1)
    want = d.min(2).values.mean(1) + d.min(1).values.mean(1)
    torch.testing.assert_close(chamfer_distance(p, q), want)
    torch.testing.assert_close(chamfer_distance(p, q, max_elems=1000), want)  # many small chunks
    assert torch.equal(chamfer_distance(p, p), torch.zeros(2, dtype=torch.float64))
    # float32 world coordinates 5 km from the origin keep their precision (clouds are centred)
    far_p, far_q = (p + 5000).float(), (q + 5000).float()
    d64 = ((far_p.double()[:, :, None] - far_q.double()[:, None]) ** 2).sum(-1)
    want64 = d64.min(2).values.mean(1) + d64.min(1).values.mean(1)
    torch.testing.assert_close(chamfer_distance(far_p, far_q).double(), want64, rtol=1e-4, atol=0)
    pg = p.clone().requires_grad_(True)
    chamfer_distance(pg, q).sum().backward()
    assert torch.isfinite(pg.grad).all() and pg.grad.abs().sum() > 0


def test_chamfer_input_checks():
    with pytest.raises(ValueError, match=r"p: expected shape \[B, N, 3\]"):
        chamfer_distance(torch.rand(1, 5, 2), torch.rand(1, 5, 3))
    with pytest.raises(ValueError, match="batch sizes differ"):
        chamfer_distance(torch.rand(1, 5, 3), torch.rand(2, 5, 3))
    q = torch.rand(1, 5, 3)
    q[0, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="q: contains NaN"):
        chamfer_distance(torch.rand(1, 5, 3), q)
