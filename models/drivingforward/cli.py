"""``clsplat train drivingforward`` and ``clsplat eval drivingforward``.

    clsplat train drivingforward --data synthetic|pandaset:PATH|nuscenes:PATH --preset tiny|small|small-odometry|paper
                                 --steps N --out DIR [--resume] [--weights RESNET18.pth]
                                 [--lpips-vgg VGG.pth --lpips-lin LIN.pth] [--eval-scenes K]
                                 [--pose network|dataset|geometric] [--set FIELD=VALUE ...] [--eval-split val|test]
                                 [--val-every N] [--val-scenes K]
                                 [--view [--view-port P] [--view-every N]]
    clsplat eval drivingforward --checkpoint FILE --data ... [--cameras ...] [--offsets ...]
                                [--eval-split val|test] --out DIR

``--data synthetic`` is the varied world (``synthetic:varied``: ego speed, path, road, layout,
traffic and sun drawn per street); ``synthetic:classic`` is the one street of the earlier releases.
Train, validation and test streets have disjoint seeds; ``--eval-split val`` scores the validation
streets (where a preset field is chosen), ``test`` (the default) the test streets.

Training uses the shared loop (``clsplat.models.common.train``): Adam at the preset's learning
rate, one new window (synthetic: a new street) per sample, colour jitter on the network inputs
drawn from the sample's own generator, JSONL log, loss PNG, checkpoints with optimiser and RNG
state, bitwise ``--resume``, DDP under ``torchrun``. After training, ``DIR/metrics.json`` holds the
evaluation on ``--eval-scenes`` held-out windows, and ``DIR/val_curve.jsonl`` / ``val_curve.png`` the
learning curve: depth AbsRel, delta<1.25 and scale ratio and the pose network's translation error on
``--val-scenes`` validation windows, before the first step and every ``--val-every`` steps.

``--pose dataset`` trains with the data's ego motion in place of the pose network (the preset's
``pose_source``); ``--set FIELD=VALUE`` changes one preset field for an experiment (a Python
literal: ``--set detach_render_pose=True --set "pose_translation_init=(0, 0, -0.8)"``). Both are
stored in the checkpoint with the preset, so ``--resume`` and ``clsplat eval`` run the same preset.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..common.cli import positive_int
from ..common.command import Family, Restored, TrainJob, eval_main, restore, train_main
from ..common.presets import apply_sets
from .data import DEFAULT_WORLD
from .training import ValCurve, make_optimizer, make_sample_loss, make_scheduler

__all__ = ["train", "evaluate", "build_model", "load_model", "make_optimizer", "make_sample_loss", "COMMANDS",
           "DEFAULT_WORLD", "ValCurve"]



def _add_cameras_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", nargs="+", default=None, help="camera names (default: all, rig order)")


def build_model(preset, weights=None, device=None):
    """A :class:`DrivingForward` for ``preset``; prints which backbone initialisation it used."""
    from .model import DrivingForward

    model = DrivingForward(preset, weights=weights, device=device)
    print(model.init_message, flush=True)
    return model


def load_model(path: str, device=None, preset_name: str | None = None):
    """(model, preset) from a checkpoint written by ``clsplat train drivingforward``
    (:func:`~clsplat.models.common.command.restore`: the run's ``--pose`` / ``--set`` changes
    travel in the checkpoint; ``preset_name`` refuses a checkpoint of another preset)."""
    r = restore(COMMANDS, path, device, preset_name)
    return r.model, r.preset


class DrivingForwardCommands(Family):
    """DrivingForward's parts of the command skeleton (:mod:`clsplat.models.common.command`)."""

    name = "drivingforward"
    title = "DrivingForward"
    default_world = DEFAULT_WORLD
    train_help = __doc__

    def add_train_args(self, p: argparse.ArgumentParser) -> None:
        _add_cameras_arg(p)
        p.add_argument("--val-every", type=int, default=25,
                       help="steps between points of the validation learning curve (default 25; 0: none)")
        p.add_argument("--val-scenes", type=positive_int, default=4,
                       help="validation windows behind each point of the learning curve (default 4)")
        p.add_argument("--pose", choices=("network", "dataset", "geometric"), default=None,
                       help="ego motion of the temporal warps: the pose network (the paper; default: the "
                            "preset's), the data's ego poses, or the motion measured from each window's images "
                            "through the calibration's ground plane (geometric_size: --set "
                            "'geometric_size=(176, 320)'); the pose network is not trained but with 'network'")

    def train_preset(self, args, preset):
        if args.val_every < 0:
            raise ValueError(f"--val-every: expected an int >= 0, got {args.val_every}")
        return apply_sets(preset, None, pose_source=args.pose)

    def build(self, job: TrainJob):
        return build_model(job.preset, job.args.weights, job.args.device)

    def scene(self, job: TrainJob):
        # the model run on held-out sample 0 (input cameras, depth maps), refreshed as it trains
        from .view import model_scene
        return model_scene(job.model, job.preset, job.data, job.args.data, cameras=job.args.cameras,
                           title="DrivingForward (training)")

    def fit(self, job: TrainJob) -> bool:
        from ..common.train import TrainSpec, distributed_info, train as run
        a, preset, model = job.args, job.preset, job.model
        spec = TrainSpec(out_dir=job.stage, steps=a.steps or preset.steps,
                         batch_size=a.batch_size or preset.batch_size, checkpoint_every=a.checkpoint_every,
                         grad_clip=preset.grad_clip, seed=a.seed, resume=a.resume, progress=not a.no_progress)
        curve = ValCurve(model, job.data, job.stage / "val_curve.jsonl", a.val_every, a.val_scenes, a.cameras,
                         a.resume) if a.val_every and distributed_info()[0] == 0 else None
        hooks = [h for h in (job.on_step, curve and curve.on_step) if h is not None]
        opt = make_optimizer(model, preset)
        run(model, opt, spec, preset, self.name, make_sample_loss(job.data, preset, a.seed, a.cameras, job.lpips),
            scheduler=make_scheduler(opt, preset),
            on_step=(lambda step, rec: [h(step, rec) for h in hooks]) if hooks else None)
        if curve is not None:
            curve.plot(job.stage / "val_curve.png")
        job.extra["steps"] = spec.steps
        return True

    def evaluate_run(self, job: TrainJob) -> str:
        if job.args.eval_scenes <= 0:
            return ""
        from .evaluation import evaluate_model
        a = job.args
        m = evaluate_model(job.model, job.data, a.eval_scenes, a.cameras, lpips=job.lpips, out_dir=job.stage,
                           step=job.extra["steps"], split=a.eval_split)
        return _summary(m)

    def add_eval_args(self, p: argparse.ArgumentParser) -> None:
        _add_cameras_arg(p)
        p.add_argument("--preset", default=None, help="expected preset (default: the checkpoint's)")
        p.add_argument("--offsets", nargs="+", type=int, default=None,
                       help="input frames as offsets from t in {-1, 0, 1} (default SF: 0; MF: -1 1)")
        p.add_argument("--target", type=int, default=None, help="rendered frame offset (default SF: 1; MF: 0)")
        p.add_argument("--no-oracle", action="store_true", help="skip the oracle-depth baseline")
        p.add_argument("--layout-windows", type=int, default=None,
                       help="training windows behind the image-blind controls (the layout baseline, a per-pixel "
                            "median true depth, and the constant motion, their mean camera motion; 0: skip them; "
                            "default: the preset's layout_windows, 32 in small)")
        p.add_argument("--supersample", type=positive_int, default=None,
                       help="synthetic only: rays per pixel side of the held-out images (default: the "
                            "checkpoint's preset), to score models trained on different images on the same ones")

    def restore_model(self, ck: dict, preset, path: Path, device=None, **context):
        model = build_model(preset, None, device)
        model.load_state_dict(ck["model"])
        model.trained_steps = int(ck.get("step", 0))   # recorded in metrics.json by eval
        return model

    def evaluate_checkpoint(self, restored: Restored, args, stage: Path, lpips) -> str:
        from ..common.data import parse_data
        from .evaluation import evaluate_model
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle,
                            default_world=self.default_world)
        model = restored.model
        m = evaluate_model(model, source, args.num_scenes, args.cameras, args.offsets, args.target, lpips,
                           out_dir=stage, oracle=not args.no_oracle, progress=not args.no_progress,
                           step=model.trained_steps, supersample=args.supersample, layout=args.layout_windows,
                           split=args.eval_split)
        return _summary(m) + f"\nwrote {args.out}/metrics.json, contact_sheet.png, depth_sheet.png"

    def checkpoint_scene(self, restored: Restored, run: Path, data: str | None, sample: int = 0,
                         safe_pickle: bool = True):
        from .view import checkpoint_scene
        return checkpoint_scene(restored.model, restored.preset, run, data, sample, safe_pickle)


