"""``clsplat train autosplat`` (reconstruct one sequence, evaluate it, write the run folder) and
``clsplat eval autosplat`` (re-evaluate a run from its checkpoint).

    clsplat train autosplat --data synthetic|pandaset:PATH|nuscenes:PATH [--cameras CAM ...]
        [--frames A:B] [--scale S] [--preset NAME] [--steps N] [--set FIELD=VALUE] [--holdout K]
        [--no-flatness] [--no-symmetry] [--no-residual-sh] [--no-pose-correction] [--no-densify]
        [--no-decompose] [--masks DIR] [--views SET ...] [--batch-size B] --out DIR [--resume]
        [--stop-after N]
        [--view [--view-port P] [--view-every N]]
    clsplat eval autosplat --checkpoint RUN/checkpoint.pt --out DIR [--data ...] [--scale S]
        [--views recorded|far-side|lane-change|appearance ...]

``--no-decompose`` is plain 3DGS from LiDAR (one static set, no objects, no phase 1). ``--steps N``
rescales the preset's four stages to N iterations in all, each keeping its share (and the
iterations a scene's objects add, by the same factor). ``--batch-size B``
trains on B frames per iteration (default 1); under ``torchrun`` the ranks share them (data
parallel on the shared loop, so B must be at least the number of processes). ``--views``
picks the test sets scored (:mod:`.viewsets`; default ``recorded lane-change``): ``far-side``
(metrics.json ``far_side``: the moving vehicles' far side, ``psnr_objects``), ``lane-change``
(``lane_change``: keys ``1m``, ``2m``, ``3m``), ``appearance`` (``appearance``:
``psnr_changing_pixels``), ``recorded`` (``train``, and ``pose_correction`` under tracker noise);
``all``/``per_camera`` always hold the held-out frames of the recorded path. ``--data
synthetic:views`` is the street those sets are built for (signal lamps, a shadow, tracker noise).

Writes ``DIR/metrics.json`` (:mod:`clsplat.models.common.report`'s schema: held-out PSNR, SSIM
per camera and overall with PSNR over object pixels, LPIPS when weights are given; ``train`` the
same on the training frames; the view sets' sections, Gaussian counts per class, seconds per
stage), ``DIR/scene.ply``,
``DIR/checkpoint.pt``, ``DIR/log.jsonl``, ``DIR/loss.png``, ``DIR/contact_sheet.png`` and
``DIR/lateral_shift_{1,2,3}m.png``.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from ..common.command import Family, Restored, TrainJob, eval_main, train_main
from .data import load_sequence, parse_frames

__all__ = ["train", "evaluate", "reconstruct", "finish_run", "COMMANDS"]

#: the --no-FLAG switches of ``train``, each a field of :class:`~.model.Switches`
SWITCH_FLAGS = ("decompose", "flatness", "symmetry", "residual-sh", "pose-correction", "densify")


def _add_views_arg(p: argparse.ArgumentParser) -> None:
    from .evaluate import DEFAULT_VIEWS
    from .viewsets import VIEW_SETS
    p.add_argument("--views", nargs="+", default=list(DEFAULT_VIEWS), choices=VIEW_SETS, metavar="SET",
                   help=f"test sets to score, some of {', '.join(VIEW_SETS)} (default: {' '.join(DEFAULT_VIEWS)}); "
                        "far-side and appearance need generated data")


def _summary(metrics: dict) -> str:
    """The one-line result of a run: held-out PSNR / SSIM, the training frames' PSNR when the
    ``recorded`` set was scored (only it writes ``train``), and each other view set's headline."""
    line = f"held-out PSNR {metrics['all']['psnr']:.2f} dB  SSIM {metrics['all']['ssim']:.3f}"
    if "train" in metrics:
        line += f"  (train PSNR {metrics['train']['psnr']:.2f} dB)"
    fmt = lambda v: "n/a" if v is None else f"{v:.2f} dB"  # noqa: E731  (None: no pixels / no generator)
    if "far_side" in metrics:
        line += f"; far side {fmt(metrics['far_side'].get('psnr_objects'))} on object pixels"
    lc = metrics.get("lane_change")
    if lc and all(v is not None for v in lc.values()):
        line += "; lane change " + " / ".join(f"{k} {fmt(v['psnr'])}" for k, v in lc.items())
    if "appearance" in metrics:
        line += f"; changing pixels {fmt(metrics['appearance'].get('psnr_changing_pixels'))}"
    return line


