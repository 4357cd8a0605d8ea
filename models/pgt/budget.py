"""EcoSplat's stage 2: keep only the Gaussians a budget κ allows, and learn which ones.

* :class:`BudgetHeads`: copies of the parameter heads plus a zero-initialised 7x7 "rate
  embedding" of the κ map added into their input features (at initialisation the copies return
  exactly what the base heads return); optionally (issue 18) an importance head, colour and
  per-axis fill residual heads and a cross-view-share embedding, all starting as the base.
* :class:`KappaDecoder` (issue 18, lead 4): copies of the decoder's last stages with a κ FiLM
  (:class:`KappaFiLM`) on each stage's input, so the features themselves change with κ.
* :func:`high_frequency_energy` -> :func:`view_weights` (softmax of the max-normalised energy at
  temperature 0.3) -> :func:`per_view_budgets`: integers K_v <= H·W summing to exactly
  round(κ·V·H·W) (overflow of a full view goes to the others; rounding by largest remainder).
* :func:`topk_mask`: keep the top-K_v per view by a score (EcoSplat: the copied head's opacity;
  the ``opacity`` baseline: the base opacity); :func:`random_mask`, :func:`grid_mask` (one per
  cell of a uniform grid) and :func:`dedup_mask` (cross-view de-duplication, then uniform): the
  other baselines. :func:`stratified_mask`: exactly K_v pixels spread along a Hilbert curve with
  a density proportional to a score (issue 18: top-K piles the budget onto edges).
* :func:`cross_view_coverage`: how many views see each pixel's surface point (from the predicted
  depth), and whether an earlier view does.
* :func:`importance_target`: the 0/1 mask of pixels that survive when the lowest-gradient 4x4
  patches are merged into one pixel each, as many as K_v needs (EcoSplat's, ``target="merge"``);
  :func:`density_target`: a soft density from image detail (local Sobel energy) and, with
  ``w_redundancy`` > 0, the cross-view share (``target="density"``, issue 18).
* :func:`fill_gain`: how much a kept Gaussian grows to cover its pruned neighbours (not in
  EcoSplat; applied to every pruning method alike, see :meth:`~.model.PGTOutput.gaussians`).
* :func:`io_loss`: w_io·(w_op·BCE(opacity, target) + BCE(rendered alpha, 1)).
* :func:`sample_kappa`: the progressive schedule κ ~ U(max(0.85 - 0.05·⌊step/interval⌋, 0.05), 0.95),
  or (``schedule="log_uniform"``) log κ ~ U(log κ_min, log κ_max) from the first step.
"""
from __future__ import annotations

import copy
import functools
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .heads import GaussianHeads, RawGaussians

__all__ = ["BudgetHeads", "KappaDecoder", "KappaFiLM", "check_kappa", "high_frequency_energy", "view_weights", "per_view_budgets",
           "topk_mask", "random_mask", "grid_mask", "stratified_mask", "hilbert_order", "cross_view_coverage",
           "dedup_mask", "fill_gain", "importance_target", "density_target", "io_loss", "sample_kappa"]


def check_kappa(kappa) -> float:
    """κ as a float in (0, 1]; ValueError naming ``kappa`` otherwise."""
    if isinstance(kappa, Tensor):
        if kappa.numel() != 1:
            raise ValueError(f"kappa: expected a single number, got a tensor of shape {list(kappa.shape)}")
        kappa = kappa.item()
    if isinstance(kappa, bool) or not isinstance(kappa, (int, float)):
        raise ValueError(f"kappa: expected a number in (0, 1], got {kappa!r}")
    if not (math.isfinite(kappa) and 0.0 < kappa <= 1.0):
        raise ValueError(f"kappa: the budget ratio must be in (0, 1], got {kappa!r}")
    return float(kappa)


class KappaFiLM(nn.Module):
    """Per-channel scale and shift of a feature map by κ: x·(1 + γ(κ)) + β(κ), with (γ, β) an MLP
    of (κ, log κ) whose last layer starts at zero, so a fresh one is the identity (exactly: x·1 + 0).

    forward(x [V, C, H, W], kappa float) -> [V, C, H, W].
    """

    def __init__(self, channels: int, hidden: int = 32) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(2, hidden), nn.ReLU(), nn.Linear(hidden, 2 * channels))
        nn.init.zeros_(self.net[2].weight)
        nn.init.zeros_(self.net[2].bias)

    def forward(self, x: Tensor, kappa: float) -> Tensor:
        k = torch.tensor([kappa, math.log(kappa)], dtype=x.dtype, device=x.device)
        gamma, beta = self.net(k).chunk(2)
        return x * (1.0 + gamma[None, :, None, None]) + beta[None, :, None, None]


