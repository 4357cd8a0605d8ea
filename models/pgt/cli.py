"""``clsplat train pgt`` and ``clsplat eval pgt``.

    clsplat train pgt --stage base   --data synthetic --preset small --steps 1200 --out runs/pgt-base
    clsplat train pgt --stage budget --init runs/pgt-base/checkpoint.pt --data synthetic \\
                      --preset small --steps 400 --out runs/pgt-budget
    clsplat eval pgt --checkpoint runs/pgt-budget/checkpoint.pt --data synthetic --views 8 \\
                     --budgets 1,0.5,0.2,0.1,0.05 [--eval-split val|test] --out runs/pgt-eval

``train`` (``--view``: watch it in the browser, clsplat view) writes the run folder of
:func:`clsplat.models.common.train.train` (checkpoint.pt, log.jsonl, loss.png) and the evaluation
on ``--eval-scenes`` held-out samples (as ``eval`` does: at κ = 1 on the base protocol after the
base stage, on ``budget_views`` views after the budget stage). ``eval --views N`` (default 8: the
multi-view protocol; 2: the base stage's two frames) writes budget.json (rows: method one of
finetuned, random, opacity, grid, dedup and, with a budget checkpoint, random@finetuned,
opacity@finetuned, grid@finetuned, dedup@finetuned (the naive selections on the finetuned
parameters, issue 33); selection, parameters, budget, views, n_gaussians, psnr, psnr_covered,
ssim, [lpips], render_ms: means over the samples; psnr_per_sample), budget.png (quality
against Gaussian count and render time, Pareto front),
metrics.json (full-set quality in the shared schema of :mod:`clsplat.models.common.report`,
depth with and without the residual head, seconds per prediction) and contact_sheet.png.
``--eval-split val`` scores the validation streets (disjoint seeds from train and test: where the
budget stage's fields and steps are chosen); ``test`` (default) is reported once per recipe.
"""
from __future__ import annotations

import sys

from clsplat.argparser import ArgumentParser
from clsplat.models.common.cli import (add_common_args, add_eval_args, add_eval_scenes_arg, add_eval_split_arg,
                                      add_view_args, lpips_from_args, no_weights)
from clsplat.models.common.data import parse_data
from clsplat.models.common.presets import apply_sets, check_preset_matches, get_preset
from clsplat.models.common.train import TrainSpec, load_checkpoint, seed_everything, set_threads
from clsplat.models.common.train import train as run_train

from .budget import check_kappa
from .model import PGT
from .presets import BUDGET_FIELDS, saved_preset

__all__ = ["train", "evaluate", "parse_budgets", "check_views_arg"]

FAMILY = "pgt"


def parse_budgets(text: str) -> list[float]:
    """"1,0.5,0.2" -> [1.0, 0.5, 0.2]; ValueError naming --budgets for anything outside (0, 1]."""
    try:
        values = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise ValueError(f"--budgets: expected comma-separated numbers in (0, 1], got {text!r}") from None
    if not values:
        raise ValueError(f"--budgets: expected at least one budget, got {text!r}")
    for v in values:
        try:
            check_kappa(v)
        except ValueError:
            raise ValueError(f"--budgets: every budget must be in (0, 1], got {v!r}") from None
    return values


#: the budgets κ of ``eval pgt`` (and of the evaluation after a budget-stage run)
DEFAULT_BUDGETS = (1.0, 0.5, 0.2, 0.1, 0.05)
#: source views of ``eval pgt`` by default: the multi-view protocol (EcoSplat's regime)
DEFAULT_VIEWS = 8


def check_views_arg(views: int) -> int:
    """--views: 2 or 3..24; ValueError naming it otherwise."""
    from .data import MAX_VIEWS
    if not (views == 2 or 3 <= views <= MAX_VIEWS):
        raise ValueError(f"--views: expected 2 (the base protocol) or 3..{MAX_VIEWS} (the multi-view protocol), "
                         f"got {views}")
    return views


def _summary(m: dict) -> str:
    a = m["all"]
    return (f"full set: PSNR {a['psnr']:.2f} dB, SSIM {a['ssim']:.3f}"
            + (f", LPIPS {a['lpips']:.3f}" if "lpips" in a else "")
            + f"; depth AbsRel {m['depth_without_residual'].get('abs_rel', float('nan')):.3f} (coarse) -> "
              f"{a.get('abs_rel', float('nan')):.3f} (residual)")


