"""Held-out evaluation of a PGT checkpoint: image quality, depth and the budget curve.

Protocol (``views``): 2 is the base stage's own (two frames of one camera, the frame between
them as target); 3..24 the multi-view protocol of :func:`~.data.make_rig_sample` (source frames
of several rig cameras at several instants, targets half-way between), where EcoSplat's budget
claim lives: cross-view redundancy.

For each held-out sample: the base prediction renders the targets (PSNR, SSIM[, LPIPS]), its
depth is compared with ground truth before (u0) and after the residual head; then for every
budget κ the same number of Gaussians per view, K_v from the high-frequency weighting, is kept
five ways (:data:`METHODS`):

* ``finetuned``: EcoSplat's stage-2 heads at κ and their own selection (only with a budget checkpoint),
* ``random``: K_v uniformly random pixels per view,
* ``opacity``: top-K_v by the base model's opacity, no finetuning,
* ``grid``: uniform grid thinning, one pixel per cell (:func:`~.budget.grid_mask`),
* ``dedup``: cross-view de-duplication (pixels whose point an earlier view already has, within
  a pixel in that view, go last), then uniform (:func:`~.budget.dedup_mask`),

and, with a budget checkpoint, each naive selection applied to the *finetuned* parameters (issue
33's controls, :data:`ON_FINETUNED`: ``random@finetuned``, ``opacity@finetuned``,
``grid@finetuned``, ``dedup@finetuned``): the stage-2 heads at κ predict every pixel's Gaussian
(``PGT.forward(full=True)``), then the naive rule picks which K_v to keep (random, grid and dedup
the very pixels of their base-model row, from the same generator; opacity by the finetuned
opacity). ``finetuned`` against ``X@finetuned`` is "which Gaussians" on the same parameters;
``X@finetuned`` against ``X`` is "how they were retrained" on the same pixels.

Each is rendered (PSNR over all pixels and over the pixels the full model covers, alpha > 0.5;
SSIM; median render milliseconds of the forward rasterisation). κ = 1 is the base model for the
naive rows and the finetuned parameters unpruned (the stage-2 heads at κ = 1, every Gaussian) for
``finetuned`` and ``X@finetuned`` (whose selections keep every pixel there, so they equal it).
Per-view counts are checked equal across methods (a ValueError otherwise). Rows are means over
samples of ``split`` (``test``, reported once; ``val``: where the budget stage's fields are
chosen, disjoint streets).
"""
from __future__ import annotations

import json
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from clsplat.io.atomic import atomic_write, write_text_atomic
from clsplat.models.common.metrics import depth_metrics, psnr, ssim
from clsplat.models.common.report import camera_blocks, image_scores, metrics_report, write_metrics

from .budget import (cross_view_coverage, dedup_mask, grid_mask, per_view_budgets, random_mask, topk_mask,
                     view_weights)
from .data import make_views_sample
from .model import PGT, learned_selection
from .presets import PGTPreset
from .training import render_views

__all__ = ["evaluate_model", "plot_budget", "pareto_front", "write_results", "covered_mask", "baseline_mask",
           "METHODS", "BASELINES", "ON_FINETUNED", "ALL_METHODS", "COVERED_ALPHA"]

METHODS = ("finetuned", "random", "opacity", "grid", "dedup")
BASELINES = METHODS[1:]
#: the naive selections applied to the finetuned parameters (issue 33's controls)
ON_FINETUNED = tuple(f"{m}@finetuned" for m in BASELINES)
#: every row name of budget.json, in the table's order
ALL_METHODS = METHODS + ON_FINETUNED
#: a target pixel is "covered" when the full model's rendered alpha exceeds this
COVERED_ALPHA = 0.5


def covered_mask(alpha) -> torch.Tensor:
    """bool [C, H, W]: the target pixels the full model covers (rendered alpha [C, H, W, 1] > 0.5)."""
    return alpha[..., 0] > COVERED_ALPHA


def baseline_mask(method: str, base, budgets: torch.Tensor, Ks: torch.Tensor, cam_to_world: torch.Tensor,
                  generator: torch.Generator | None = None, coverage_tol: float = 0.05) -> torch.Tensor:
    """bool [V, H, W]: the pixels ``method`` (one of :data:`BASELINES`) keeps of the output
    ``base`` (:class:`~.model.PGTOutput`: the base model's, or the finetuned parameters'),
    ``budgets[v]`` per view exactly."""
    V, H, W = base.opacities.shape
    if method == "random":
        return random_mask(budgets, H, W, generator)
    if method == "opacity":
        return topk_mask(base.opacities, budgets)
    if method == "grid":
        return grid_mask(budgets, H, W)
    if method == "dedup":
        earlier = cross_view_coverage(base.depth, Ks, cam_to_world, coverage_tol)[1]
        return dedup_mask(earlier, budgets, generator)
    raise ValueError(f"method: expected one of {BASELINES}, got {method!r}")