class KappaDecoder(nn.Module):
    """κ conditioning inside the decoder (issue 18, lead 4): trainable copies of the last
    ``stages`` stages of the base :class:`~.heads.Decoder` (1 = the full-resolution output conv,
    2 = also the 1/2 block, .. 4 = all), each reading its input through a :class:`KappaFiLM`
    (``film``; without it the copies are only extra capacity, the ablation of the κ input). It
    starts from the base decoder's intermediate output before the first copied stage, so a fresh
    one returns exactly the base decoder's features; only κ < 1 runs it (κ = 1 is the base model).

    forward(decoder, levels [the base's stage outputs, :meth:`~.heads.Decoder.levels`], kappa,
    matched, u0 [V, h, w], f2, f4, images, u0_full [V, H, W]) -> [V, head_channels, H, W].
    """

    def __init__(self, decoder: nn.Module, stages: int, film: bool = True) -> None:
        super().__init__()
        n = len(decoder.STAGES)
        if not 1 <= stages <= n:
            raise ValueError(f"stages: expected 1..{n}, got {stages}")
        self.first = n - stages
        self.stages = nn.ModuleList(copy.deepcopy(getattr(decoder, name)) for name in decoder.STAGES[self.first:])
        self.film = (nn.ModuleList(KappaFiLM(c) for c in decoder.in_channels[self.first:]) if film else None)

    def forward(self, decoder: nn.Module, levels: list[Tensor], kappa: float, matched: Tensor, u0: Tensor,
                f2: Tensor, f4: Tensor, images: Tensor, u0_full: Tensor) -> Tensor:
        x = levels[self.first - 1] if self.first > 0 else None
        for j, stage in enumerate(self.stages):
            inp = decoder.stage_input(self.first + j, x, matched, u0, f2, f4, images, u0_full)
            if self.film is not None:
                inp = self.film[j](inp, kappa)
            x = stage(inp)
        return x


class BudgetHeads(nn.Module):
    """A copy of ``heads`` reading features + rate_embed(κ map) (+ cover_embed(1/n map)).

    With ``importance``, an extra head (a copy of the opacity head, so it starts as the base
    opacity) gives the selection score, and the opacity is left to rendering (EcoSplat selects by
    the opacity itself). With ``coverage``, a zero-initialised 3x3 conv of the cross-view share
    1/n (:func:`cross_view_coverage`, from the model's own depth) is added to the features too.
    With ``decoder_stages`` > 0, a :class:`KappaDecoder` (copies of the base decoder's last stages,
    conditioned on κ) gives the features these heads read (the model runs it).
    With ``colour`` and base heads without a colour head (colour from the source pixel), a
    zero-initialised colour residual head lets a kept Gaussian take the colour of what it stands
    for (its pruned neighbours), not only its own pixel's. With ``fill``, a zero-initialised head
    gives per-axis log-multipliers of the fill widening (:meth:`~.model.PGTOutput.gaussians`), so a
    kept Gaussian can stretch along an edge and stay thin across it instead of growing round.

    forward(feat [V, C, H, W], kappa float, share [V, H, W] or None) -> :class:`RawGaussians`
    (``importance`` [V, 1, H, W] logits when the head exists).
    """

    def __init__(self, heads: GaussianHeads, channels: int, kernel: int = 7, importance: bool = False,
                 coverage: bool = False, colour: bool = False, fill: bool = False, decoder: nn.Module | None = None,
                 decoder_stages: int = 0, film: bool = True) -> None:
        super().__init__()
        self.heads = copy.deepcopy(heads)
        #: κ conditioning in the decoder (``decoder_stages`` > 0): the model runs it and passes its
        #: features to :meth:`forward` in place of the base decoder's
        self.decoder = KappaDecoder(decoder, decoder_stages, film) if decoder_stages > 0 else None
        self.rate = nn.Conv2d(1, channels, kernel, padding=kernel // 2)
        nn.init.zeros_(self.rate.weight)
        nn.init.zeros_(self.rate.bias)
        self.importance = copy.deepcopy(heads.opacity) if importance else None
        self.cover = None
        if coverage:
            self.cover = nn.Conv2d(1, channels, 3, padding=1)
            nn.init.zeros_(self.cover.weight)
            nn.init.zeros_(self.cover.bias)
        self.colour = None
        if colour and heads.colour is None:
            self.colour = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True),
                                        nn.Conv2d(channels, 3, 1))
            nn.init.zeros_(self.colour[2].weight)
            nn.init.zeros_(self.colour[2].bias)
        self.fill = None
        if fill:
            self.fill = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True),
                                      nn.Conv2d(channels, 3, 1))
            nn.init.zeros_(self.fill[2].weight)
            nn.init.zeros_(self.fill[2].bias)

    def forward(self, feat: Tensor, kappa: float, share: Tensor | None = None) -> RawGaussians:
        V, _, H, W = feat.shape
        kmap = torch.full((V, 1, H, W), float(kappa), dtype=feat.dtype, device=feat.device)
        x = feat + self.rate(kmap)
        if self.cover is not None:
            if share is None:
                raise ValueError("share: the coverage-conditioned budget heads need the cross-view share map")
            x = x + self.cover(share[:, None].to(feat.dtype))
        raw = self.heads(x)
        if self.colour is not None:
            raw.colour = self.colour(x)
        if self.fill is not None:
            raw.fill = self.fill(x)
        if self.importance is not None:
            raw.importance = self.importance(x)
        return raw


