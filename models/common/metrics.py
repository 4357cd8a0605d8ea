"""Evaluation metrics shared by the model families: PSNR and SSIM (the engine's
:mod:`clsplat.image_metrics`, re-exported here: 11x11 Gaussian window, 'valid' padding, the same
definition as the engine's oracle-depth baseline), depth errors in metric units, relative-pose
errors (translation in m and %, rotation in degrees), and LPIPS (VGG-16, v0.1 linear layers)
from local weight files only.

LPIPS is computed only from weights the user names; :func:`lpips_or_none` returns ``None`` and a
message saying the metric is off when there are none. A randomly initialised backbone is never
reported as LPIPS.
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Optional

import torch
from torch import Tensor, nn

from clsplat.image_metrics import SSIM_WINDOW, check_image_pair, psnr, ssim

from .backbones import VGG16, load_backbone_weights

__all__ = ["psnr", "ssim", "SSIM_WINDOW", "depth_metrics", "pose_errors", "LPIPS", "lpips_or_none", "LPIPS_OFF_MESSAGE"]

LPIPS_OFF_MESSAGE = "LPIPS off: no VGG-16 / LPIPS weights given (nothing is downloaded)"


def depth_metrics(
    pred: Tensor,
    gt: Tensor,
    mask: Optional[Tensor] = None,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
) -> dict:
    """Depth errors in metric units, with no median scaling, pooled over every valid pixel of the
    input (call once per image or camera and average for per-image means).

    Valid pixels: ``gt`` finite (sky = inf is ignored) and in ``(min_depth, max_depth)``, and
    ``mask`` non-zero when given. ``pred`` is clamped to ``[min_depth, max_depth]`` (monodepth2).

    pred, gt: same shape (e.g. [B, H, W] or [B, 1, H, W]); mask: same shape, bool or 0/1.
    Returns floats ``abs_rel = mean |p-g|/g``, ``sq_rel = mean (p-g)²/g``,
    ``rmse = sqrt(mean (p-g)²)``, ``delta1 = fraction with max(p/g, g/p) < 1.25``,
    ``scale_ratio = median(gt) / median(pred)`` and the int ``n_pixels``. With no valid pixel
    every float is NaN and ``n_pixels`` is 0 (so a camera that sees only sky aggregates cleanly).
    Raises ValueError on shape mismatch or a non-finite ``pred``.
    """
    if not isinstance(pred, Tensor) or not isinstance(gt, Tensor):
        raise ValueError("pred and gt: expected torch.Tensors")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt: shapes differ, {list(pred.shape)} vs {list(gt.shape)}")
    if not (0 <= min_depth < max_depth):
        raise ValueError(f"min_depth, max_depth: need 0 <= min_depth < max_depth, got {min_depth}, {max_depth}")
    pred, gt = pred.detach().double(), gt.detach().double()
    valid = torch.isfinite(gt) & (gt > min_depth) & (gt < max_depth)
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.shape != gt.shape:
            raise ValueError(f"mask: expected shape {list(gt.shape)}, got {list(getattr(mask, 'shape', []))}")
        valid &= mask != 0
    if not torch.isfinite(pred[valid]).all():
        raise ValueError("pred: contains NaN or inf at valid pixels")
    n = int(valid.sum())
    if n == 0:
        nan = math.nan
        return dict(abs_rel=nan, sq_rel=nan, rmse=nan, delta1=nan, scale_ratio=nan, n_pixels=0)
    p = pred[valid].clamp(min_depth, max_depth)
    g = gt[valid]
    diff = p - g
    thresh = torch.maximum(p / g, g / p)
    return dict(
        abs_rel=float((diff.abs() / g).mean()),
        sq_rel=float((diff * diff / g).mean()),
        rmse=float((diff * diff).mean().sqrt()),
        delta1=float((thresh < 1.25).double().mean()),
        scale_ratio=float(g.median() / p.median()),
        n_pixels=n,
    )


# --------------------------------------------------------------------------------------------
# LPIPS (Zhang et al. 2018), VGG-16 variant, v0.1 linear calibration
# --------------------------------------------------------------------------------------------
_LPIPS_CHANNELS = (64, 128, 256, 512, 512)
# The lpips ScalingLayer: inputs in [-1, 1] are shifted and scaled to ImageNet-like statistics.
_LPIPS_SHIFT = (-0.030, -0.088, -0.188)
_LPIPS_SCALE = (0.458, 0.448, 0.450)


class _LinLayer(nn.Module):
    """lpips's NetLinLayer: (dropout,) 1x1 conv C -> 1 without bias; named ``model.1`` as in
    the lpips weight files. Dropout is inert: LPIPS is always in eval mode."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, kernel_size=1, bias=False))

    def forward(self, x: Tensor) -> Tensor:
        return self.model(x)


