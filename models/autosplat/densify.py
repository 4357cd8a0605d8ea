"""Densification and pruning in gsplat's manner (its default strategy with ``absgrad=True``).

Per trainable set (:class:`GaussianParams`), while a stage trains it:

* after every backward, the screen-space gradient of each Gaussian is read from
  ``meta["means2d"].absgrad`` ``[C, N, 2]``, scaled to NDC units (``x W/2 · C``, ``y H/2 · C``,
  as gsplat), and its norm accumulated over the cameras that see it (``radii > 0``);
* every ``densify_every`` steps, Gaussians whose mean accumulated gradient exceeds
  ``grad_threshold`` grow: small ones (largest scale <= ``split_scale``) are cloned, large ones
  split into two children drawn from the Gaussian with scales / 1.6; growth is capped so the set
  stays under ``max_gaussians`` (highest gradients first);
* Gaussians with opacity < ``prune_opacity``, or (if ``growable``) a scale > ``prune_scale``, are
  removed; then the accumulators restart.

Adam's moments follow the Gaussians (new ones start at zero), so the optimiser state stays
consistent when parameter counts change. The parameter and optimiser surgery is
:func:`clsplat.strategy.rebuild` (each parameter replaced, its moments re-gathered through
:func:`clsplat.strategy.swap_parameter`), the one copy that gsplat's strategies in
:mod:`clsplat.strategy` use too; what is AutoSplat's own is only which rows survive, which are
copied and where split children go. ``AutoSplatModel.sizes`` records the set sizes for checkpoints.
"""
from __future__ import annotations

import torch
from torch import nn

from clsplat.strategy import rebuild

from ..common.geometry import quat_to_matrix

__all__ = ["GaussianParams", "GradStats", "Densifier", "densify_and_prune"]

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN")


class GaussianParams(nn.Module):
    """A trainable Gaussian set: raw parameters plus per-Gaussian buffers.

    Parameters: means [N,3], quats [N,4] (raw), log_scales [N,3], opacity_logits [N], sh0 [N,1,3],
    shN [N,K-1,3]. Buffers: ``labels [N]`` int64 and ``normals [N,3]`` (flatness reference; zeros
    when unused).
    """

    def __init__(self, n: int = 0, sh_degree: int = 1) -> None:
        super().__init__()
        K = (sh_degree + 1) ** 2
        self.sh_degree = sh_degree
        self.means = nn.Parameter(torch.zeros(n, 3))
        self.quats = nn.Parameter(torch.zeros(n, 4))
        self.log_scales = nn.Parameter(torch.zeros(n, 3))
        self.opacity_logits = nn.Parameter(torch.zeros(n))
        self.sh0 = nn.Parameter(torch.zeros(n, 1, 3))
        self.shN = nn.Parameter(torch.zeros(n, K - 1, 3))
        self.register_buffer("labels", torch.zeros(n, dtype=torch.int64))
        self.register_buffer("normals", torch.zeros(n, 3))

    @staticmethod
    def from_points(means, colors, scales, sh_degree: int, opacity: float = 0.5, labels=None, normals=None,
                    quats=None) -> "GaussianParams":
        """Start from points ``[N,3]``, colours ``[N,3]`` in [0,1], scales ``[N,3]``."""
        from ..common.gaussians import rgb_to_sh
        means = torch.as_tensor(means, dtype=torch.float32)
        n = means.shape[0]
        g = GaussianParams(n, sh_degree)
        with torch.no_grad():
            g.means.copy_(means)
            if quats is None:
                g.quats[:, 0] = 1.0
            else:
                g.quats.copy_(torch.as_tensor(quats, dtype=torch.float32))
            g.log_scales.copy_(torch.as_tensor(scales, dtype=torch.float32).clamp_min(1e-4).log())
            g.opacity_logits.fill_(float(torch.logit(torch.tensor(opacity))))
            g.sh0.copy_(rgb_to_sh(torch.as_tensor(colors, dtype=torch.float32)))
            if labels is not None:
                g.labels.copy_(torch.as_tensor(labels, dtype=torch.int64))
            if normals is not None:
                g.normals.copy_(torch.as_tensor(normals, dtype=torch.float32))
        return g

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def resize_(self, n: int) -> None:
        """Make every parameter and buffer zeros of length ``n`` (before ``load_state_dict``). The
        parameters are resized in place, so an optimiser built over them still holds them (the
        shared loop's resume loads the optimiser's state after this)."""
        for name in PARAM_NAMES:
            p = getattr(self, name)
            p.data = p.data.new_zeros((n,) + tuple(p.shape[1:]))
        self.labels = self.labels.new_zeros(n)
        self.normals = self.normals.new_zeros(n, 3)

    def activated(self):
        """``(means, quats, scales, opacities, sh)`` post-activation tensors."""
        return (self.means, self.quats, self.log_scales.exp(), torch.sigmoid(self.opacity_logits),
                torch.cat([self.sh0, self.shN], 1))


