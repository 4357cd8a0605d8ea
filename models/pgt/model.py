"""The PGT model: V source views -> one Gaussian per source pixel (GPS-Gaussian+), with EcoSplat's
budget κ when the stage-2 heads are present.

Pipeline (:meth:`PGT.forward`): shared residual U-Net encoder (1/2, 1/4, 1/8) -> epipolar matching
at 1/8 (coarse normalised inverse depth u0) -> decoder to full resolution -> depth residual head
(u = u0 + 0.5·tanh(r)) -> parameter heads -> unprojection of every pixel centre to its depth along
its own ray (world frame = the frame of ``cam_to_world``) and rotation of the camera-frame
quaternions and SH into that frame.

With κ < 1 (after :meth:`PGT.enable_budget`), the copied heads (:class:`~.budget.BudgetHeads`)
give the parameters and K_v pixels per view are kept (K_v from the views' high-frequency
energy): the top-K_v by their opacity (EcoSplat, ``selection="topk"``) or, with
``selection="stratified"``, spread in proportion to the score (:func:`~.budget.stratified_mask`);
the score is the opacity, or the importance head's when the preset has one. κ = 1 (or None)
never runs the copies: it is the base model, bitwise; ``full=True`` runs the copies at κ (1
included) and keeps every Gaussian: the finetuned parameters unpruned (issue 33's controls select
from them). With ``kappa_decoder`` > 0 the copied heads
read features from κ-conditioned copies of the decoder's last stages (:class:`~.budget.KappaDecoder`);
the depth is still the base decoder's.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from clsplat.models.common.backbones import ResidualUNetEncoder
from clsplat.models.common.gaussians import GaussianSet, rotate_sh
from clsplat.models.common.geometry import check_rigid, matrix_to_quat, quat_multiply, unproject

from .budget import (BudgetHeads, check_kappa, cross_view_coverage, fill_gain, per_view_budgets, stratified_mask,
                     topk_mask, view_weights)
from .heads import Decoder, DepthResidualHead, GaussianHeads, activate
from .matching import make_matcher, u_to_depth
from .presets import PGTPreset

__all__ = ["PGT", "PGTOutput", "check_views", "count_parameters", "learned_selection"]

_MEAN, _STD = 0.45, 0.225  # input normalisation (monodepth2's)


@dataclass
class PGTOutput:
    """Per-pixel predictions for V source views of H x W.

    u0, u: [V, H, W] coarse (upsampled matching) and refined normalised inverse depth;
    depth0, depth: the same as z-depth (metres); prob: [V, D, H/8, W/8] matching distribution;
    means [V, H, W, 3], quats [V, H, W, 4], scales [V, H, W, 3], opacities [V, H, W],
    sh [V, H, W, K, 3]: Gaussians in the world frame; keep: bool [V, H, W] (None: all kept);
    budgets: long [V] per-view counts (None without a budget); kappa: the budget used;
    footprint: [V, H, W] one pixel's width at the Gaussian's depth (depth / fx, metres);
    fill_window, scale_cap, fill_cap_px: see :meth:`gaussians`; importance: [V, H, W] the
    selection score in [0, 1] (None from the base heads); coverage: long [V, H, W] views seeing each pixel's
    point (None unless the budget path computed it); fill_log: [V, H, W, 3] per-axis log-multipliers
    of the fill widening from the budget heads (None: 0).
    """

    u0: Tensor
    u: Tensor
    depth0: Tensor
    depth: Tensor
    prob: Tensor
    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    keep: Tensor | None = None
    budgets: Tensor | None = None
    kappa: float = 1.0
    footprint: Tensor | None = None
    fill_window: int = 0
    scale_cap: float = float("inf")
    fill_cap_px: float = 0.0
    importance: Tensor | None = None
    coverage: Tensor | None = None
    fill_log: Tensor | None = None

    def gaussians(self, keep: Tensor | None = None) -> GaussianSet:
        """The kept Gaussians (``keep`` [V, H, W] bool overrides :attr:`keep`; None keeps all),
        view-major, row-major order.

        With a pruning mask and ``fill_window`` > 0, a kept Gaussian that stands for its pruned
        neighbours is widened to cover them: with g = 1/sqrt(share of kept pixels in the
        ``fill_window`` square around it) (:func:`~.budget.fill_gain`), its variance grows by
        (g² - 1)·(footprint/2)², i.e. from one pixel's area to g² pixels' (capped at ``scale_cap``
        metres, or at ``fill_cap_px`` footprints where that is larger). The same for every pruning
        method; nothing changes without a mask (or where g = 1). With learned ``fill_log`` (the
        budget heads', ``learned_fill``) the added variance is multiplied by exp(2·fill_log) per axis.
        """
        keep = self.keep if keep is None else keep
        if keep is not None and bool(keep.all()):   # nothing pruned: nothing to stand for, nothing widens
            keep = None
        scales = self.scales
        if keep is not None and self.fill_window > 0 and self.footprint is not None:
            g2 = fill_gain(keep, self.fill_window) ** 2
            extra = ((g2 - 1.0) * (0.5 * self.footprint) ** 2)[..., None]
            if self.fill_log is not None:
                extra = extra * torch.exp(2.0 * self.fill_log)
            scales = (scales ** 2 + extra).sqrt()
            scales = torch.minimum(scales, _cap(self.scale_cap, self.fill_cap_px, self.footprint)[..., None])
        g = GaussianSet(self.means.reshape(-1, 3), self.quats.reshape(-1, 4), scales.reshape(-1, 3),
                        self.opacities.reshape(-1), self.sh.reshape(-1, *self.sh.shape[-2:]))
        return g if keep is None else g.index(keep.reshape(-1))


def _cap(scale_cap: float, fill_cap_px: float, footprint: Tensor) -> Tensor:
    """[V, H, W] the largest scale of a pruned set's Gaussian: ``scale_cap`` metres, or
    ``fill_cap_px`` pixel footprints where that is larger (0: the metric cap alone)."""
    cap = torch.full_like(footprint, scale_cap)
    return torch.maximum(cap, fill_cap_px * footprint) if fill_cap_px > 0 else cap


def learned_selection(importance: Tensor, budgets: Tensor, selection: str) -> Tensor:
    """bool [V, H, W]: the budget stage's own choice of ``budgets[v]`` pixels per view from the
    score ``importance`` [V, H, W]: top-K (``selection="topk"``, EcoSplat) or spread in proportion
    to it (``"stratified"``)."""
    return topk_mask(importance, budgets) if selection == "topk" else stratified_mask(importance, budgets)


def check_views(images: Tensor, Ks: Tensor, cam_to_world: Tensor) -> None:
    """ValueError naming the argument for: fewer than 2 views, wrong or mismatched shapes, sizes
    that are not multiples of 8, NaN/Inf, non-rigid poses."""
    if not isinstance(images, Tensor) or images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"images: expected [V, 3, H, W], got {list(getattr(images, 'shape', []))}")
    V, _, H, W = images.shape
    if V < 2:
        raise ValueError(f"images: PGT needs at least 2 source views, got {V}")
    if H % 8 or W % 8:
        raise ValueError(f"images: height and width must be multiples of 8, got {H}x{W}")
    for t, name, shape in ((Ks, "Ks", (V, 3, 3)), (cam_to_world, "cam_to_world", (V, 4, 4))):
        if not isinstance(t, Tensor) or tuple(t.shape) != shape:
            raise ValueError(f"{name}: expected shape {list(shape)} to match images' {V} views, "
                             f"got {list(getattr(t, 'shape', []))}")
    for t, name in ((images, "images"), (Ks, "Ks"), (cam_to_world, "cam_to_world")):
        if not torch.isfinite(t).all():
            raise ValueError(f"{name}: contains NaN or Inf")
    if (Ks[:, 0, 0] <= 0).any() or (Ks[:, 1, 1] <= 0).any():
        raise ValueError("Ks: focal lengths must be positive")
    for v in range(V):
        check_rigid(cam_to_world[v], f"cam_to_world[{v}]")


class PGT(nn.Module):
    """Pixel-aligned Gaussian predictor (see the module docstring).

    Args:
        preset: a :class:`~clsplat.models.pgt.presets.PGTPreset`.
    """

    def __init__(self, preset: PGTPreset) -> None:
        super().__init__()
        self.preset = preset
        p = preset
        self.encoder = ResidualUNetEncoder(3, p.channels, p.norm)
        self.matcher = make_matcher(p)
        self.decoder = Decoder(p.channels, p.decoder_channels, p.head_channels, p.norm)
        self.depth_head = DepthResidualHead(p.head_channels) if p.residual else None
        self.heads = GaussianHeads(p.head_channels, p.sh_coeffs if p.colour == "sh" else 0)
        self.budget: BudgetHeads | None = None

    def enable_budget(self) -> "PGT":
        """Add EcoSplat's stage-2 heads (copies of the current parameter heads + zero rate
        embedding) and freeze everything else. Idempotent."""
        if self.budget is None:
            p = self.preset
            self.budget = BudgetHeads(self.heads, p.head_channels, p.rate_kernel, importance=p.importance_head,
                                      coverage=p.coverage_input, colour=p.budget_colour, fill=p.learned_fill,
                                      decoder=self.decoder, decoder_stages=p.kappa_decoder, film=p.kappa_film)
        for name, prm in self.named_parameters():
            prm.requires_grad_(name.startswith("budget."))
        return self

    def forward(self, images: Tensor, Ks: Tensor, cam_to_world: Tensor, kappa: float | None = None,
                full: bool = False) -> PGTOutput:
        """Predict one Gaussian per source pixel.

        Args:
            images: [V, 3, H, W] in [0, 1], V >= 2, H and W multiples of 8.
            Ks: [V, 3, 3] intrinsics.
            cam_to_world: [V, 4, 4] camera-to-world poses (OpenCV cameras).
            kappa: budget ratio in (0, 1]; None or 1 = every Gaussian, from the base heads.
            full: with the budget stage, its copied heads at ``kappa`` (None: 1) and every Gaussian
                kept (``keep`` None; ``budgets`` and ``importance`` still those of κ, so a caller
                can apply another selection to the same finetuned parameters).
        Returns:
            :class:`PGTOutput`.
        """
        check_views(images, Ks, cam_to_world)
        kappa = 1.0 if kappa is None else check_kappa(kappa)
        if (kappa < 1.0 or full) and self.budget is None:
            what = "full=True" if full else f"kappa: {kappa} < 1"
            raise ValueError(f"{what} needs the budget stage (train --stage budget, or "
                             "enable_budget()); prune the base output with budget.topk_mask for baselines")
        finetuned = kappa < 1.0 or full
        p = self.preset
        V, _, H, W = images.shape
        f2, f4, f8 = self.encoder((images - _MEAN) / _STD)
        h, w = f8.shape[-2:]
        K8 = Ks.clone()
        K8[:, 0] *= w / W
        K8[:, 1] *= h / H
        matched, prob, u0_8 = self.matcher(f8, K8, cam_to_world)
        u0 = F.interpolate(u0_8[:, None], size=(H, W), mode="bilinear", align_corners=False)[:, 0]
        levels = self.decoder.levels(matched, u0_8, f2, f4, images, u0)
        feat = levels[-1]
        u = self.depth_head(feat, u0) if self.depth_head is not None else u0
        depth = u_to_depth(u, p.min_depth, p.max_depth)
        keep = budgets = importance = coverage = fill_log = None
        fx = Ks[:, 0, 0]
        if finetuned:
            share = None
            if p.coverage_input or (p.target == "density" and p.w_redundancy):
                coverage = cross_view_coverage(depth, Ks, cam_to_world, p.coverage_tol)[0]
                share = 1.0 / coverage.to(depth.dtype)
            # the depth stays the base's; with kappa_decoder the heads read κ-conditioned features
            bfeat = (feat if self.budget.decoder is None
                     else self.budget.decoder(self.decoder, levels, kappa, matched, u0_8, f2, f4, images, u0))
            raw = self.budget(bfeat, kappa, share)
            cap = (p.scale_cap if p.fill_cap_px <= 0
                   else _cap(p.scale_cap, p.fill_cap_px, depth / fx[:, None, None])[..., None])
        else:
            raw = self.heads(feat)
            cap = p.scale_cap
        g = activate(raw, depth, images, fx, cap, p.sh_degree if p.colour == "sh" else 0)
        if finetuned:
            budgets = per_view_budgets(kappa, view_weights(images, p.hf_temperature), H, W)
            importance = g["opacities"] if raw.importance is None else torch.sigmoid(raw.importance[:, 0])
            if not full:
                keep = learned_selection(importance, budgets, p.selection)
            if raw.fill is not None:  # bounded: at most e^1.5 = 4.5x wider or narrower per axis
                fill_log = 1.5 * torch.tanh(raw.fill.permute(0, 2, 3, 1))
        means = unproject(depth, Ks, cam_to_world)
        R = cam_to_world[:, :3, :3]
        quats = quat_multiply(matrix_to_quat(R)[:, None, None].expand(V, H, W, 4), g["quats"])
        sh = g["sh"]
        if sh.shape[-2] > 1:
            Kc = sh.shape[-2]
            sh = torch.stack([rotate_sh(sh[v].reshape(-1, Kc, 3), R[v]) for v in range(V)]).reshape(sh.shape)
        return PGTOutput(u0=u0, u=u, depth0=u_to_depth(u0, p.min_depth, p.max_depth), depth=depth, prob=prob, means=means,
                         quats=quats, scales=g["scales"], opacities=g["opacities"], sh=sh, keep=keep,
                         budgets=budgets, kappa=kappa, footprint=depth / Ks[:, 0, 0, None, None],
                         fill_window=p.fill_window, scale_cap=p.scale_cap, fill_cap_px=p.fill_cap_px,
                         importance=importance, coverage=coverage, fill_log=fill_log)

    @staticmethod
    def expected_count(kappa: float, views: int, height: int, width: int) -> int:
        """round(κ·V·H·W): the number of Gaussians a budget keeps."""
        return int(round(check_kappa(kappa) * views * height * width))


def count_parameters(module: nn.Module) -> int:
    """Number of parameters of ``module``."""
    return sum(p.numel() for p in module.parameters())

