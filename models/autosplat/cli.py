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
rescales the preset's four stages to N iterations in all, each keeping its share. ``--batch-size B``
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

from clsplat.argparser import ArgumentParser

from .data import load_sequence, parse_frames

__all__ = ["train", "evaluate", "reconstruct"]

def _parser() -> argparse.ArgumentParser:
    from ..common.cli import add_common_args, add_view_args
    p = ArgumentParser(prog="clsplat train autosplat", description=__doc__.split("\n")[0])
    add_common_args(p, default_preset="demo")
    p.add_argument("--cameras", nargs="+", default=None, help="camera names (default: all)")
    p.add_argument("--frames", default=None, help="frame range A:B (default: the whole sequence; synthetic 0:16)")
    p.add_argument("--scale", type=float, default=None, help="image scale (default: the preset's)")
    p.add_argument("--holdout", type=int, default=None, help="hold out every K-th frame (default: the preset's)")
    p.add_argument("--masks", default=None, help="folder of semantic masks <CAM>/<NN>.png (class indices)")
    _add_views_arg(p)
    for flag in ("decompose", "flatness", "symmetry", "residual-sh", "pose-correction", "densify"):
        p.add_argument(f"--no-{flag}", action="store_true", help=f"switch the {flag.replace('-', ' ')} constraint off")
    add_view_args(p)
    p.add_argument("--stop-after", type=int, default=None,
                   help="stop after this many iterations in all (checkpointed; continue with --resume)")
    return p


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


