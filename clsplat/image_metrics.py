"""Image metrics that the engine's baseline and the model families both report: PSNR and SSIM,
defined once here so their figures are comparable.

SSIM is Wang et al.'s index over an 11x11 Gaussian window (sigma 1.5), data range 1,
``C1 = 0.01²``, ``C2 = 0.03²``, no epsilon (``kornia.metrics.ssim`` with ``eps=0``). Which padding
is used where, and why:

* **'valid'** -- the *metric* (:func:`ssim`): only windows wholly inside the image, averaged over
  them and the channels, as scikit-image's ``structural_similarity(gaussian_weights=True)`` and
  the original MATLAB code; this is what papers report. Used by every model family's evaluation
  (``clsplat.models.common.metrics`` re-exports it) and by the engine's oracle-depth baseline
  (:mod:`clsplat.pixel_recon`), so the baseline's SSIM is comparable with the models'.
* **'same'** -- a *masked training loss* (:func:`ssim_map` with ``padding="same"``): the map keeps
  ``H x W`` (reflect padding, kornia's ``'same'``) so that it lines up pixel for pixel with a mask,
  as 3DGS's ``1 - SSIM`` term does; AutoSplat's background loss
  (``models/autosplat/background.py``) uses it.
* monodepth2's photometric loss uses a different SSIM (3x3 box window), which stays with the
  model losses (``models/common/losses.py::ssim_map3``): it is a loss, not this metric.

All functions check their input and raise ``ValueError`` naming the argument. SSIM needs kornia
(the ``models`` extra; imported when first used, so PSNR and the input checks work without it).
"""
from __future__ import annotations

from typing import Literal, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["SSIM_WINDOW", "check_image_pair", "psnr", "ssim", "ssim_map"]

#: side of SSIM's Gaussian window: images must be at least this high and wide ('valid'), or more
#: than half of it ('same').
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5                 # the window's standard deviation, pixels (Wang et al.)
SSIM_C1 = (0.01 * 1.0) ** 2      # the stabilisers for a data range of 1, as kornia forms them
SSIM_C2 = (0.03 * 1.0) ** 2


def check_image_pair(a: Tensor, b: Tensor, name_a: str = "a", name_b: str = "b", channels: int | None = None,
                     finite: bool = True) -> None:
    """ValueError unless ``a`` and ``b`` are floating [B, C, H, W] tensors of one shape (with
    ``C == channels`` when given), and finite unless ``finite=False`` (a loss skips that scan of
    every pixel and lets a NaN reach the trainer's own guard)."""
    for t, name in ((a, name_a), (b, name_b)):
        if not isinstance(t, Tensor):
            raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
        if t.dim() != 4 or (channels is not None and t.shape[1] != channels):
            c = "C" if channels is None else str(channels)
            raise ValueError(f"{name}: expected shape [B, {c}, H, W], got {list(t.shape)}")
        if not t.is_floating_point():
            raise ValueError(f"{name}: expected a floating-point tensor, got {t.dtype}")
        if finite and not torch.isfinite(t).all():
            raise ValueError(f"{name}: contains NaN or inf")
    if a.shape != b.shape:
        raise ValueError(f"{name_a} and {name_b}: shapes differ, {list(a.shape)} vs {list(b.shape)}")


