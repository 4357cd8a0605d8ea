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

import argparse
from pathlib import Path

from clsplat.models.common.command import Family, Restored, TrainJob, eval_main, train_main
from clsplat.models.common.presets import check_preset_matches

from .budget import check_kappa
from .presets import BUDGET_FIELDS, saved_preset

__all__ = ["train", "evaluate", "parse_budgets", "check_views_arg", "COMMANDS"]

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


class PGTCommands(Family):
    """PGT's (and EcoSplat's budget stage's) parts of the command skeleton
    (:mod:`clsplat.models.common.command`)."""

    name = FAMILY
    title = "PGT"
    no_weights = "its U-Net encoder and matcher train from random initialisation, as in the paper"
    train_help = "Train PGT (base) or EcoSplat's budget stage."
    eval_help = "Evaluate PGT on held-out data: budget curve."

    def add_train_args(self, p: argparse.ArgumentParser) -> None:
        p.add_argument("--stage", choices=("base", "budget"), default="base",
                       help="base: the pixel-aligned predictor; budget: EcoSplat stage 2 from --init")
        p.add_argument("--init", default=None, help="base checkpoint to start the budget stage from")

    def train_preset(self, args, preset):
        if args.stage == "budget" and args.init is None and not args.resume:
            raise ValueError("--init: the budget stage starts from a base checkpoint; give --init FILE")
        return preset

    def build(self, job: TrainJob):
        from ..common.train import load_checkpoint
        from .model import PGT
        a, preset = job.args, job.preset
        model = PGT(preset)
        if a.stage == "budget":
            if a.init is not None:
                ck = load_checkpoint(a.init, FAMILY)
                # the base network must match; the budget stage's own fields may differ
                saved = dict(ck.get("preset") or {})
                saved.update({k: v for k, v in preset.to_dict().items() if k in BUDGET_FIELDS})
                check_preset_matches(saved, preset, str(a.init))
                model.load_state_dict({k: v for k, v in ck["model"].items() if not k.startswith("budget.")})
            model.enable_budget()
        job.extra["steps"] = a.steps or (preset.steps if a.stage == "base" else preset.budget_steps)
        return model

    def scene(self, job: TrainJob):
        # the model run on held-out sample 0 (input/target cameras, depth), refreshed as it trains
        from .view import model_scene
        return model_scene(job.model, job.preset, job.data, job.args.data, title=f"PGT {job.args.stage} (training)")

    def fit(self, job: TrainJob) -> bool:
        from ..common.train import TrainSpec, train as run
        from .training import make_optimizer, make_sample_loss
        a, preset, steps = job.args, job.preset, job.extra["steps"]
        opt, sched = make_optimizer(job.model, preset, steps, a.stage)
        spec = TrainSpec(out_dir=job.stage, steps=steps, batch_size=a.batch_size or preset.batch_size,
                         checkpoint_every=a.checkpoint_every, seed=a.seed, grad_clip=preset.grad_clip,
                         resume=a.resume, progress=not a.no_progress)
        run(job.model, opt, spec, preset, FAMILY,   # the loss's LPIPS term only when w_lpips asks for it
            make_sample_loss(job.data, preset, a.stage, a.seed, job.lpips if preset.w_lpips else None),
            scheduler=sched, extra_state={"stage": a.stage}, on_step=job.on_step)
        return True

    def evaluate_run(self, job: TrainJob) -> str:
        a, preset, steps = job.args, job.preset, job.extra["steps"]
        if a.eval_scenes <= 0:
            return ""
        from .evaluate import evaluate_model, write_results
        res = evaluate_model(job.model, job.data, preset, [1.0] if a.stage == "base" else DEFAULT_BUDGETS,
                             a.eval_scenes, a.seed, sheet=job.stage / "contact_sheet.png", lpips=job.lpips,
                             step=steps, views=2 if a.stage == "base" else preset.budget_views, split=a.eval_split)
        write_results(res, job.stage, f"PGT {preset.name} ({a.stage}, step {steps}) on held-out "
                                      f"{job.data.name} ({a.eval_split})")
        return _summary(res["metrics"])

    def add_eval_args(self, p: argparse.ArgumentParser) -> None:
        p.add_argument("--budgets", default=",".join(f"{k:g}" for k in DEFAULT_BUDGETS),
                       help="comma-separated κ in (0, 1]")
        p.add_argument("--repeats", type=int, default=3, help="timed renders per point (median)")
        p.add_argument("--views", type=int, default=DEFAULT_VIEWS,
                       help="source views per sample: 2 (the base protocol: two frames of one camera) or 3..24 "
                            "(the multi-view protocol: rig cameras at several instants, targets between them)")

    def check_eval_args(self, args) -> None:
        parse_budgets(args.budgets)
        check_views_arg(args.views)
        if args.repeats < 1:
            raise ValueError(f"--repeats: expected at least 1, got {args.repeats}")

    def saved_preset(self, saved, name=None):
        return saved_preset(saved)   # a budget field its record lacks: the code's default when it was written

    def restore_model(self, ck: dict, preset, path: Path, device=None, **context):
        from .model import PGT
        model = PGT(preset)
        if any(k.startswith("budget.") for k in ck["model"]):
            model.enable_budget()
        model.load_state_dict(ck["model"])
        return model

    def evaluate_checkpoint(self, restored: Restored, args, stage: Path, lpips) -> str:
        from ..common.data import parse_data
        from .evaluate import evaluate_model, write_results
        budgets, views = parse_budgets(args.budgets), check_views_arg(args.views)
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle,
                            default_world=self.default_world)
        preset, step = restored.preset, int(restored.checkpoint["step"])
        res = evaluate_model(restored.model, source, preset, budgets, args.num_scenes, args.seed, args.repeats,
                             sheet=stage / "contact_sheet.png", lpips=lpips, step=step, views=views,
                             split=args.eval_split)
        res["metrics"]["checkpoint"] = str(args.checkpoint)
        write_results(res, stage, f"PGT {preset.name} (step {step}) on held-out {source.name} "
                                  f"({args.eval_split}), {views} views")
        return "\n".join([_summary(res["metrics"])] + [
            f"  {r['method']:>17} kappa={r['budget']:<5g} n={r['n_gaussians']:>8.0f} PSNR {r['psnr']:.2f} "
            f"(covered {r['psnr_covered']:.2f}) SSIM {r['ssim']:.3f} render {r['render_ms']:.1f} ms"
            for r in res["rows"]])

    def checkpoint_scene(self, restored: Restored, run: Path, data: str | None, sample: int = 0,
                         safe_pickle: bool = True):
        from .view import checkpoint_scene
        return checkpoint_scene(restored.model, restored.preset, run, data, sample, safe_pickle)


COMMANDS = PGTCommands()


def train(argv: list[str]) -> int:
    """``clsplat train pgt ...``; returns the exit status."""
    return train_main(COMMANDS, argv)


def evaluate(argv: list[str]) -> int:
    """``clsplat eval pgt ...``; returns the exit status."""
    return eval_main(COMMANDS, argv)