def reconstruct(data, preset, switches, out: Path, *, device=None, progress: bool = True,
                checkpoint_every: int = 100, resume: bool = False, stop_after: int | None = None,
                lpips=(None, "LPIPS off: no weights given"), extra: dict | None = None,
                view: dict | None = None, batch_size: int = 1, views=None) -> dict | None:
    """Train (or resume) and evaluate one run; writes metrics.json and scene.ply into ``out``.
    With ``view`` ({"host", "port", "every"}) the run is served to the browser as it trains.

    ``out`` is written in place; the commands (``clsplat train autosplat``, ``clsplat demo``) pass
    the staging folder of a :class:`~..common.runfolder.RunFolder`, which publishes it as a group.
    ``views``: the test sets scored (default :data:`.evaluate.DEFAULT_VIEWS`).
    Returns the metrics, or None when ``stop_after`` stopped the schedule early or on a rank > 0
    under ``torchrun`` (rank 0 evaluates and writes the outputs).
    """
    from ..common.report import metrics_report, write_metrics
    from ..common.train import distributed_info, read_log
    from .evaluate import DEFAULT_VIEWS, evaluate_run
    from .trainer import Trainer
    from .viewsets import check_views

    views = check_views(DEFAULT_VIEWS if views is None else views, data.seq)   # before minutes of training
    t_start = time.perf_counter()
    trainer = Trainer(data, preset, switches, out, device=device, progress=progress,
                      checkpoint_every=checkpoint_every, batch_size=batch_size)
    watcher = None
    if view is not None:
        from ..common.view import TrainView
        from .view import autosplat_scene
        watcher = TrainView(lambda: autosplat_scene(trainer.model, data.seq, data, f"AutoSplat {preset.name} "
                                                    f"(training, step {trainer.step})"), device=device, **view)
    try:
        trainer.fit(resume=resume, stop_at=stop_after, on_step=None if watcher is None else watcher.on_step)
    finally:
        if watcher is not None:
            watcher.close()
    if distributed_info()[0] != 0:
        return None
    if trainer.step < trainer.total:
        print(f"stopped after {trainer.step} of {trainer.total} iterations (the unfinished run is in {out}); "
              "continue with --resume")
        return None
    steps = read_log(out / "log.jsonl")
    it = [r["time_s"] for r in steps]
    train_s = sum(it)
    ev = evaluate_run(trainer, lpips=lpips[0], views=views)
    recorded = ("data", "scale", "frames")   # what eval autosplat and the viewer rebuild the run from
    ev["protocol"].update({k: extra[k] for k in recorded if extra and k in extra})
    sections = {k: v for k, v in ev.items() if k not in ("protocol", "all", "per_camera", "eval_seconds")}
    sections.update({
        **{k: v for k, v in (extra or {}).items() if k not in recorded},
        "switches": switches.to_dict(),
        "seconds_per_stage": {**({"load": extra["load_seconds"]} if extra and "load_seconds" in extra else {}),
                              **trainer.stage_seconds, "eval": ev["eval_seconds"]},
        "seconds_per_iteration": float(np.median(it)) if it else None,
        # kernels' device time (forward + backward) from OpenCL profiling events, over step wall time
        "renderer_device_share": float(sum(r["renderer_device_s"] for r in steps) / train_s) if it else None,
        # wall time inside the rasterisation calls and loss.backward (an upper bound), over step wall time
        "renderer_wall_share": float(sum(r["render_wall_s"] + r["backward_s"] for r in steps) / train_s) if it else None,
        "wall_seconds": time.perf_counter() - t_start,
    })
    metrics = metrics_report("autosplat", preset.name, trainer.total, ev["protocol"], ev["all"], ev["per_camera"],
                             **sections)
    show = data.test_frames[len(data.test_frames) // 2] if data.test_frames else data.train_frames[0]
    trainer.scene_gaussians(show).save_ply(out / "scene.ply")
    write_metrics(out, metrics)
    return metrics


def train(argv: list[str]) -> int:
    """Entry point of ``clsplat train autosplat``; returns the exit status."""
    from ..common.cli import no_weights
    from ..common.metrics import lpips_or_none
    from ..common.presets import apply_sets, get_preset
    from ..common.train import set_threads
    from .data import prepare_data
    from .model import Switches
    from .presets import with_total_steps

    a = _parser().parse_args(argv)
    no_weights(a, "AutoSplat", "a per-scene optimisation of Gaussians initialised from LiDAR, no network encoder")
    preset = apply_sets(get_preset("autosplat", a.preset), a.set)
    if a.steps is not None:   # the four stages keep their shares of the schedule
        preset = with_total_steps(preset, a.steps)
    batch = 1 if a.batch_size is None else a.batch_size
    world = int(os.environ.get("WORLD_SIZE", "1"))   # torchrun's; checked before the process group starts
    if batch < world:
        raise ValueError(f"--batch-size: {batch} frame(s) per iteration cannot be shared by {world} processes; "
                         f"give --batch-size {world} or more")
    set_threads(a.threads, a.device)
    preset = preset.replace(seed=a.seed) if a.seed != preset.seed else preset
    if a.holdout is not None:
        preset = preset.replace(holdout=a.holdout)
    scale = preset.scale if a.scale is None else a.scale
    switches = Switches(decompose=not a.no_decompose, flatness=not a.no_flatness, symmetry=not a.no_symmetry,
                        residual_sh=not a.no_residual_sh, pose_correction=not a.no_pose_correction,
                        densify=not a.no_densify)
    frames = parse_frames(a.frames)
    if a.view:  # before the data loads: a taken port is a one-line error now, not after minutes
        from clsplat.viewer.server import check_port_free
        check_port_free(a.view_host, a.view_port, ("--view-host", "--view-port"))
    t0 = time.perf_counter()
    seq = load_sequence(a.data, a.cameras, frames, scale, seed=a.seed, safe_pickle=not a.trust_pickle)
    if a.masks:
        from .init import load_mask_folder
        load_mask_folder(seq, a.masks, list(range(*(frames or (0, len(seq.frames))))))
    data = prepare_data(seq, a.cameras, preset.holdout, preset.dynamic_threshold, preset.road_classes)
    from .viewsets import check_views
    views = check_views(a.views, seq)
    load_s = time.perf_counter() - t0
    if a.stop_after is not None and a.stop_after < 1:
        raise ValueError(f"--stop-after: expected a positive number of iterations, got {a.stop_after}")
    lp, msg = lpips_or_none(a.lpips_vgg, a.lpips_lin)
    print(msg, flush=True)
    from ..common.runfolder import RunFolder
    from ..common.train import distributed_info, end_distributed
    distributed_info()   # under torchrun: the process group the run folder's ranks meet in
    with RunFolder(a.out, resume=a.resume) as rf:  # the lock; outputs staged, then published as a group
        metrics = reconstruct(data, preset, switches, rf.stage, device=a.device, progress=not a.no_progress,
                              checkpoint_every=a.checkpoint_every, resume=a.resume, stop_after=a.stop_after,
                              lpips=(lp, msg), extra={"data": a.data, "scale": scale, "frames": list(frames) if frames else None,
                                     "load_seconds": load_s},
                              view={"host": a.view_host, "port": a.view_port, "every": a.view_every}
                              if a.view else None, batch_size=batch, views=views)
        if metrics is None:
            end_distributed()
            return 0
        rf.publish()
    print(f"{_summary(metrics)}; {metrics['gaussians']['total']} Gaussians; outputs in {a.out}")
    end_distributed()
    return 0


def evaluate(argv: list[str]) -> int:
    """Entry point of ``clsplat eval autosplat``: re-evaluate a run from its checkpoint (on the
    run's data, or ``--data``) into ``--out``: metrics.json, contact and lateral-shift sheets."""
    from ..common.cli import add_eval_args, lpips_from_args
    from ..common.report import metrics_report, write_metrics
    from ..common.runfolder import STAGING
    from ..common.train import load_checkpoint, set_threads
    from .evaluate import evaluate_run, trainer_from_checkpoint

    p = ArgumentParser(prog="clsplat eval autosplat", description=evaluate.__doc__.split("\n")[0])
    add_eval_args(p, scenes=False)
    _add_views_arg(p)
    p.add_argument("--scale", type=float, default=None,
                   help="image scale the run trained at (default: the one its metrics.json records, else the preset's)")
    p.set_defaults(data=None)
    a = p.parse_args(argv)
    ck_path = Path(a.checkpoint)
    if ck_path.is_dir():   # a run folder: its checkpoint, finished or not
        ck_path = next((c for c in (ck_path / "checkpoint.pt", ck_path / STAGING / "checkpoint.pt") if c.is_file()),
                       ck_path / "checkpoint.pt")
    set_threads(a.threads, a.device)
    ck = load_checkpoint(ck_path, "autosplat")
    run = ck_path.parent.parent if ck_path.parent.name == STAGING else ck_path.parent
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tr = trainer_from_checkpoint(ck, ck_path, run, a.data, out_dir=out, device=a.device, arg="--checkpoint",
                                 scale=a.scale)
    lpips = lpips_from_args(a)
    ev = evaluate_run(tr, lpips=lpips, views=a.views)
    ev["protocol"]["checkpoint"] = str(ck_path)
    sections = {k: v for k, v in ev.items() if k not in ("protocol", "all", "per_camera", "eval_seconds")}
    m = metrics_report("autosplat", tr.preset.name, tr.step, ev["protocol"], ev["all"], ev["per_camera"],
                       switches=tr.switches.to_dict(), eval_seconds=ev["eval_seconds"], **sections)
    write_metrics(out, m)
    print(f"{_summary(m)} at step {tr.step}; wrote {out}/metrics.json")
    return 0