class GradStats:
    """Accumulated screen-space gradient norms ``grad [N]`` and visibility counts ``count [N]``."""

    def __init__(self, n: int) -> None:
        self.grad = torch.zeros(n)
        self.count = torch.zeros(n)

    def add(self, absgrad: torch.Tensor, radii: torch.Tensor, width: int, height: int, rows: torch.Tensor) -> None:
        """Add one render's ``absgrad [C, M, 2]`` and ``radii [C, M, 2]`` of rendered rows that are
        this set's rows ``rows [M]`` (a row may appear twice: an object and its mirror copy)."""
        C = absgrad.shape[0]
        g = absgrad.detach().clone()
        g[..., 0] *= width / 2.0 * C
        g[..., 1] *= height / 2.0 * C
        vis = (radii > 0).all(-1) if radii.dim() == 3 else radii > 0
        self.grad.index_add_(0, rows, (g.norm(dim=-1) * vis).sum(0).to(self.grad.dtype))
        self.count.index_add_(0, rows, vis.sum(0).to(self.count.dtype))

    def state(self) -> dict:
        return {"grad": self.grad, "count": self.count}

    def load(self, st: dict) -> None:
        self.grad, self.count = st["grad"].clone(), st["count"].clone()


def _gathered(v: torch.Tensor, src: torch.Tensor, fresh: torch.Tensor) -> torch.Tensor:
    """Per-row optimiser state after the surgery: rows gathered by ``src``, rows ``fresh`` zeroed."""
    v = v[src].clone()
    v[fresh] = 0
    return v


@torch.no_grad()
def densify_and_prune(g: GaussianParams, stats: GradStats, opt: torch.optim.Optimizer, *, grad_threshold: float,
                      split_scale: float, prune_opacity: float, prune_scale: float, max_gaussians: int,
                      growable: torch.Tensor, generator: torch.Generator) -> dict[str, int]:
    """Clone, split and prune ``g`` in place (and in ``opt``); returns counts of each action."""
    n = len(g)
    avg = stats.grad / stats.count.clamp_min(1)
    scales = g.log_scales.exp()
    max_s = scales.max(1).values
    grow = (avg > grad_threshold) & growable
    room = max(max_gaussians - n, 0)
    if int(grow.sum()) > room:
        cand = torch.nonzero(grow).flatten()
        top = cand[avg[cand].argsort(descending=True, stable=True)[:room]]
        grow = torch.zeros_like(grow)
        grow[top] = True
    clone = grow & (max_s <= split_scale)
    split = grow & (max_s > split_scale)
    prune = (torch.sigmoid(g.opacity_logits) < prune_opacity) | (growable & (max_s > prune_scale))
    keep = ~prune & ~split
    kept_idx = torch.nonzero(keep).flatten()
    clone_idx = torch.nonzero(clone & ~prune).flatten()
    split_idx = torch.nonzero(split & ~prune).flatten()
    src = torch.cat([kept_idx, clone_idx, split_idx, split_idx])
    n_new = src.shape[0]
    fresh = torch.zeros(n_new, dtype=torch.bool)
    fresh[kept_idx.shape[0]:] = True
    # split children: offsets drawn from the parent Gaussian, scales / 1.6
    ns = split_idx.shape[0]
    s0 = kept_idx.shape[0] + clone_idx.shape[0]
    if ns:
        R = quat_to_matrix(torch.nn.functional.normalize(g.quats[split_idx], dim=-1)).repeat(2, 1, 1)
        z = torch.randn(2 * ns, 3, generator=generator)
        offsets = (R @ (z * scales[split_idx].repeat(2, 1))[..., None])[..., 0]

    def gathered(name: str, old: torch.Tensor) -> torch.Tensor:
        val = old.data[src].clone()
        if ns and name == "means":
            val[s0:] += offsets
        if ns and name == "log_scales":
            val[s0:] -= torch.log(torch.tensor(1.6))
        return val

    params = {name: getattr(g, name) for name in PARAM_NAMES}
    rebuild(params, {name: opt for name in PARAM_NAMES}, gathered, lambda key, v: _gathered(v, src, fresh))
    for name in PARAM_NAMES:
        setattr(g, name, params[name])
    g.labels = g.labels[src].clone()
    g.normals = g.normals[src].clone()
    stats.grad = torch.zeros(n_new)
    stats.count = torch.zeros(n_new)
    return {"cloned": int(clone_idx.shape[0]), "split": int(ns), "pruned": int(prune.sum()), "total": n_new}