def _mask(mask: Optional[Tensor], like: Tensor, name: str = "mask") -> Optional[Tensor]:
    """A [B, 1, H, W] or [B, H, W] mask as a float [B, 1, H, W] tensor (non-zero = used)."""
    if mask is None:
        return None
    if not isinstance(mask, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor or None, got {type(mask).__name__}")
    B, _, H, W = like.shape
    if mask.dim() == 3:
        mask = mask[:, None]
    if mask.shape != (B, 1, H, W):
        raise ValueError(f"{name}: expected shape [{B}, 1, {H}, {W}] or [{B}, {H}, {W}], got {list(mask.shape)}")
    return (mask != 0).to(like.dtype)


def psnr(pred: Tensor, target: Tensor, mask: Optional[Tensor] = None) -> Tensor:
    """Peak signal-to-noise ratio in dB per image, ``-10 log10(MSE)``, both images clipped to
    [0, 1] first; with ``mask``, the MSE is over the masked pixels (all channels) only.

    pred, target: [B, C, H, W]; mask: [B, 1, H, W] or [B, H, W] (bool or 0/1) -> [B].
    Identical images give inf; an image with an empty mask gives NaN.
    """
    check_image_pair(pred, target, "pred", "target")
    m = _mask(mask, pred)
    err = (pred.clamp(0, 1) - target.clamp(0, 1)) ** 2
    if m is None:
        mse = err.mean(dim=(1, 2, 3))
    else:
        mse = (err * m).sum(dim=(1, 2, 3)) / (m.sum(dim=(1, 2, 3)) * pred.shape[1])
    return -10.0 * torch.log10(mse)


def ssim_map(pred: Tensor, target: Tensor, padding: Literal["same", "valid"] = "valid") -> Tensor:
    """Per-pixel SSIM map over the 11x11 Gaussian window (see the module docstring); the images
    are **not** clipped nor scanned for NaN (usable as a differentiable loss on raw renders).

    pred, target: [B, C, H, W] -> [B, C, H, W] (``padding="same"``, reflect-padded; needs
    H, W >= 6) or [B, C, H - 10, W - 10] (``padding="valid"``; needs H, W >= 11).
    """
    check_image_pair(pred, target, "pred", "target", finite=False)
    if padding not in ("same", "valid"):
        raise ValueError(f"padding: expected 'same' or 'valid', got {padding!r}")
    need = SSIM_WINDOW if padding == "valid" else SSIM_WINDOW // 2 + 1
    if min(pred.shape[-2:]) < need:
        raise ValueError(f"pred: SSIM's 11x11 window with padding={padding!r} needs H, W >= {need}, "
                         f"got {list(pred.shape[-2:])}")
    return _ssim_map(pred, target, padding)


def _ssim_map(a: Tensor, b: Tensor, padding: str) -> Tensor:
    """:func:`ssim_map` without the checks: ``kornia.metrics.ssim(a, b, 11, max_val=1, eps=0,
    padding=padding)`` with its five local moments (means, second moments, cross moment) stacked as
    one [B, 5C, H, W] image and filtered by one pair of depthwise convolutions, not five. The map is
    kornia's bit for bit on colour images (the same products, sums and filter; tested; one
    single-channel image differs by ~1e-6, where oneDNN convolves kornia's one channel another way);
    gradients agree to float rounding (~1e-7 relative: autograd sums the three paths into ``a`` in
    another order), so training runs from before this change are not reproduced bit for bit. On the CPU
    in float32 the stack is filtered channels-last (oneDNN otherwise copies an NCHW image into
    channel blocks around each depthwise convolution). A 480x270 six-camera AutoSplat frame,
    forward and backward: 0.55x kornia's time (bench/notes/shared_nets_losses_metrics.md).

    a, b: [B, C, H, W] floating -> [B, C, H, W] ('same') or [B, C, H - 10, W - 10] ('valid')."""
    from kornia.filters import get_gaussian_kernel1d

    out_dtype = torch.promote_types(a.dtype, b.dtype)
    dtype = torch.float32 if out_dtype in (torch.float16, torch.bfloat16) else out_dtype
    a, b = a.to(dtype), b.to(dtype)
    C, r = a.shape[1], SSIM_WINDOW // 2
    kernel = get_gaussian_kernel1d(SSIM_WINDOW, SSIM_SIGMA, device=a.device, dtype=dtype)
    x = torch.cat([a, b, a**2, b**2, a * b], 1)
    if a.device.type == "cpu" and dtype == torch.float32:
        x = x.contiguous(memory_format=torch.channels_last)
    n = 5 * C
    x = F.conv2d(F.pad(x, [r, r, 0, 0], mode="reflect"), kernel.view(1, 1, 1, -1).expand(n, 1, 1, -1), groups=n)
    x = F.conv2d(F.pad(x, [0, 0, r, r], mode="reflect"), kernel.view(1, 1, -1, 1).expand(n, 1, -1, 1), groups=n)
    if padding == "valid":
        x = x[..., r:-r, r:-r]
    mu1, mu2, m11, m22, m12 = x.contiguous().split(C, 1)
    # kornia's arithmetic, term for term, so that the map is its own
    mu1_sq, mu2_sq, mu1_mu2 = mu1**2, mu2**2, mu1 * mu2
    num = (2.0 * mu1_mu2 + SSIM_C1) * (2.0 * (m12 - mu1_mu2) + SSIM_C2)
    den = (mu1_sq + mu2_sq + SSIM_C1) * ((m11 - mu1_sq) + (m22 - mu2_sq) + SSIM_C2)
    return (num / (den + 0.0)).to(out_dtype)


def ssim(pred: Tensor, target: Tensor) -> Tensor:
    """Mean SSIM per image, the metric: images clipped to [0, 1], the 'valid' map of
    :func:`ssim_map` averaged over windows and channels (scikit-image's ``structural_similarity``
    with ``gaussian_weights=True``).

    pred, target: [B, C, H, W] with H, W >= 11 -> [B].
    """
    check_image_pair(pred, target, "pred", "target")
    return ssim_map(pred.clamp(0, 1), target.clamp(0, 1), "valid").mean(dim=(1, 2, 3))