def train(argv: list[str]) -> int:
    """``clsplat train pgt ...``; returns the exit status."""
    p = ArgumentParser(prog="clsplat train pgt", description="Train PGT (base) or EcoSplat's budget stage.")
    add_common_args(p, default_preset="small")
    p.add_argument("--stage", choices=("base", "budget"), default="base",
                   help="base: the pixel-aligned predictor; budget: EcoSplat stage 2 from --init")
    p.add_argument("--init", default=None, help="base checkpoint to start the budget stage from")
    add_eval_scenes_arg(p)
    add_eval_split_arg(p)
    add_view_args(p)
    args = p.parse_args(argv)
    try:
        no_weights(args, "PGT", "its U-Net encoder and matcher train from random initialisation, as in the paper")
        preset = apply_sets(get_preset(FAMILY, args.preset), args.set)
        if args.stage == "budget" and args.init is None and not args.resume:
            raise ValueError("--init: the budget stage starts from a base checkpoint; give --init FILE")
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle)
        set_threads(args.threads, args.device)
        seed_everything(args.seed)
        model = PGT(preset)
        if args.stage == "budget":
            if args.init is not None:
                ck = load_checkpoint(args.init, FAMILY)
                # the base network must match; the budget stage's own fields may differ
                saved = dict(ck.get("preset") or {})
                saved.update({k: v for k, v in preset.to_dict().items() if k in BUDGET_FIELDS})
                check_preset_matches(saved, preset, str(args.init))
                state = {k: v for k, v in ck["model"].items() if not k.startswith("budget.")}
                model.load_state_dict(state)
            model.enable_budget()
        steps = args.steps or (preset.steps if args.stage == "base" else preset.budget_steps)
        from .training import make_optimizer, make_sample_loss
        opt, sched = make_optimizer(model, preset, steps, args.stage)
        lpips = lpips_from_args(args)   # the loss's LPIPS term (w_lpips) and the final evaluation
        from ..common.view import train_watcher
        from .view import model_scene
        # --view: the model run on held-out sample 0 (input/target cameras, depth), refreshed as it trains
        watcher = train_watcher(args, lambda: model_scene(model, preset, source, args.data,
                                                          title=f"PGT {args.stage} (training)"), args.device)
        from ..common.runfolder import RunFolder
        from ..common.train import distributed_info, end_distributed
        distributed_info()
        with RunFolder(args.out, resume=args.resume) as rf:  # the lock; outputs staged, then published as a group
            spec = TrainSpec(out_dir=rf.stage, steps=steps, batch_size=args.batch_size or preset.batch_size,
                             checkpoint_every=args.checkpoint_every, seed=args.seed, grad_clip=preset.grad_clip,
                             resume=args.resume, progress=not args.no_progress)
            try:
                run_train(model, opt, spec, preset, FAMILY,
                          make_sample_loss(source, preset, args.stage, args.seed, lpips if preset.w_lpips else None),
                          scheduler=sched, extra_state={"stage": args.stage},
                          on_step=None if watcher is None else watcher.on_step)
            finally:
                if watcher is not None:
                    watcher.close()
            if args.eval_scenes > 0 and distributed_info()[0] == 0:
                from .evaluate import evaluate_model, write_results
                res = evaluate_model(model, source, preset, [1.0] if args.stage == "base" else DEFAULT_BUDGETS,
                                     args.eval_scenes, args.seed, sheet=rf.stage / "contact_sheet.png",
                                     lpips=lpips, step=steps,
                                     views=2 if args.stage == "base" else preset.budget_views,
                                     split=args.eval_split)
                write_results(res, rf.stage, f"PGT {preset.name} ({args.stage}, step {steps}) on held-out "
                                             f"{source.name} ({args.eval_split})")
                print(_summary(res["metrics"]), flush=True)
            rf.publish()
        end_distributed()
    except ValueError as e:
        print(f"clsplat train pgt: {e}", file=sys.stderr)
        return 2
    return 0


def evaluate(argv: list[str]) -> int:
    """``clsplat eval pgt ...``; returns the exit status."""
    p = ArgumentParser(prog="clsplat eval pgt", description="Evaluate PGT on held-out data: budget curve.")
    add_eval_args(p)
    p.add_argument("--budgets", default=",".join(f"{k:g}" for k in DEFAULT_BUDGETS),
                   help="comma-separated κ in (0, 1]")
    p.add_argument("--repeats", type=int, default=3, help="timed renders per point (median)")
    p.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                   help="source views per sample: 2 (the base protocol: two frames of one camera) or 3..24 "
                        "(the multi-view protocol: rig cameras at several instants, targets between them)")
    add_eval_split_arg(p)
    args = p.parse_args(argv)
    try:
        budgets = parse_budgets(args.budgets)
        views = check_views_arg(args.views)
        if args.repeats < 1:
            raise ValueError(f"--repeats: expected at least 1, got {args.repeats}")
        ck = load_checkpoint(args.checkpoint, FAMILY)
        preset = saved_preset(ck["preset"])   # with the run's --set changes
        check_preset_matches(ck["preset"], preset, str(args.checkpoint))
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle)
        lpips = lpips_from_args(args)
        set_threads(args.threads, args.device)
        model = PGT(preset)
        if any(k.startswith("budget.") for k in ck["model"]):
            model.enable_budget()
        model.load_state_dict(ck["model"])
        from clsplat.io.atomic import staged_group
        from .evaluate import evaluate_model, write_results
        with staged_group(args.out) as stage:  # the four files replace an earlier evaluation's together
            res = evaluate_model(model, source, preset, budgets, args.num_scenes, args.seed, args.repeats,
                                 sheet=stage / "contact_sheet.png", lpips=lpips, step=int(ck["step"]), views=views,
                                 split=args.eval_split)
            res["metrics"]["checkpoint"] = str(args.checkpoint)
            write_results(res, stage, f"PGT {preset.name} (step {ck['step']}) on held-out {source.name} "
                                      f"({args.eval_split}), {views} views")
        print(_summary(res["metrics"]))
        for r in res["rows"]:
            print(f"  {r['method']:>17} kappa={r['budget']:<5g} n={r['n_gaussians']:>8.0f} PSNR {r['psnr']:.2f} "
                  f"(covered {r['psnr_covered']:.2f}) SSIM {r['ssim']:.3f} render {r['render_ms']:.1f} ms")
    except ValueError as e:
        print(f"clsplat eval pgt: {e}", file=sys.stderr)
        return 2
    return 0
