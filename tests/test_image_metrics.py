"""The engine's image metrics: PSNR, SSIM (11x11 Gaussian window, 'valid' for the metric, 'same'
for a masked loss) against direct numpy implementations, and their input errors."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from clsplat.image_metrics import SSIM_WINDOW, psnr, ssim, ssim_map


def numpy_gaussian_ssim_map(a: np.ndarray, b: np.ndarray, padding: str) -> np.ndarray:
    """SSIM map of one channel over 11x11 Gaussian (sigma 1.5) windows, by loops: 'valid' keeps the
    windows inside the image, 'same' reflect-pads by 5 first (numpy's 'reflect': edge not repeated)."""
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    c1, c2 = 0.01**2, 0.03**2
    if padding == "same":
        a, b = np.pad(a, 5, mode="reflect"), np.pad(b, 5, mode="reflect")
    out = np.empty((a.shape[0] - 10, a.shape[1] - 10))
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            wa, wb = a[i : i + 11, j : j + 11], b[i : i + 11, j : j + 11]
            ma, mb = (w * wa).sum(), (w * wb).sum()
            va, vb = (w * wa**2).sum() - ma**2, (w * wb**2).sum() - mb**2
            cov = (w * wa * wb).sum() - ma * mb
            out[i, j] = (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
    return out


def test_psnr_known_values_mask_and_clipping():
    pred = torch.full((2, 3, 4, 5), 0.5)
    target = torch.full((2, 3, 4, 5), 0.6)
    torch.testing.assert_close(psnr(pred, target), torch.tensor([20.0, 20.0]))
    target[1] = 0.5 + 0.01  # mse 1e-4 -> 40 dB
    torch.testing.assert_close(psnr(pred, target), torch.tensor([20.0, 40.0]))
    # the mask selects pixels: outside it the error is huge, inside it is 0.1
    t2 = torch.full((1, 3, 4, 5), 0.6)
    t2[..., 2:, :] = 0.0
    mask = torch.zeros(1, 4, 5, dtype=torch.bool)
    mask[:, :2] = True
    torch.testing.assert_close(psnr(pred[:1], t2, mask), torch.tensor([20.0]))
    # values are clipped to [0, 1] before the error
    assert math.isinf(float(psnr(torch.full((1, 3, 4, 4), 1.7), torch.ones(1, 3, 4, 4))))
    # an empty mask gives NaN, not a number
    assert math.isnan(float(psnr(pred[:1], t2, torch.zeros(1, 4, 5))))


def test_ssim_of_an_image_with_itself_is_one():
    img = torch.rand(2, 3, 16, 16, dtype=torch.float64)
    torch.testing.assert_close(ssim(img, img), torch.ones(2, dtype=torch.float64))
    for padding in ("same", "valid"):
        torch.testing.assert_close(ssim_map(img, img, padding), torch.ones_like(ssim_map(img, img, padding)))


def test_ssim_flat_images_luminance_term():
    a, b = 0.3, 0.7
    want = (2 * a * b + 1e-4) / (a * a + b * b + 1e-4)
    got = ssim(torch.full((1, 3, 12, 12), a, dtype=torch.float64), torch.full((1, 3, 12, 12), b, dtype=torch.float64))
    torch.testing.assert_close(got, torch.tensor([want], dtype=torch.float64))


@pytest.mark.parametrize("padding", ["valid", "same"])
def test_ssim_map_matches_numpy_on_a_tiny_image(padding):
    gen = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 13, 14, dtype=torch.float64, generator=gen)
    noisy = img + 0.1 * torch.randn(img.shape, dtype=torch.float64, generator=gen)   # not clipped: a loss input
    got = ssim_map(noisy, img, padding)
    want = np.stack([np.stack([numpy_gaussian_ssim_map(noisy[i, c].numpy(), img[i, c].numpy(), padding)
                               for c in range(3)]) for i in range(2)])
    assert got.shape == ((2, 3, 3, 4) if padding == "valid" else (2, 3, 13, 14))
    torch.testing.assert_close(got, torch.from_numpy(want))


def test_ssim_metric_is_the_clipped_valid_map_mean():
    gen = torch.Generator().manual_seed(1)
    img = torch.rand(2, 3, 12, 15, dtype=torch.float64, generator=gen)
    noisy = img + 0.2 * torch.randn(img.shape, dtype=torch.float64, generator=gen)
    want = [np.mean([numpy_gaussian_ssim_map(noisy[i, c].clamp(0, 1).numpy(), img[i, c].numpy(), "valid")
                     for c in range(3)]) for i in range(2)]
    torch.testing.assert_close(ssim(noisy, img), torch.tensor(want, dtype=torch.float64))


def test_ssim_map_is_differentiable_and_passes_nan_to_the_caller():
    a = torch.rand(1, 3, 8, 8, requires_grad=True)
    b = torch.rand(1, 3, 8, 8)
    (1 - ssim_map(a, b, "same")).mean().backward()
    assert a.grad is not None and torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    bad = a.detach().clone()
    bad[0, 0, 0, 0] = float("nan")
    assert torch.isnan(ssim_map(bad, b, "same")).any()     # a loss leaves NaN to the trainer's guard


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("padding", ["valid", "same"])
def test_ssim_map_is_kornias_map_bit_for_bit_and_its_gradient_to_rounding(padding, dtype):
    """The five moments filtered as one stacked image give kornia's map exactly (RGB frames, the
    sizes the models render, one camera and six), and the gradient kornia's to float rounding."""
    from kornia.metrics import ssim as kornia_ssim

    gen = torch.Generator().manual_seed(2)
    for shape in ((1, 3, 48, 64), (6, 3, 67, 121)):
        a = torch.rand(shape, dtype=dtype, generator=gen)
        b = (a + 0.2 * torch.randn(shape, dtype=dtype, generator=gen)).clamp(0, 1)
        want = kornia_ssim(a, b, SSIM_WINDOW, max_val=1.0, eps=0.0, padding=padding)
        assert torch.equal(ssim_map(a, b, padding), want)
        g = torch.rand(want.shape, dtype=dtype, generator=gen)
        grads = []
        for f in (lambda x: kornia_ssim(x, b, SSIM_WINDOW, max_val=1.0, eps=0.0, padding=padding),
                  lambda x: ssim_map(x, b, padding)):
            x = a.clone().requires_grad_()
            (f(x) * g).sum().backward()
            grads.append(x.grad)
        rel = float((grads[0] - grads[1]).norm() / grads[0].norm())
        assert rel < (1e-6 if dtype == torch.float32 else 1e-13), rel


def test_ssim_map_gradcheck_and_mixed_precision():
    gen = torch.Generator().manual_seed(3)
    a = torch.rand(1, 2, 7, 8, dtype=torch.float64, generator=gen, requires_grad=True)
    b = torch.rand(1, 2, 7, 8, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x, y: ssim_map(x, y, "same"), (a, b))
    half = a.detach().to(torch.float16)
    assert ssim_map(half, half, "same").dtype == torch.float16                # computed in float32
    mixed = ssim_map(a.detach().float(), b.detach(), "same")
    assert mixed.dtype == torch.float64


def test_errors_name_the_argument():
    ok = torch.rand(1, 3, 16, 16)
    with pytest.raises(ValueError, match=r"^pred: expected a torch.Tensor"):
        ssim(np.zeros((1, 3, 16, 16)), ok)
    with pytest.raises(ValueError, match=r"^target: expected shape \[B, C, H, W\]"):
        ssim(ok, ok[0])
    with pytest.raises(ValueError, match=r"^pred and target: shapes differ"):
        psnr(ok, ok[:, :2])
    with pytest.raises(ValueError, match=r"^target: expected a floating-point tensor"):
        psnr(ok, (ok * 255).to(torch.uint8))
    bad = ok.clone()
    bad[0, 1, 2, 3] = float("inf")
    with pytest.raises(ValueError, match=r"^target: contains NaN or inf"):
        ssim(ok, bad)
    with pytest.raises(ValueError, match=r"^mask: expected shape \[1, 1, 16, 16\]"):
        psnr(ok, ok, torch.ones(1, 16, 15))
    with pytest.raises(ValueError, match=r"^padding: expected 'same' or 'valid'"):
        ssim_map(ok, ok, "reflect")
    small = torch.rand(1, 3, SSIM_WINDOW - 1, 16)
    with pytest.raises(ValueError, match=r"^pred: SSIM's 11x11 window with padding='valid' needs H, W >= 11"):
        ssim(small, small)
    tiny = torch.rand(1, 3, 5, 16)
    with pytest.raises(ValueError, match=r"^pred: SSIM's 11x11 window with padding='same' needs H, W >= 6"):
        ssim_map(tiny, tiny, "same")
