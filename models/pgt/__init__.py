"""clsplat.models.pgt: pixel-aligned Gaussian prediction (GPS-Gaussian+) with EcoSplat's budget.

V >= 2 posed source views -> one Gaussian per source pixel, rendered through clsplat; a user
budget κ in (0, 1] keeps round(κ·V·H·W) of them, chosen by finetuned copies of the parameter heads.

    presets    tiny / small / paper (PGTPreset, registered under "pgt")
    matching   epipolar sampling at 1/8; plane-sweep cost volume or epipolar attention
    heads      decoder, depth residual head (u0 + 0.5·tanh r), rotation/scale/opacity/colour heads
    budget     EcoSplat stage 2: copied heads + rate embedding, per-view budgets, importance target, L_io
    model      PGT (forward -> PGTOutput -> GaussianSet)
    data       samples (source views, poses, targets) from clsplat.models.common.data
    losses     render L1 + SSIM (+ MSE, LPIPS), depth L1, Chamfer
    training   the base and budget stages' sample losses and optimiser
    evaluate   held-out quality, depth, the budget curve (budget.json / budget.png)
    cli        ``clsplat train pgt`` / ``clsplat eval pgt``
"""
from . import presets as _presets  # noqa: F401  (registers the presets under "pgt")
