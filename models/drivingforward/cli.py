"""``clsplat train drivingforward`` and ``clsplat eval drivingforward``.

    clsplat train drivingforward --data synthetic|pandaset:PATH|nuscenes:PATH --preset tiny|small|paper
                                 --steps N --out DIR [--resume] [--weights RESNET18.pth]
                                 [--lpips-vgg VGG.pth --lpips-lin LIN.pth] [--eval-scenes K]
                                 [--pose network|dataset] [--set FIELD=VALUE ...] [--eval-split val|test]
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
import sys

import torch

from clsplat.argparser import ArgumentParser

from ..common.cli import (add_common_args, add_eval_args, add_eval_scenes_arg, add_eval_split_arg, add_view_args,
                          lpips_from_args, positive_int)
from ..common.data import parse_data
from ..common.presets import apply_sets, get_preset
from .checkpoint import FAMILY, build_model, load_model

__all__ = ["train", "evaluate", "build_model", "load_model", "make_sample_loss", "DEFAULT_WORLD"]

#: the synthetic world of a plain ``--data synthetic``
DEFAULT_WORLD = "varied"


def _add_cameras_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", nargs="+", default=None, help="camera names (default: all, rig order)")


def preset_overrides(preset, pose: str | None, sets: list[str] | None):
    """``preset`` with ``--pose`` and every ``--set FIELD=VALUE`` applied (ValueError naming the
    argument on a bad field or value)."""
    return apply_sets(preset, sets, pose_source=pose)


def make_optimizer(model, preset) -> torch.optim.Adam:
    """Adam at ``preset.lr``; the pose network at ``preset.pose_lr`` when the preset sets one."""
    pose = list(model.pose_net.parameters())
    ids = {id(q) for q in pose}
    rest = [q for q in model.parameters() if id(q) not in ids]
    groups = [{"params": rest}, {"params": pose, "lr": preset.pose_lr or preset.lr}]
    return torch.optim.Adam(groups, lr=preset.lr)


def make_scheduler(opt: torch.optim.Optimizer, preset) -> torch.optim.lr_scheduler.LambdaLR | None:
    """The linear learning-rate warm-up of ``preset.lr_warmup`` (None when it is 0): step s
    (from 0) runs at (s + 1) / lr_warmup of every group's rate until the ramp reaches 1."""
    n = preset.lr_warmup
    if n == 0:
        return None
    return torch.optim.lr_scheduler.LambdaLR(opt, lambda s: min(1.0, (s + 1) / n))


def make_sample_loss(source, preset, seed: int, cameras=None, lpips=None):
    """``sample_loss(model, step, index)`` for :func:`clsplat.models.common.train.train`: window
    ``index`` of the train split, jitter and automask noise from the sample's own generator."""
    from ..common.train import sample_generator
    from .data import colour_jitter, gt_ego_motion, load_triplet

    def sample_loss(model, step: int, index: int) -> dict:
        s = load_triplet(source, index, preset, "train", cameras)
        g = sample_generator(seed, index)
        net = colour_jitter(s["images"], g, preset.jitter)
        V = s["Ks"].shape[0]
        noise = torch.randn(V, 2, preset.height, preset.width, generator=g) * preset.automask_noise
        gt = None
        if preset.pose_source == "dataset":
            M = gt_ego_motion(s)
            gt = [M[0], M[2]]
        return model.training_losses(s["images"], net, s["Ks"], s["cam_to_ego"], noise, lpips, step, gt)

    return sample_loss