class Densifier:
    """Densification of a scene's sets while their stage trains: the screen-space gradient
    statistics of every set (summed over the ranks under ``torchrun``, so every rank densifies
    alike) and, on the preset's schedule, :func:`densify_and_prune` of the sets a stage trains.

    Args:
        preset: an ``AutoSplatPreset`` (thresholds, schedule, ``max_gaussians``).
        sizes: set key (``background``, ``object<k>``) -> its number of Gaussians.
        sky: the label whose background Gaussians never grow (the sky dome keeps its layout).
        object_caps: ``object<k>`` -> the Gaussians that object set may grow to (issue 36's
            per-track budget, :class:`.objects.ObjectBudget`); a set not named: 4 x ``object_points``.
    """

    def __init__(self, preset, sizes: dict[str, int], sky: int, object_caps: dict[str, int] | None = None) -> None:
        self.preset, self.sky = preset, sky
        self.object_caps = dict(object_caps or {})
        self.stats = {k: GradStats(n) for k, n in sizes.items()}

    def cap(self, key: str, stage: str, n: int) -> int:
        """The size set ``key`` may grow to in ``stage``: an object its cap (``object_caps``, by
        default 4x ``object_points``: 4x its initial template points), never below its size; the
        background ``max_gaussians``, of which phase 1 (road and sky alone) may fill only
        ``phase1_budget_share``."""
        p = self.preset
        if key != "background":
            return max(self.object_caps.get(key, 4 * p.object_points), n)
        return int(p.max_gaussians * p.phase1_budget_share) if stage == "bg_phase1" else p.max_gaussians

    def accumulate(self, renders: list, trained: list[str], world: int, width: int, height: int) -> None:
        """Add one step's renders (``(meta, layout)`` pairs: the rasteriser's meta and the
        ``(set key, rows)`` blocks of the rendered Gaussians) to the statistics of the ``trained``
        sets; under torchrun the step's contributions are summed over the ranks first."""
        target = self.stats if world == 1 else {k: GradStats(len(self.stats[k].grad)) for k in trained}
        for meta, layout in renders:
            ag = getattr(meta["means2d"], "absgrad", None)
            if ag is None:
                continue
            start = 0
            for key, rows in layout:
                n = rows.shape[0]
                if key in trained:
                    target[key].add(ag[:, start:start + n], meta["radii"][:, start:start + n], width, height, rows)
                start += n
        if world > 1:
            import torch.distributed as dist
            flat = torch.cat([t for k in trained for t in (target[k].grad, target[k].count)])
            dist.all_reduce(flat)
            off = 0
            for k in trained:
                n = len(target[k].grad)
                self.stats[k].grad += flat[off:off + n]
                self.stats[k].count += flat[off + n:off + 2 * n]
                off += 2 * n

    def due(self, s_in: int, n_stage: int) -> bool:
        """Whether step ``s_in`` (from 0) of a stage of ``n_stage`` steps densifies: every
        ``densify_every`` steps from ``densify_start``, not in the stage's last 20 %."""
        p, s = self.preset, s_in + 1
        return s >= p.densify_start and s % p.densify_every == 0 and s <= 0.8 * n_stage

    def densify(self, sets: dict[str, "GaussianParams"], opt: torch.optim.Optimizer, stage: str,
                generator: torch.Generator) -> dict[str, int]:
        """Densify and prune every set of ``sets`` (key -> set, those the stage trains) in place
        and in ``opt``; returns ``{"densify_<key>": Gaussians after}``."""
        p, record = self.preset, {}
        for key, g in sets.items():
            if len(g) == 0:
                continue
            growable = g.labels != self.sky if key == "background" else torch.ones(len(g), dtype=torch.bool)
            res = densify_and_prune(
                g, self.stats[key], opt,
                grad_threshold=p.grad_threshold if key == "background" or not p.object_grad_threshold
                else p.object_grad_threshold,
                split_scale=p.split_scale if key == "background" else p.object_split_scale,
                prune_opacity=p.prune_opacity, prune_scale=p.prune_scale,
                max_gaussians=self.cap(key, stage, len(g)), growable=growable, generator=generator)
            record[f"densify_{key}"] = res["total"]
        return record

    def state(self) -> dict:
        return {k: s.state() for k, s in self.stats.items()}

    def load(self, sizes: dict[str, int], state: dict) -> None:
        """Statistics for sets of ``sizes``, those of ``state`` (a checkpoint's) restored."""
        self.stats = {k: GradStats(0) for k in sizes}
        for k, st in state.items():
            self.stats[k].load(st)