def _timed_render(g, s, preset: PGTPreset, repeats: int) -> tuple[torch.Tensor, torch.Tensor, float]:
    times = []
    rgb = alpha = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        rgb, alpha = render_views(g, s.target_viewmats, s.target_Ks, preset.width, preset.height)
        times.append(time.perf_counter() - t0)
    return rgb, alpha, 1000.0 * statistics.median(times)


def _check_counts(keep: torch.Tensor, budgets: torch.Tensor, method: str) -> None:
    got = keep.reshape(keep.shape[0], -1).sum(1).cpu()
    if not torch.equal(got, budgets.cpu().long()):
        raise ValueError(f"{method}: kept {got.tolist()} Gaussians per view, the budget is {budgets.tolist()}")


def evaluate_model(model: PGT, source, preset: PGTPreset, budgets: list[float], num_scenes: int = 4,
                   seed: int = 0, repeats: int = 3, sheet: str | Path | None = None, lpips=None,
                   step: int = 0, views: int = 2, methods: tuple[str, ...] | None = None,
                   split: str = "test") -> dict:
    """Evaluate ``model`` on held-out samples 0..num_scenes-1 of ``split`` ("test", or "val":
    the validation streets, disjoint from train and test) with ``views`` source views (2: the
    base protocol; 3..24: the multi-view protocol).

    Returns {"rows": budget rows (method, selection, parameters, budget, views, n_gaussians, psnr,
    psnr_covered, ssim, [lpips], render_ms: means over the samples; psnr_per_sample: sample i's
    PSNR, so that two methods compare street by street), "metrics": the ``metrics.json`` dict
    (:mod:`clsplat.models.common.report`) of the full set: PSNR/SSIM[/LPIPS] and depth (with the
    residual head) overall and per target camera, the depth without the residual head, render and
    prediction times}. ``methods``: a subset of :data:`ALL_METHODS` (default all; ``finetuned``
    and :data:`ON_FINETUNED` only with a budget checkpoint). With ``sheet``, a contact sheet of
    sample 0 (full set and each method at the smallest budget against the ground truth).
    """
    if split not in ("val", "test"):
        raise ValueError(f"split: expected 'val' or 'test' (held-out streets), got {split!r}")
    model.eval()
    for m in methods or ():
        if m not in ALL_METHODS:
            raise ValueError(f"methods: expected names from {ALL_METHODS}, got {m!r}")
    methods = [m for m in (methods or ALL_METHODS)
               if model.budget is not None or not (m == "finetuned" or m in ON_FINETUNED)]
    uses_finetuned = any(m == "finetuned" or m in ON_FINETUNED for m in methods)
    acc: dict[tuple[str, float], list[dict]] = {}
    full, full_gt, cams, d_coarse, d_fine, pred_s, render_ms = [], [], [], [], [], [], []
    for i in range(num_scenes):
        s = make_views_sample(source, preset, i, views, split, None)
        V, _, H, W = s.images.shape
        with torch.no_grad():
            t0 = time.perf_counter()
            base = model(s.images, s.Ks, s.cam_to_world)
            pred_s.append(time.perf_counter() - t0)
            rgb, alpha, ms = _timed_render(base.gaussians(), s, preset, repeats)
            covered = covered_mask(alpha)
            full.append(rgb)
            full_gt.append(s.target_images)
            cams += list(s.target_cameras)
            render_ms.append(ms)
            if s.depths is not None:
                d_coarse.append(depth_metrics(base.depth0, s.depths, max_depth=preset.max_depth))
                d_fine.append(depth_metrics(base.depth, s.depths, max_depth=preset.max_depth))
            weights = view_weights(s.images, preset.hf_temperature)
            sheet_rows = [rgb[0]]
            for kappa in budgets:
                K = per_view_budgets(kappa, weights, H, W)
                # the finetuned parameters at κ, every pixel's Gaussian (κ = 1: the stage-2 heads unpruned)
                ft = model(s.images, s.Ks, s.cam_to_world, kappa=kappa, full=True) if uses_finetuned else None
                for m in methods:
                    name, _, on = m.partition("@")
                    if kappa == 1.0 and m in BASELINES:
                        g, r, t = base.gaussians(), rgb, ms
                    else:
                        if m == "finetuned":
                            keep = None if kappa == 1.0 else learned_selection(ft.importance, K, preset.selection)
                        else:
                            gen = torch.Generator().manual_seed(seed * 1_000_003 + i * 1009 + int(kappa * 1e6))
                            keep = baseline_mask(name, ft if on else base, K, s.Ks, s.cam_to_world, gen,
                                                 preset.coverage_tol)
                        if keep is not None:
                            _check_counts(keep, K, m)
                        g = (ft if on or m == "finetuned" else base).gaussians(keep)
                        r, _, t = _timed_render(g, s, preset, repeats)
                    row = {"n_gaussians": len(g), "psnr": float(psnr(r, s.target_images).mean()),
                           "psnr_covered": float(psnr(r, s.target_images, covered).nanmean()),
                           "ssim": float(ssim(r, s.target_images).mean()), "render_ms": t}
                    if lpips is not None:
                        row["lpips"] = float(lpips(r.clamp(0, 1), s.target_images).mean())
                    acc.setdefault((m, kappa), []).append(row)
                    if kappa == min(budgets) and i == 0:
                        sheet_rows.append(r[0])
            if sheet is not None and i == 0:
                from clsplat.io.contact_sheet import make_contact_sheet
                rows = torch.stack(sheet_rows).permute(0, 2, 3, 1).clamp(0, 1)
                names = ["full"] + [f"{m} k={min(budgets)}" for m in methods]
                make_contact_sheet(rows, s.target_images[:1].permute(0, 2, 3, 1).expand_as(rows), sheet, names=names,
                                   title=f"PGT {preset.name}: {s.name}")
    keys = ("n_gaussians", "psnr", "psnr_covered", "ssim", "render_ms") + (("lpips",) if lpips is not None else ())
    rows = [{"method": m, "selection": "learned" if m == "finetuned" else m.partition("@")[0],
             "parameters": "finetuned" if m == "finetuned" or m in ON_FINETUNED else "base",
             "budget": k, "views": views, **{key: float(np.mean([r[key] for r in v])) for key in keys},
             "psnr_per_sample": [r["psnr"] for r in v]}
            for (m, k), v in acc.items()]

    def mean_depth(ds: list[dict]) -> dict:
        keys = ("abs_rel", "sq_rel", "rmse", "delta1")
        return {k: float(np.nanmean([d[k] for d in ds])) for k in keys} if ds else {}

    all_, per_camera = camera_blocks(image_scores(torch.cat(full), torch.cat(full_gt), lpips), cams)
    all_.update(mean_depth(d_fine))
    protocol = {"data": source.name, "split": split, "scenes": num_scenes, "images": len(cams),
                "cameras": list(dict.fromkeys(cams)),
                "views": (f"{preset.num_views if views == 2 else views} source views "
                          f"({preset.views if views == 2 else 'multi-view: rig cameras x instants'})"),
                "lpips": "on" if lpips is not None else "off (no weights given)",
                "psnr_covered": f"PSNR over the target pixels the full model covers (alpha > {COVERED_ALPHA})",
                "depth": "source views' depth after the residual head against the data's depth (mean over samples)",
                "render_ms": "median over samples of the median of timed forward renders"}
    metrics = metrics_report(
        "pgt", preset.name, step, protocol, all_, per_camera,
        depth_without_residual=mean_depth(d_coarse), render_ms=float(np.median(render_ms)),
        seconds_per_prediction=float(np.median(pred_s)))
    return {"rows": rows, "metrics": metrics}


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points (cost, quality) not dominated by one of lower-or-equal cost and higher quality,
    sorted by cost."""
    front, best = [], -math.inf
    for c, q in sorted(points, key=lambda p: (p[0], -p[1])):
        if q > best:
            front.append((c, q))
            best = q
    return front


def plot_budget(rows: list[dict], png: str | Path, title: str = "PGT budget curve") -> Path:
    """PSNR against Gaussian count and against render time, per method, with the Pareto front; a
    naive selection on the finetuned parameters (``X@finetuned``) in its base row's colour and
    marker, dotted."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    for ax, xkey, xlabel in ((axes[0], "n_gaussians", "Gaussians kept"), (axes[1], "render_ms", "render time (ms)")):
        for m in ALL_METHODS:
            j = METHODS.index(m.partition("@")[0])
            style = "os^dv"[j] + (":" if m in ON_FINETUNED else ("-", "--", ":", "-.", "--")[j])
            rs = sorted((r for r in rows if r["method"] == m), key=lambda r: r[xkey])
            if rs:
                ax.plot([r[xkey] for r in rs], [r["psnr"] for r in rs], style, label=m, color=f"C{j}",
                        alpha=0.6 if m in ON_FINETUNED else 1.0)
                for r in rs:
                    ax.annotate(f"{r['budget']:g}", (r[xkey], r["psnr"]), fontsize=6, alpha=0.6)
        front = pareto_front([(r[xkey], r["psnr"]) for r in rows])
        ax.step([c for c, _ in front], [q for _, q in front], where="post", color="k", lw=2, alpha=0.25,
                label="Pareto front")
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    try:
        return atomic_write(Path(png), lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)


def write_results(result: dict, out_dir: str | Path, title: str) -> None:
    """out_dir/budget.json (rows), budget.png, metrics.json (each written atomically; a failed
    write is an OSError naming the file)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "budget.json", json.dumps(result["rows"], indent=1))
    write_metrics(out, result["metrics"])
    plot_budget(result["rows"], out / "budget.png", title)

