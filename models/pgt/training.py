"""PGT's two training stages on top of :func:`clsplat.models.common.train.train`.

* stage ``base`` (GPS-Gaussian+): every parameter trains; per sample, the Gaussians of the source
  views render the target views and the source views; loss = render terms + w_depth·depth L1
  (data with depth) or + w_chamfer·Chamfer (without). AdamW(lr, wd), one-cycle, clip 1.0.
* stage ``budget`` (EcoSplat stage 2): starts from a base checkpoint; only the copied heads and
  the rate embedding train (with ``kappa_decoder``, also copies of the decoder's last stages); κ follows ``kappa_schedule``; samples have ``budget_views`` source
  views (> 2: the multi-view protocol, :func:`~.data.make_rig_sample`); the kept Gaussians render
  the target and source views; loss = render terms + L_io against ``target`` (EcoSplat's merged
  patches, or :func:`~.budget.density_target` with the cross-view share), on the importance
  head's score when there is one, else on the opacity.

Everything random in a sample (camera, t0, κ, Chamfer points) comes from
``sample_generator(seed, index)``, so resume and data parallelism are exact.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor, nn

from clsplat.models.common.train import sample_generator

from .budget import density_target, importance_target, io_loss, sample_kappa
from .data import make_sample, make_views_sample
from .losses import chamfer_term, depth_term, render_terms
from .model import PGT
from .presets import PGTPreset

__all__ = ["make_optimizer", "render_views", "make_sample_loss"]


def make_optimizer(model: nn.Module, preset: PGTPreset, steps: int, stage: str) -> tuple[torch.optim.Optimizer, object]:
    """AdamW over the trainable parameters and a one-cycle schedule over ``steps``."""
    lr = preset.lr if stage == "base" else preset.budget_lr
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=preset.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps + 1, pct_start=0.1,
                                                cycle_momentum=False)
    return opt, sched


def render_views(gaussians, viewmats: Tensor, Ks: Tensor, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Render ``gaussians`` into C cameras on a black background -> (rgb [C, 3, H, W], alpha [C, H, W, 1])."""
    C = viewmats.shape[0]
    bg = torch.zeros(C, 3, dtype=viewmats.dtype)
    rgb, alpha, _ = gaussians.render(viewmats, Ks, width, height, backgrounds=bg)
    return rgb.permute(0, 3, 1, 2), alpha


def make_sample_loss(source, preset: PGTPreset, stage: str, seed: int, lpips=None
                     ) -> Callable[[nn.Module, int, int], dict[str, Tensor]]:
    """The ``sample_loss(model, step, index)`` of a stage ("base" or "budget")."""
    if stage not in ("base", "budget"):
        raise ValueError(f"stage: expected 'base' or 'budget', got {stage!r}")

    def sample_loss(model: PGT, step: int, index: int) -> dict[str, Tensor]:
        gen = sample_generator(seed, index)
        if stage == "budget" and preset.budget_views != 2:
            s = make_views_sample(source, preset, index, preset.budget_views, "train", gen)
        else:
            s = make_sample(source, preset, index, "train", gen)
        kappa = sample_kappa(step, gen, preset.kappa_start, preset.kappa_decay, preset.kappa_interval,
                             preset.kappa_min, preset.kappa_max, preset.kappa_schedule) if stage == "budget" else None
        out = model(s.images, s.Ks, s.cam_to_world, kappa=kappa)
        viewmats = torch.cat([s.target_viewmats, torch.linalg.inv(s.cam_to_world)])
        Ks = torch.cat([s.target_Ks, s.Ks])
        rgb, alpha = render_views(out.gaussians(), viewmats, Ks, preset.width, preset.height)
        terms = render_terms(rgb, torch.cat([s.target_images, s.images]), preset, lpips)
        loss = terms["render"]
        if stage == "base":
            if s.depths is not None and preset.w_depth:
                terms["depth"] = depth_term(out.u, out.u0, s.depths, preset.min_depth, preset.max_depth)
                loss = loss + preset.w_depth * terms["depth"]
            elif preset.w_chamfer:
                terms["chamfer"] = chamfer_term(out.means, preset.chamfer_points, gen)
                loss = loss + preset.w_chamfer * terms["chamfer"]
        else:
            if preset.target == "density":
                share = None if out.coverage is None else 1.0 / out.coverage.to(out.depth.dtype)
                target = density_target(s.images, share, preset.target_floor, preset.w_redundancy)
            else:
                target = importance_target(s.images, out.budgets, preset.patch)
            terms["io"] = io_loss(out.importance, target, alpha, preset.w_io, preset.w_io_opacity)
            terms["kappa"] = torch.tensor(out.kappa)
            loss = loss + terms["io"]
        terms["loss"] = loss
        return terms

    return sample_loss