class ValCurve:
    """The validation learning curve of a run: :func:`~.evaluation.validation_point` before the
    first step and every ``every`` steps, one JSON line per point in ``path``, plotted to a PNG.
    On ``--resume`` the points after the resumed step (written by the interrupted run) are dropped
    when the first new one comes, so the file reads as one run. The points draw no random numbers,
    so the training they watch stays bitwise what it is without them."""

    def __init__(self, model, source, path, every: int, scenes: int, cameras=None, resume: bool = False) -> None:
        from pathlib import Path

        from .evaluation import validation_point
        self._point = validation_point
        self.model, self.source, self.path = model, source, Path(path)
        self.every, self.scenes, self.cameras = every, scenes, cameras
        self.records: list[dict] = []
        if resume and self.path.is_file():
            from ..common.train import read_log
            self.records = read_log(self.path)
        self._trim_at: int | None = 0 if resume else None
        try:                # a recorded sequence too short for a validation window: the run goes on without
            validation_point(model, source, 1, cameras)
        except ValueError as e:
            print(f"no validation curve: {e}", flush=True)
            self.every = 0
            return
        if not resume:
            self._add(0)

    def _add(self, step: int) -> None:
        import json
        from clsplat.io.atomic import write_text_atomic
        if self._trim_at is not None:       # the first point of a resumed run: drop what came after its start
            self.records = [r for r in self.records if r["step"] < step]
            self._trim_at = None
        self.records.append({"step": step, **self._point(self.model, self.source, self.scenes, self.cameras)})
        write_text_atomic(self.path, "".join(json.dumps(r, allow_nan=True) + "\n" for r in self.records))

    def on_step(self, step: int, rec: dict) -> None:
        if self.every and step % self.every == 0:
            self._add(step)

    def plot(self, png) -> None:
        """Three panels against step: AbsRel, scale ratio and the pose translation error (median %)."""
        if not self.records:
            return
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from clsplat.io.atomic import atomic_write
        fig, axes = plt.subplots(1, 3, figsize=(11, 3.2), dpi=110)
        for ax, key, label in zip(axes, ("abs_rel", "scale_ratio", "pose_t_err_pct_median"),
                                  ("depth AbsRel", "scale ratio (median gt / median pred)", "pose t error (median %)")):
            pts = [(r["step"], r[key]) for r in self.records if isinstance(r.get(key), (int, float))]
            if pts:
                ax.plot(*zip(*pts), marker=".")
            ax.set_title(label, fontsize=9)
            ax.set_xlabel("step")
            ax.grid(alpha=0.3)
        fig.suptitle(f"validation ({self.scenes} windows of {self.source.name})", fontsize=9)
        fig.tight_layout()
        atomic_write(png, lambda p: fig.savefig(p, format="png"))
        plt.close(fig)


def train(argv: list[str]) -> int:
    """Entry point of ``clsplat train drivingforward``; returns the exit code."""
    from ..common.train import TrainSpec, seed_everything, set_threads, train as run
    from .evaluation import evaluate_model

    p = ArgumentParser(prog="clsplat train drivingforward", description=__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_args(p, default_preset="small")
    _add_cameras_arg(p)
    add_eval_scenes_arg(p)
    add_eval_split_arg(p)
    p.add_argument("--val-every", type=int, default=25,
                   help="steps between points of the validation learning curve (default 25; 0: none)")
    p.add_argument("--val-scenes", type=positive_int, default=4,
                   help="validation windows behind each point of the learning curve (default 4)")
    p.add_argument("--pose", choices=("network", "dataset"), default=None,
                   help="ego motion of the temporal warps: the pose network (the paper; default: the "
                        "preset's) or the data's ego poses (the pose network is not trained)")
    add_view_args(p)
    args = p.parse_args(argv)
    try:
        if args.val_every < 0:
            raise ValueError(f"--val-every: expected an int >= 0, got {args.val_every}")
        preset = preset_overrides(get_preset(FAMILY, args.preset), args.pose, args.set)
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle, default_world=DEFAULT_WORLD)
        threads = set_threads(args.threads, args.device)
        seed_everything(args.seed)
        model = build_model(preset, args.weights, args.device)
        lpips = lpips_from_args(args)
        opt = make_optimizer(model, preset)
        from ..common.view import train_watcher
        from .view import model_scene
        # --view: the model run on held-out sample 0 (input cameras, depth maps), refreshed as it trains
        watcher = train_watcher(args, lambda: model_scene(model, preset, source, args.data, cameras=args.cameras,
                                                          title="DrivingForward (training)"), args.device)
        from ..common.runfolder import RunFolder
        from ..common.train import distributed_info, end_distributed
        distributed_info()
        with RunFolder(args.out, resume=args.resume) as rf:  # the lock; outputs staged, then published as a group
            spec = TrainSpec(out_dir=rf.stage, steps=args.steps or preset.steps,
                             batch_size=args.batch_size or preset.batch_size, checkpoint_every=args.checkpoint_every,
                             grad_clip=preset.grad_clip, seed=args.seed, resume=args.resume,
                             progress=not args.no_progress)
            print(f"data {source.name}, torch threads {threads}", flush=True)
            rank0 = distributed_info()[0] == 0
            curve = ValCurve(model, source, rf.stage / "val_curve.jsonl", args.val_every, args.val_scenes,
                             args.cameras, args.resume) if args.val_every and rank0 else None
            hooks = [h.on_step for h in (watcher, curve) if h is not None]
            try:
                run(model, opt, spec, preset, FAMILY, make_sample_loss(source, preset, args.seed, args.cameras, lpips),
                    scheduler=make_scheduler(opt, preset),
                    on_step=(lambda step, rec: [h(step, rec) for h in hooks]) if hooks else None)
            finally:
                if watcher is not None:
                    watcher.close()
            if curve is not None:
                curve.plot(rf.stage / "val_curve.png")
            if args.eval_scenes > 0 and rank0:
                m = evaluate_model(model, source, args.eval_scenes, args.cameras, lpips=lpips, out_dir=rf.stage,
                                   step=spec.steps, split=args.eval_split)
                print(_summary(m), flush=True)
            rf.publish()
        end_distributed()
    except ValueError as e:
        print(f"clsplat train drivingforward: {e}", file=sys.stderr)
        return 2
    return 0


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