COMMANDS = DrivingForwardCommands()


def _summary(m: dict) -> str:
    keys = ("psnr", "ssim", "lpips", "abs_rel", "sq_rel", "rmse", "delta1", "scale_ratio", "oracle_psnr",
            "layout_abs_rel", "layout_delta1", "pose_t_err_m", "pose_t_err_pct_median", "constant_motion_t_err_pct_median",
            "pose_r_err_deg")
    lines = [f"eval {m['protocol']['split']} all: " + ", ".join(f"{k} {m['all'][k]:.4g}" for k in keys
                                                              if m["all"].get(k) is not None)]
    for name, b in m.get("speed_bins", {}).items():
        if b.get("windows"):
            lines.append(f"  {name} m/s ({b['windows']} windows): " + ", ".join(
                f"{k} {b[k]:.4g}" for k in ("abs_rel", "delta1", "scale_ratio", "layout_abs_rel", "pose_t_err_m",
                                            "pose_t_err_pct_median", "constant_motion_t_err_pct_median")
                if b.get(k) is not None))
    return "\n".join(lines)


def train(argv: list[str]) -> int:
    """Entry point of ``clsplat train drivingforward``; returns the exit code."""
    return train_main(COMMANDS, argv)


def evaluate(argv: list[str]) -> int:
    """Entry point of ``clsplat eval drivingforward``; returns the exit code."""
    return eval_main(COMMANDS, argv)