def high_frequency_energy(images: Tensor) -> Tensor:
    """[V, 3, H, W] in [0, 1] -> [V]: mean squared difference between each view's grey image and
    its 5x5 Gaussian blur (σ = 1 px), i.e. the energy above about a quarter of the sampling rate."""
    import kornia
    grey = images.mean(1, keepdim=True)
    blur = kornia.filters.gaussian_blur2d(grey, (5, 5), (1.0, 1.0), border_type="reflect")
    return ((grey - blur) ** 2).mean((1, 2, 3))


def view_weights(images: Tensor, temperature: float = 0.3) -> Tensor:
    """[V] softmax(e_v / max(e) / T) of the high-frequency energies; sums to 1."""
    e = high_frequency_energy(images)
    return torch.softmax(e / e.max().clamp_min(1e-12) / temperature, 0)


def per_view_budgets(kappa: float, weights: Tensor, height: int, width: int) -> Tensor:
    """Integer budgets K_v (long [V]) with Σ K_v = round(κ·V·H·W) and 0 <= K_v <= H·W, split in
    proportion to ``weights`` [V]; a view's share above H·W goes to the others in proportion."""
    kappa = check_kappa(kappa)
    V, P = weights.shape[0], height * width
    total = int(round(kappa * V * P))
    w = weights.detach().double().clamp_min(0)
    share = torch.zeros(V, dtype=torch.float64)
    full = torch.zeros(V, dtype=torch.bool)
    left = float(total)
    for _ in range(V):  # water-filling: at most V rounds
        free = ~full
        share[free] = left * w[free] / w[free].sum().clamp_min(1e-300)
        over = free & (share > P)
        if not over.any():
            break
        full |= over
        share[full] = P
        left = total - P * int(full.sum())
    k = share.floor().long().clamp_max(P)
    rest = total - int(k.sum())
    if rest > 0:  # largest remainders first, among views with room
        frac = (share - k.double()).masked_fill(k >= P, -1.0)
        for i in torch.argsort(frac, descending=True, stable=True)[:rest]:
            k[i] += 1
    return k.to(weights.device)


def topk_mask(scores: Tensor, budgets: Tensor) -> Tensor:
    """bool [V, H, W]: per view, the ``budgets[v]`` pixels with the highest ``scores`` [V, H, W]."""
    V, H, W = scores.shape
    flat = scores.detach().reshape(V, H * W)
    order = torch.argsort(flat, dim=1, descending=True, stable=True)
    rank = torch.empty_like(order)
    rank.scatter_(1, order, torch.arange(H * W, device=scores.device).expand(V, -1))
    return (rank < budgets.to(scores.device)[:, None]).reshape(V, H, W)