def evaluate(argv: list[str]) -> int:
    """Entry point of ``clsplat eval drivingforward``; returns the exit code."""
    from ..common.train import set_threads
    from .evaluation import evaluate_model

    p = ArgumentParser(prog="clsplat eval drivingforward")
    add_eval_args(p)
    add_eval_split_arg(p)
    _add_cameras_arg(p)
    p.add_argument("--preset", default=None, help="expected preset (default: the checkpoint's)")
    p.add_argument("--offsets", nargs="+", type=int, default=None,
                   help="input frames as offsets from t in {-1, 0, 1} (default SF: 0; MF: -1 1)")
    p.add_argument("--target", type=int, default=None, help="rendered frame offset (default SF: 1; MF: 0)")
    p.add_argument("--no-oracle", action="store_true", help="skip the oracle-depth baseline")
    p.add_argument("--layout-windows", type=int, default=32,
                   help="training windows behind the image-blind controls (the layout baseline, a per-pixel "
                        "median true depth, and the constant motion, their mean camera motion; 0: skip them)")
    p.add_argument("--supersample", type=positive_int, default=None,
                   help="synthetic only: rays per pixel side of the held-out images (default: the "
                        "checkpoint's preset), to score models trained on different images on the same ones")
    args = p.parse_args(argv)
    try:
        set_threads(args.threads, args.device)
        model, preset = load_model(args.checkpoint, args.device, args.preset)
        source = parse_data(args.data, seed=args.seed, safe_pickle=not args.trust_pickle, default_world=DEFAULT_WORLD)
        lpips = lpips_from_args(args)
        from clsplat.io.atomic import staged_group
        with staged_group(args.out) as stage:  # the three files replace an earlier evaluation's together
            m = evaluate_model(model, source, args.num_scenes, args.cameras, args.offsets, args.target, lpips,
                               out_dir=stage, oracle=not args.no_oracle, progress=not args.no_progress,
                               step=model.trained_steps, supersample=args.supersample, layout=args.layout_windows,
                               split=args.eval_split)
        print(_summary(m))
        print(f"wrote {args.out}/metrics.json, contact_sheet.png, depth_sheet.png")
    except ValueError as e:
        print(f"clsplat eval drivingforward: {e}", file=sys.stderr)
        return 2
    return 0