def pose_errors(pred: Tensor, true: Tensor) -> dict[str, float]:
    """Errors of a predicted rigid motion against the true one.

    Args:
        pred, true: ``[4, 4]`` rigid motions in the same frame (e.g. a camera's motion between two
            instants, ``p_later = T p_earlier``).
    Returns:
        ``t_err_m`` (|t_pred - t_true|), ``t_err_pct`` (100 t_err / |t_true|; None when the true
        translation is below 1 mm), ``r_err_deg`` (angle of ``R_pred^T R_true``), ``t_pred_m`` and
        ``t_true_m`` (translation norms).
    """
    from .geometry import matrix_to_axis_angle

    for name, T in (("pred", pred), ("true", true)):
        if not isinstance(T, Tensor) or T.shape != (4, 4) or not torch.isfinite(T).all():
            raise ValueError(f"{name}: expected a finite [4, 4] rigid motion, got "
                             f"{list(T.shape) if isinstance(T, Tensor) else type(T).__name__}")
    P, G = pred.double(), true.double()
    t_err = float((P[:3, 3] - G[:3, 3]).norm())
    t_true = float(G[:3, 3].norm())
    angle = float(matrix_to_axis_angle(P[:3, :3].T @ G[:3, :3]).norm())
    return {"t_err_m": t_err, "t_err_pct": 100.0 * t_err / t_true if t_true >= 1e-3 else None,
            "r_err_deg": math.degrees(angle), "t_pred_m": float(P[:3, 3].norm()), "t_true_m": t_true}


def _load_lin(path: str) -> dict[str, Tensor]:
    """The lpips v0.1 ``vgg.pth`` state dict: ``lin{k}.model.1.weight`` of shape [1, C_k, 1, 1]."""
    if not os.path.isfile(path):
        raise ValueError(f"LPIPS linear weights: file {path!r} does not exist")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(f"LPIPS linear weights: cannot read {path!r} as a torch state dict ({exc})") from exc
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError(f"LPIPS linear weights: {path!r} is not a state dict, got {type(state).__name__}")
    expected = {f"lin{k}.model.1.weight": (1, c, 1, 1) for k, c in enumerate(_LPIPS_CHANNELS)}
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(
            f"LPIPS linear weights: {path!r} is not lpips v0.1 vgg.pth layout "
            f"(missing: {missing[:5] or 'none'}; unexpected: {unexpected[:5] or 'none'})"
        )
    for k, shape in expected.items():
        if tuple(state[k].shape) != shape:
            raise ValueError(
                f"LPIPS linear weights: {path!r} has {k} of shape {list(state[k].shape)}, expected {list(shape)}"
            )
    return dict(state)


class LPIPS(nn.Module):
    """Learned perceptual distance, lpips v0.1 with a VGG-16 backbone, from two local files:

    - ``vgg_weights``: a torchvision ``vgg16`` state dict (``features.*``; ``classifier.*`` ignored);
    - ``lin_weights``: the lpips wheel's ``lpips/weights/v0.1/vgg.pth`` (``lin0..lin4.model.1.weight``).

    ``forward(a, b)``: images [B, 3, H, W], H, W >= 16, in [0, 1] (mapped to [-1, 1], then lpips's shift/scale;
    computed in the module's dtype) -> [B]: per tap ``relu1_2 .. relu5_3``, channel-unit-normalised features, squared difference,
    the 1x1 linear weights, spatial mean; summed over taps. 0 for identical images. Parameters are
    frozen and the module stays in eval mode; gradients flow to the inputs (usable as a loss).
    ``self.message`` says what was loaded.
    """

    def __init__(self, vgg_weights: str | os.PathLike, lin_weights: str | os.PathLike) -> None:
        super().__init__()
        if vgg_weights is None or lin_weights is None:
            raise ValueError("vgg_weights, lin_weights: LPIPS needs both local files (use lpips_or_none for optional)")
        lin = _load_lin(os.fspath(lin_weights))
        self.net = VGG16()
        vgg_msg = load_backbone_weights(self.net, vgg_weights)
        for k, c in enumerate(_LPIPS_CHANNELS):
            setattr(self, f"lin{k}", _LinLayer(c))
        self.load_state_dict(lin, strict=False)
        self.register_buffer("shift", torch.tensor(_LPIPS_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_LPIPS_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()
        self.message = f"LPIPS on (VGG-16, v0.1): {vgg_msg}; linear layers from {os.fspath(lin_weights)}"

    def train(self, mode: bool = True) -> "LPIPS":
        return super().train(False)

    def forward(self, a: Tensor, b: Tensor) -> Tensor:
        check_image_pair(a, b, "a", "b", channels=3)
        if min(a.shape[-2:]) < 16:
            raise ValueError(f"a: LPIPS's VGG-16 needs H, W >= 16 (four 2x2 pools), got {list(a.shape[-2:])}")
        x = torch.cat([a, b], 0).to(self.shift.dtype) * 2.0 - 1.0  # the network's dtype
        x = (x - self.shift) / self.scale
        total = x.new_zeros(a.shape[0])
        for k, f in enumerate(self.net.lpips_features(x)):
            f = f / (f.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            fa, fb = f.chunk(2, 0)
            total = total + getattr(self, f"lin{k}")((fa - fb) ** 2).mean(dim=(1, 2, 3))
        return total


def lpips_or_none(
    vgg_weights: Optional[str | os.PathLike], lin_weights: Optional[str | os.PathLike]
) -> tuple[Optional[LPIPS], str]:
    """``(LPIPS, message)`` when both files are given, ``(None, LPIPS_OFF_MESSAGE)`` when neither is.
    One without the other, or a bad file, is a ValueError: a run never silently drops or fakes
    the metric."""
    if vgg_weights is None and lin_weights is None:
        return None, LPIPS_OFF_MESSAGE
    if vgg_weights is None or lin_weights is None:
        given, absent = ("lin_weights", "vgg_weights") if vgg_weights is None else ("vgg_weights", "lin_weights")
        raise ValueError(f"{absent}: LPIPS needs both the VGG-16 and the linear-layer files; only {given} was given")
    model = LPIPS(vgg_weights, lin_weights)
    return model, model.message