def finish_run(trainer, t_start: float, lpips=None, extra: dict | None = None, views=None) -> dict:
    """Evaluate a finished run (rank 0) and write ``metrics.json`` and ``scene.ply`` into
    ``trainer.out``; returns the metrics. ``extra``: the run's ``data``, ``scale``, ``frames``
    (recorded in the protocol, what ``eval autosplat`` and the viewer rebuild the run from),
    ``load_seconds`` and further sections; ``t_start``: when the run started
    (``time.perf_counter``), for ``wall_seconds``."""
    from ..common.report import metrics_report, write_metrics
    from ..common.train import read_log
    from .evaluate import DEFAULT_VIEWS, evaluate_run

    steps = read_log(trainer.out / "log.jsonl")
    it = [r["time_s"] for r in steps]
    train_s = sum(it)
    ev = evaluate_run(trainer, lpips=lpips, views=DEFAULT_VIEWS if views is None else views)
    recorded = ("data", "scale", "frames")
    ev["protocol"].update({k: extra[k] for k in recorded if extra and k in extra})
    sections = {k: v for k, v in ev.items() if k not in ("protocol", "all", "per_camera", "eval_seconds")}
    sections.update({
        **{k: v for k, v in (extra or {}).items() if k not in recorded and k != "load_seconds"},
        "switches": trainer.switches.to_dict(),
        "seconds_per_stage": {**({"load": extra["load_seconds"]} if extra and "load_seconds" in extra else {}),
                              **trainer.stage_seconds, "eval": ev["eval_seconds"]},
        "seconds_per_iteration": float(np.median(it)) if it else None,
        # kernels' device time (forward + backward) from OpenCL profiling events, over step wall time
        "renderer_device_share": float(sum(r["renderer_device_s"] for r in steps) / train_s) if it else None,
        # wall time inside the rasterisation calls and loss.backward (an upper bound), over step wall time
        "renderer_wall_share": float(sum(r["render_wall_s"] + r["backward_s"] for r in steps) / train_s) if it else None,
        "wall_seconds": time.perf_counter() - t_start,
    })
    metrics = metrics_report("autosplat", trainer.preset.name, trainer.total, ev["protocol"], ev["all"],
                             ev["per_camera"], **sections)
    d = trainer.data
    show = d.test_frames[len(d.test_frames) // 2] if d.test_frames else d.train_frames[0]
    trainer.scene_gaussians(show).save_ply(trainer.out / "scene.ply")
    write_metrics(trainer.out, metrics)
    return metrics


def _stopped(trainer) -> bool:
    """True (and says so) when the run stopped before the end of its schedule (``--stop-after``)."""
    if trainer.step < trainer.total:
        print(f"stopped after {trainer.step} of {trainer.total} iterations (the unfinished run is in "
              f"{trainer.out}); continue with --resume")
        return True
    return False


def reconstruct(data, preset, switches, out: Path, *, device=None, progress: bool = True,
                checkpoint_every: int = 100, resume: bool = False, lpips=None,
                extra: dict | None = None, views=None) -> dict | None:
    """Train (or resume) and evaluate one run in the folder ``out`` (written in place: ``clsplat
    demo`` passes the staging folder of a :class:`~..common.runfolder.RunFolder`); the metrics,
    or None on a rank > 0 under ``torchrun``. ``clsplat train autosplat`` runs the same parts
    through the command skeleton (:class:`AutoSplatCommands`)."""
    from ..common.train import distributed_info
    from .evaluate import DEFAULT_VIEWS
    from .trainer import Trainer
    from .viewsets import check_views

    views = check_views(DEFAULT_VIEWS if views is None else views, data.seq)   # before minutes of training
    t_start = time.perf_counter()
    trainer = Trainer(data, preset, switches, out, device=device, progress=progress,
                      checkpoint_every=checkpoint_every)
    trainer.fit(resume=resume)
    if distributed_info()[0] != 0 or _stopped(trainer):
        return None
    return finish_run(trainer, t_start, lpips, extra, views)


class AutoSplatCommands(Family):
    """AutoSplat's parts of the command skeleton (:mod:`clsplat.models.common.command`): a
    per-scene optimisation, so the data is one sequence (its held-out frames are the test) and
    the model is the :class:`~.trainer.Trainer` holding the scene."""

    name = "autosplat"
    title = "AutoSplat"
    default_preset = "demo"
    feed_forward = False
    no_weights = "a per-scene optimisation of Gaussians initialised from LiDAR, no network encoder"
    train_help = __doc__.split("\n")[0]
    eval_help = ("re-evaluate a run from its checkpoint (on the run's data, or --data) into --out: "
                 "metrics.json, contact and lateral-shift sheets")

    def add_train_args(self, p: argparse.ArgumentParser) -> None:
        p.add_argument("--cameras", nargs="+", default=None, help="camera names (default: all)")
        p.add_argument("--frames", default=None, help="frame range A:B (default: the whole sequence; synthetic 0:16)")
        p.add_argument("--scale", type=float, default=None, help="image scale (default: the preset's)")
        p.add_argument("--holdout", type=int, default=None, help="hold out every K-th frame (default: the preset's)")
        p.add_argument("--masks", default=None, help="folder of semantic masks <CAM>/<NN>.png (class indices)")
        _add_views_arg(p)
        for flag in SWITCH_FLAGS:
            p.add_argument(f"--no-{flag}", action="store_true",
                           help=f"switch the {flag.replace('-', ' ')} constraint off")
        p.add_argument("--stop-after", type=int, default=None,
                       help="stop after this many iterations in all (checkpointed; continue with --resume)")

    def train_preset(self, args, preset):
        from .presets import with_total_steps
        if args.steps is not None:   # the four stages keep their shares of the schedule
            preset = with_total_steps(preset, args.steps)
        world = int(os.environ.get("WORLD_SIZE", "1"))   # torchrun's; checked before the process group starts
        if (args.batch_size or 1) < world:
            raise ValueError(f"--batch-size: {args.batch_size or 1} frame(s) per iteration cannot be shared by "
                             f"{world} processes; give --batch-size {world} or more")
        if args.stop_after is not None and args.stop_after < 1:
            raise ValueError(f"--stop-after: expected a positive number of iterations, got {args.stop_after}")
        if args.seed != preset.seed:
            preset = preset.replace(seed=args.seed)
        if args.holdout is not None:
            preset = preset.replace(holdout=args.holdout)
        return preset

    def load_data(self, job: TrainJob):
        from .data import prepare_data
        from .viewsets import check_views
        a, preset = job.args, job.preset
        scale = preset.scale if a.scale is None else a.scale
        frames = parse_frames(a.frames)
        seq = load_sequence(a.data, a.cameras, frames, scale, seed=a.seed, safe_pickle=not a.trust_pickle)
        if a.masks:
            from .init import load_mask_folder
            load_mask_folder(seq, a.masks, list(range(*(frames or (0, len(seq.frames))))))
        data = prepare_data(seq, a.cameras, preset.holdout, preset.dynamic_threshold, preset.road_classes)
        job.extra.update(views=check_views(a.views, seq),    # before minutes of training
                         record={"data": a.data, "scale": scale, "frames": list(frames) if frames else None})
        return data

    def build(self, job: TrainJob):
        from .model import Switches
        from .trainer import Trainer
        a = job.args
        switches = Switches(**{f.replace("-", "_"): not getattr(a, f"no_{f.replace('-', '_')}") for f in SWITCH_FLAGS})
        job.extra["t_start"] = time.perf_counter()
        return Trainer(job.data, job.preset, switches, job.stage, device=a.device, progress=not a.no_progress,
                       checkpoint_every=a.checkpoint_every, batch_size=a.batch_size or 1)

    def scene(self, job: TrainJob):
        from .view import autosplat_scene
        tr = job.model
        return autosplat_scene(tr.model, job.data.seq, job.data, f"AutoSplat {job.preset.name} (training, step {tr.step})")

    def fit(self, job: TrainJob) -> bool:
        from ..common.train import distributed_info
        tr = job.model
        tr.fit(resume=job.args.resume, stop_at=job.args.stop_after, on_step=job.on_step)
        return distributed_info()[0] != 0 or not _stopped(tr)

    def evaluate_run(self, job: TrainJob) -> str:
        m = finish_run(job.model, job.extra["t_start"], job.lpips,
                       {**job.extra["record"], "load_seconds": job.extra["load_seconds"]}, job.extra["views"])
        return f"{_summary(m)}; {m['gaussians']['total']} Gaussians; outputs in {job.args.out}"

    def add_eval_args(self, p: argparse.ArgumentParser) -> None:
        _add_views_arg(p)
        p.add_argument("--scale", type=float, default=None,
                       help="image scale the run trained at (default: the one its metrics.json records, "
                            "else the preset's)")
        p.set_defaults(data=None)   # the run's own data

    def checkpoint_path(self, args) -> Path:
        from ..common.runfolder import STAGING
        ck = Path(args.checkpoint)
        if ck.is_dir():   # a run folder: its checkpoint, finished or not
            ck = next((c for c in (ck / "checkpoint.pt", ck / STAGING / "checkpoint.pt") if c.is_file()),
                      ck / "checkpoint.pt")
        return ck

    def restore_model(self, ck: dict, preset, path: Path, device=None, data: str | None = None,
                      safe_pickle: bool = True, scale: float | None = None, **context):
        """The run's :class:`~.trainer.Trainer` rebuilt on its data (:func:`.evaluate.trainer_from_checkpoint`)."""
        from ..common.runfolder import STAGING
        from .evaluate import trainer_from_checkpoint
        run = path.parent.parent if path.parent.name == STAGING else path.parent
        return trainer_from_checkpoint(ck, path, run, data, device=device, arg="--checkpoint",
                                       safe_pickle=safe_pickle, scale=scale)

    def evaluate_checkpoint(self, restored: Restored, args, stage: Path, lpips) -> str:
        from ..common.report import metrics_report, write_metrics
        from .evaluate import evaluate_run
        tr = restored.model
        tr.out = stage   # the sheets go with metrics.json
        ev = evaluate_run(tr, lpips=lpips, views=args.views)
        ev["protocol"]["checkpoint"] = str(restored.path)
        sections = {k: v for k, v in ev.items() if k not in ("protocol", "all", "per_camera", "eval_seconds")}
        m = metrics_report("autosplat", tr.preset.name, tr.step, ev["protocol"], ev["all"], ev["per_camera"],
                           switches=tr.switches.to_dict(), eval_seconds=ev["eval_seconds"], **sections)
        write_metrics(stage, m)
        return f"{_summary(m)} at step {tr.step}; wrote {args.out}/metrics.json"

    def checkpoint_scene(self, restored: Restored, run: Path, data: str | None, sample: int = 0,
                         safe_pickle: bool = True):
        # ``sample`` is unused: the model is the scene
        from .view import autosplat_scene
        tr = restored.model
        return autosplat_scene(tr.model, tr.data.seq, tr.data, f"AutoSplat {tr.preset.name} ({run.name})")


COMMANDS = AutoSplatCommands()


def train(argv: list[str]) -> int:
    """Entry point of ``clsplat train autosplat``; returns the exit status."""
    return train_main(COMMANDS, argv)


def evaluate(argv: list[str]) -> int:
    """Entry point of ``clsplat eval autosplat``; returns the exit status."""
    return eval_main(COMMANDS, argv)
