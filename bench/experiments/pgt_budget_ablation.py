"""The budget stage's ablation on the multi-view protocol (issue 18): what each departure from EcoSplat's
stage 2 is worth, at equal per-view counts, without retraining where the change is a choice at
evaluation time.

For each held-out sample (``--views`` source views, :func:`clsplat.models.pgt.data.make_views_sample`)
the base model runs once; for every κ in ``--budgets`` each *row* keeps exactly K_v Gaussians
per view (the high-frequency weighting) and renders the targets:

* the five methods of ``clsplat eval pgt`` (``finetuned`` with the checkpoint's own preset;
  ``random``, ``opacity``, ``grid``, ``dedup`` on the base output);
* ``finetuned:topk``: the same finetuned heads selecting EcoSplat's way (top-K of the score);
* ``finetuned:nofillcap`` / ``<baseline>:nofillcap``: without ``fill_cap_px`` (far Gaussians stop
  growing at ``scale_cap`` metres);
* ``target:w=W,floor=F``: the oracle of the importance target (stratified selection by
  :func:`~clsplat.models.pgt.budget.density_target` itself, from the base's depth), i.e. what the
  importance head is trained to predict, for each ``--targets`` setting;
* ``finetuned@CK`` for each extra ``--compare`` checkpoint (a training-time ablation).

Writes ``--out`` (JSON: rows of method, budget, n_gaussians, psnr, psnr_covered, ssim,
render_ms, per-sample PSNRs) and prints a markdown table.

Run: ``python bench/experiments/pgt_budget_ablation.py --checkpoint U/checkpoint.pt --views 8
--budgets 1,0.1,0.05 --num-scenes 4 --out bench/out/pgt18_ablation.json``.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from clsplat.models.common.data import parse_data
from clsplat.models.common.metrics import psnr, ssim
from clsplat.models.common.presets import apply_sets
from clsplat.models.common.train import load_checkpoint, set_threads
from clsplat.models.pgt.budget import (cross_view_coverage, density_target, per_view_budgets, stratified_mask,
                                       topk_mask, view_weights)
from clsplat.models.pgt.data import make_views_sample
from clsplat.models.pgt.evaluate import BASELINES, baseline_mask, covered_mask
from clsplat.models.pgt.model import PGT
from clsplat.models.pgt.presets import saved_preset
from clsplat.models.pgt.training import render_views


def prefiltered(base, keep: torch.Tensor, images: torch.Tensor, window: int):
    """The base output's kept Gaussians with each colour replaced by the source image blurred at
    the scale the Gaussian is widened to (σ = g/2 px, g = fill gain; nearest of a few levels):
    the oracle of what a colour head could learn (anti-aliasing before thinning)."""
    import kornia
    from clsplat.models.common.gaussians import rgb_to_sh
    from clsplat.models.pgt.budget import fill_gain
    V, _, H, W = images.shape
    sig = 0.5 * fill_gain(keep, window)  # [V, H, W]
    levels = [0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0]
    blurred = [images] + [kornia.filters.gaussian_blur2d(images, (2 * int(3 * s) + 1,) * 2, (s, s),
                                                         border_type="reflect") for s in levels[1:]]
    idx = torch.argmin((sig[None] - torch.tensor(levels)[:, None, None, None]).abs(), 0)  # [V, H, W]
    stack = torch.stack(blurred)  # [L, V, 3, H, W]
    col = torch.gather(stack, 0, idx[None, :, None].expand(1, V, 3, H, W))[0].permute(0, 2, 3, 1)
    out = dataclasses.replace(base, sh=rgb_to_sh(col.reshape(-1, 3)).reshape(V, H, W, 1, 3))
    return out.gaussians(keep)


def load(path: str, sets: list[str] | None = None, **changes) -> tuple[PGT, object]:
    ck = load_checkpoint(path, "pgt")
    preset = apply_sets(saved_preset(ck["preset"]), sets or [])
    if changes:
        preset = dataclasses.replace(preset, **changes)
    model = PGT(preset)
    if any(k.startswith("budget.") for k in ck["model"]):
        model.enable_budget()
    model.load_state_dict(ck["model"])
    return model.eval(), preset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--budgets", default="1,0.2,0.1,0.05,0.02")
    ap.add_argument("--num-scenes", type=int, default=4)
    ap.add_argument("--targets", default="1:0.1,0:0.1", help="w_redundancy:floor pairs of oracle rows ('' none)")
    ap.add_argument("--compare", nargs="*", default=[], help="other budget checkpoints (training-time ablations)")
    ap.add_argument("--prefilter", action="store_true", help="add the colour-prefilter oracle rows")
    ap.add_argument("--no-variants", action="store_true", help="skip the topk / nofillcap rows")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], help="FIELD=VALUE: change the checkpoint's preset "
                    "(evaluation-time fields, e.g. fill_cap_px=8.0)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    set_threads(1, None)
    budgets = [float(k) for k in args.budgets.split(",")]
    model, preset = load(args.checkpoint, args.set)
    has_budget = model.budget is not None
    topk = load(args.checkpoint, args.set, selection="topk")[0] if has_budget and not args.no_variants else None
    others = {Path(c).parent.name: load(c)[0] for c in args.compare}
    targets = [tuple(float(x) for x in t.split(":")) for t in args.targets.split(",") if t]
    source = parse_data("synthetic", seed=args.seed)
    acc: dict[tuple[str, float], list[dict]] = {}

    def timed(g, s):
        ts, rgb = [], None
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            rgb, _ = render_views(g, s.target_viewmats, s.target_Ks, preset.width, preset.height)
            ts.append(time.perf_counter() - t0)
        return rgb, 1000 * float(np.median(ts))

    def score(name, kappa, g, s, covered):
        r, ms = timed(g, s)
        acc.setdefault((name, kappa), []).append({
            "n_gaussians": len(g), "psnr": float(psnr(r, s.target_images).mean()),
            "psnr_covered": float(psnr(r, s.target_images, covered).nanmean()),
            "ssim": float(ssim(r, s.target_images).mean()), "render_ms": ms})

    for i in range(args.num_scenes):
        s = make_views_sample(source, preset, i, args.views, "test", None)
        V, _, H, W = s.images.shape
        with torch.no_grad():
            base = model(s.images, s.Ks, s.cam_to_world)
            _, alpha = render_views(base.gaussians(), s.target_viewmats, s.target_Ks, preset.width, preset.height)
            covered = covered_mask(alpha)
            count = cross_view_coverage(base.depth, s.Ks, s.cam_to_world, preset.coverage_tol)[0]
            weights = view_weights(s.images, preset.hf_temperature)
            for kappa in budgets:
                K = per_view_budgets(kappa, weights, H, W)
                if kappa == 1.0:
                    score("full", kappa, base.gaussians(), s, covered)
                    continue
                gen = lambda: torch.Generator().manual_seed(args.seed * 1_000_003 + i * 1009 + int(kappa * 1e6))
                masks = {m: baseline_mask(m, base, K, s.Ks, s.cam_to_world, gen(), preset.coverage_tol)
                         for m in BASELINES}
                for m, keep in masks.items():
                    score(m, kappa, base.gaussians(keep), s, covered)
                    if args.prefilter and m in ("random", "grid"):
                        score(f"{m}:prefilter", kappa, prefiltered(base, keep, s.images, preset.fill_window), s,
                              covered)
                    if not args.no_variants and preset.fill_cap_px > 0 and m in ("random", "grid"):
                        base.fill_cap_px = 0.0
                        score(f"{m}:nofillcap", kappa, base.gaussians(keep), s, covered)
                        base.fill_cap_px = preset.fill_cap_px
                for w, fl in targets:
                    dens = density_target(s.images, 1.0 / count.float(), fl, w)
                    keep = stratified_mask(dens, K)
                    score(f"target:w={w:g},floor={fl:g}", kappa, base.gaussians(keep), s, covered)
                    if args.prefilter:
                        score(f"target:w={w:g},floor={fl:g}:prefilter", kappa,
                              prefiltered(base, keep, s.images, preset.fill_window), s, covered)
                if has_budget:
                    out = model(s.images, s.Ks, s.cam_to_world, kappa=kappa)
                    score("finetuned", kappa, out.gaussians(), s, covered)
                    if topk is not None:
                        score("finetuned:topk", kappa, topk(s.images, s.Ks, s.cam_to_world, kappa=kappa).gaussians(),
                              s, covered)
                        if preset.fill_cap_px > 0:
                            out.fill_cap_px = 0.0
                            score("finetuned:nofillcap", kappa, out.gaussians(), s, covered)
                for name, m in others.items():
                    score(f"finetuned@{name}", kappa, m(s.images, s.Ks, s.cam_to_world, kappa=kappa).gaussians(),
                          s, covered)
        print(f"sample {i} done", flush=True)
    rows = [{"method": m, "budget": k, "views": args.views,
             **{key: float(np.mean([r[key] for r in v])) for key in ("n_gaussians", "psnr", "psnr_covered", "ssim",
                                                                     "render_ms")},
             "psnr_per_sample": [r["psnr"] for r in v]} for (m, k), v in acc.items()]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"checkpoint": args.checkpoint, "views": args.views,
                                          "num_scenes": args.num_scenes, "rows": rows}, indent=1))
    print("| method | κ | Gaussians | PSNR | PSNR covered | SSIM | render ms |\n|---|---|---|---|---|---|---|")
    for r in sorted(rows, key=lambda r: (-r["budget"], -r["psnr"])):
        print(f"| {r['method']} | {r['budget']:g} | {r['n_gaussians']:.0f} | {r['psnr']:.2f} | "
              f"{r['psnr_covered']:.2f} | {r['ssim']:.3f} | {r['render_ms']:.1f} |")


if __name__ == "__main__":
    main()