def random_mask(budgets: Tensor, height: int, width: int, generator: torch.Generator | None = None) -> Tensor:
    """bool [V, H, W]: ``budgets[v]`` pixels of view v chosen uniformly at random."""
    V = budgets.shape[0]
    scores = torch.rand(V, height, width, generator=generator)
    return topk_mask(scores, budgets.cpu()).to(budgets.device)


@functools.lru_cache(maxsize=16)
def _hilbert_order_np(height: int, width: int) -> np.ndarray:
    n = 1
    while n < max(height, width):
        n *= 2
    d = np.arange(n * n, dtype=np.int64)
    x = np.zeros_like(d)
    y = np.zeros_like(d)
    t = d.copy()
    s = 1
    while s < n:  # the classic d -> (x, y) of a Hilbert curve, vectorised over d
        rx = 1 & (t // 2)
        ry = 1 & (t ^ rx)
        flip = (ry == 0) & (rx == 1)
        x = np.where(flip, s - 1 - x, x)
        y = np.where(flip, s - 1 - y, y)
        swap = ry == 0
        x, y = np.where(swap, y, x), np.where(swap, x, y)
        x = x + s * rx
        y = y + s * ry
        t = t // 4
        s *= 2
    inside = (x < width) & (y < height)
    return (y * width + x)[inside]


def hilbert_order(height: int, width: int) -> Tensor:
    """long [H·W]: the flat pixel indices (row-major) in the order a Hilbert curve over the
    enclosing power-of-two square visits them (pixels outside the image skipped): consecutive
    pixels are neighbours, and any run of them is a compact blob."""
    return torch.from_numpy(_hilbert_order_np(int(height), int(width)).copy())


def _stratified_view(density: Tensor, k: int, order: Tensor) -> Tensor:
    """bool [P]: exactly k of P pixels, density-proportional, stratified along ``order``."""
    P = density.numel()
    keep = torch.zeros(P, dtype=torch.bool)
    if k <= 0:
        return keep
    if k >= P:
        return ~keep
    d = density.detach().reshape(-1).cpu().double().clamp_min(0.0)[order] + 1e-12
    # water-filling: x = min(c·d, 1) with Σ x = k, so that no pixel is due more than one pick
    full = torch.zeros(P, dtype=torch.bool)
    x = d
    for _ in range(P):
        c = (k - int(full.sum())) / float(d[~full].sum())
        x = torch.where(full, torch.ones_like(d), c * d)
        new = (~full) & (x >= 1.0)
        if not new.any():
            break
        full |= new
    x = x.clamp_max(1.0)
    cum = torch.cumsum(x, 0)
    picks = torch.floor(cum + 0.5) > torch.floor(cum - x + 0.5)  # one pick per unit of mass
    n = int(picks.sum())
    if n < k:  # rounding: top up with the largest unpicked mass
        cand = torch.where(picks, torch.full_like(x, -1.0), x)
        picks[torch.argsort(cand, descending=True, stable=True)[:k - n]] = True
    elif n > k:
        cand = torch.where(picks, x, torch.full_like(x, 2.0))
        picks[torch.argsort(cand, stable=True)[:n - k]] = False
    keep[order[picks]] = True
    return keep


def stratified_mask(density: Tensor, budgets: Tensor) -> Tensor:
    """bool [V, H, W]: per view exactly ``budgets[v]`` pixels, chosen with a probability
    proportional to ``density`` [V, H, W] (>= 0) and spread out: the density, capped so no pixel
    is due more than one pick (water-filling), is accumulated along a Hilbert curve and one pixel
    is taken per unit of mass (systematic sampling). A uniform density gives an even blue-noise-like
    thinning; a density 4x higher on edges gives them 4x the samples, still spread."""
    V, H, W = density.shape
    order = hilbert_order(H, W)
    out = torch.stack([_stratified_view(density[v], int(budgets[v]), order).reshape(H, W) for v in range(V)])
    return out.to(density.device)


def grid_mask(budgets: Tensor, height: int, width: int) -> Tensor:
    """bool [V, H, W]: uniform grid thinning, one pixel (the cell's centre) per c x c cell, c the
    largest cell size with at least ``budgets[v]`` cells; when there are more cells than the
    budget, cells evenly spaced along a Hilbert curve over the cell grid are kept (exact counts)."""
    V, P = budgets.shape[0], height * width
    out = torch.zeros(V, P, dtype=torch.bool)
    for v in range(V):
        k = int(budgets[v])
        if k >= P:
            out[v] = True
            continue
        if k <= 0:
            continue
        c = max(1, int(math.floor(math.sqrt(P / k))))
        while c > 1 and math.ceil(height / c) * math.ceil(width / c) < k:
            c -= 1
        ys = torch.clamp(torch.arange(0, height, c) + c // 2, max=height - 1)
        xs = torch.clamp(torch.arange(0, width, c) + c // 2, max=width - 1)
        cells = (ys[:, None] * width + xs[None, :]).reshape(-1)[hilbert_order(len(ys), len(xs))]
        n = cells.numel()
        pick = torch.floor((torch.arange(k, dtype=torch.float64) + 0.5) * n / k).long()
        out[v, cells[pick]] = True
    return out.reshape(V, height, width).to(budgets.device)


def cross_view_coverage(depth: Tensor, Ks: Tensor, cam_to_world: Tensor, rel_tol: float = 0.05
                        ) -> tuple[Tensor, Tensor]:
    """Which views see each source pixel's surface point.

    Pixel (x, y) of view v, lifted to ``depth[v, y, x]``, is *seen* by view u != v when it lands
    inside u's image, in front of it, and u's own depth at the pixel it lands in agrees within
    ``rel_tol`` (relative): the two pixels are the same surface point, i.e. two Gaussians within a
    pixel of each other in view u.

    Args:
        depth: [V, H, W] z-depth (metres); Ks: [V, 3, 3]; cam_to_world: [V, 4, 4].
    Returns:
        count long [V, H, W]: the number of views seeing the point (itself included, >= 1);
        earlier bool [V, H, W]: some view u < v sees it (the de-duplication keeps the first).
    """
    from clsplat.models.common.geometry import invert_rigid, project, unproject
    V, H, W = depth.shape
    depth = depth.detach()
    pts = unproject(depth, Ks, cam_to_world).reshape(1, V * H * W, 3)
    w2c = invert_rigid(cam_to_world)
    owner = torch.arange(V, device=depth.device).repeat_interleave(H * W)
    count = torch.ones(V * H * W, dtype=torch.long, device=depth.device)
    earlier = torch.zeros(V * H * W, dtype=torch.bool, device=depth.device)
    for u in range(V):
        uv, z = project(pts, Ks[u:u + 1], w2c[u:u + 1])
        uv, z = uv[0], z[0]
        px, py = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = (z > 1e-3) & (px >= 0) & (px < W) & (py >= 0) & (py < H) & (owner != u)
        du = depth[u][py.clamp(0, H - 1), px.clamp(0, W - 1)]
        seen = inside & ((du - z).abs() <= rel_tol * z.abs())
        count += seen.long()
        earlier |= seen & (owner > u)
    return count.reshape(V, H, W), earlier.reshape(V, H, W)


def dedup_mask(earlier: Tensor, budgets: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """bool [V, H, W]: the cross-view de-duplication baseline: per view, ``budgets[v]`` pixels,
    first uniformly at random among those no earlier view sees (``earlier`` [V, H, W], from
    :func:`cross_view_coverage`: duplicates merge into the first view's Gaussian), then, when the
    budget exceeds them, among the duplicates."""
    V, H, W = earlier.shape
    scores = torch.rand(V, H, W, generator=generator) + (~earlier.cpu()).to(torch.float32)
    return topk_mask(scores, budgets.cpu()).to(earlier.device)


def fill_gain(keep: Tensor, window: int) -> Tensor:
    """[V, H, W] scale factor 1/sqrt(d), d = the share of kept pixels in the ``window`` x ``window``
    square around each pixel (at least one pixel's share): a kept Gaussian whose neighbourhood lost
    a share 1 - d of its pixels covers 1/d times the area."""
    d = F.avg_pool2d(keep.to(torch.float32)[:, None], window, stride=1, padding=window // 2,
                     count_include_pad=False)[:, 0]
    return d.clamp_min(1.0 / window ** 2).rsqrt()


def importance_target(images: Tensor, budgets: Tensor, patch: int = 4) -> Tensor:
    """The 0/1 importance target [V, H, W] (float).

    Per view, ``patch`` x ``patch`` patches are ranked by mean Sobel gradient magnitude; the
    lowest are merged (only their highest-gradient pixel survives) until at most K_v pixels
    remain; if merging every patch still leaves more than K_v, the survivors of the
    lowest-gradient patches are dropped too.
    """
    import kornia
    V, _, H, W = images.shape
    p2 = patch * patch
    grad = kornia.filters.sobel(images.mean(1, keepdim=True))[:, 0]  # [V, H, W]
    # [V, P, p2]: pixels of each patch
    cells = grad.reshape(V, H // patch, patch, W // patch, patch).permute(0, 1, 3, 2, 4).reshape(V, -1, p2)
    P = cells.shape[1]
    order = torch.argsort(cells.mean(-1), dim=1, stable=True)  # lowest gradient first
    best = cells.argmax(-1)  # [V, P] survivor of a merged patch
    keep = torch.ones(V, P, p2, dtype=torch.bool, device=images.device)
    for v in range(V):
        K = int(budgets[v])
        merged = min(P, max(0, math.ceil((H * W - K) / max(p2 - 1, 1))))
        idx = order[v, :merged]
        keep[v, idx] = False
        keep[v, idx, best[v, idx]] = True
        if merged == P and P > K:  # one survivor per patch is still too many
            keep[v, order[v, :P - K]] = False
    keep = keep.reshape(V, H // patch, W // patch, patch, patch).permute(0, 1, 3, 2, 4).reshape(V, H, W)
    return keep.to(images.dtype)


def density_target(images: Tensor, share: Tensor | None = None, floor: float = 0.1, w_redundancy: float = 1.0,
                   window: int = 5) -> Tensor:
    """Soft importance target [V, H, W] in [0, 1] for :func:`stratified_mask` (issue 18).

    detail = the Sobel gradient magnitude of the grey image averaged over a ``window`` square,
    divided by the view's 95th percentile and clipped to 1; target = (floor + (1 - floor)·detail)
    · share^w_redundancy, share = 1/n of the views that see the pixel's point
    (:func:`cross_view_coverage`; None: 1). A flat patch keeps ``floor`` of an edge's density (its
    Gaussians widen to cover it); a point n views see is worth 1/n in each.
    """
    import kornia
    grey = images.mean(1, keepdim=True)
    grad = kornia.filters.sobel(grey)
    grad = F.avg_pool2d(grad, window, stride=1, padding=window // 2, count_include_pad=False)[:, 0]
    V = grad.shape[0]
    flat = grad.reshape(V, -1)
    q = torch.quantile(flat, 0.95, dim=1).clamp_min(1e-6)
    detail = (grad / q[:, None, None]).clamp(0.0, 1.0)
    t = floor + (1.0 - floor) * detail
    if share is not None and w_redundancy:
        t = t * share.to(t.dtype) ** w_redundancy
    return t.detach()


def io_loss(opacities: Tensor, target: Tensor, alphas: Tensor, w_io: float = 0.1, w_opacity: float = 0.1) -> Tensor:
    """w_io·(w_opacity·BCE(opacities [V, H, W], target [V, H, W]) + BCE(alphas [C, H, W, 1], 1))."""
    bce_op = F.binary_cross_entropy(opacities.clamp(1e-6, 1 - 1e-6), target)
    bce_alpha = -torch.log(alphas.clamp(1e-6, 1.0)).mean()
    return w_io * (w_opacity * bce_op + bce_alpha)


def sample_kappa(step: int, generator: torch.Generator, start: float = 0.85, decay: float = 0.05,
                 interval: int = 1000, low: float = 0.05, high: float = 0.95, schedule: str = "progressive") -> float:
    """``progressive``: κ ~ U(max(start - decay·⌊step/interval⌋, low), high); ``log_uniform``:
    log κ ~ U(log low, log high) at every step (as many draws below 0.1 as above 0.5 when low
    is 0.02); drawn from ``generator``."""
    if schedule == "log_uniform":
        r = float(torch.rand((), generator=generator, dtype=torch.float64))
        return math.exp(math.log(low) + (math.log(high) - math.log(low)) * r)
    if schedule != "progressive":
        raise ValueError(f"schedule: expected 'progressive' or 'log_uniform', got {schedule!r}")
    lo = max(start - decay * (step // interval), low)
    return lo + (high - lo) * float(torch.rand((), generator=generator, dtype=torch.float64))
