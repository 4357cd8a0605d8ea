"""Evaluation of an AutoSplat run: held-out and training frames per camera and overall (PSNR,
SSIM, LPIPS when weights are given, PSNR over the moving objects' pixels), the novel-view sets of
:mod:`.viewsets` that are asked for (far side of moving vehicles, lane changes, changing
appearance, pose corrections under tracker noise), per-class and per-track object scores with the
worst tracks' sheet (:mod:`.object_report`), Gaussian counts per class; and a run rebuilt
from its checkpoint (``clsplat eval autosplat``, the viewer).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from clsplat.data.scene import DrivingSequence

from .data import load_sequence, prepare_data
from .init import BG_CLASSES
from .model import Switches
from .object_report import SHEET_NAME, object_report
from ..common.presets import preset_from_saved
from .trainer import Trainer, checkpoint_extra
from .viewsets import _pooled_psnr, _sq_err, appearance, check_views, far_side, lane_change, pose_corrections

__all__ = ["evaluate_run", "trainer_from_checkpoint", "DEFAULT_VIEWS"]

#: the view sets a training run scores by default (``--views``): the far side and appearance sets
#: cost generator renders of every frame, so they are asked for
DEFAULT_VIEWS: tuple[str, ...] = ("recorded", "lane-change")


@torch.no_grad()
def evaluate_run(trainer: Trainer, lpips=None, views=DEFAULT_VIEWS) -> dict:
    """The ``metrics.json`` sections of this run (:mod:`clsplat.models.common.report`):
    ``all``/``per_camera`` over the held-out frames (PSNR, SSIM[, LPIPS], PSNR over the moving
    objects' pixels ``psnr_objects``; always, as the contract asks), and per view set in ``views``
    (:data:`.viewsets.VIEW_SETS`): ``recorded``: ``train`` (the same on the training frames) and
    ``pose_correction`` (with tracker noise in the data); ``far-side``: ``far_side``;
    ``lane-change``: ``lane_change`` (keys ``1m``, ``2m``, ``3m``); ``appearance``:
    ``appearance``; always ``objects`` (:mod:`.object_report`: per-class and per-track object PSNR /
    SSIM on the scored frames, the worst tracks' sheet ``objects_worst.png``); then Gaussian counts
    per class."""
    from clsplat.io.contact_sheet import make_contact_sheet

    from ..common.report import camera_blocks, image_scores

    d = trainer.data
    views = check_views(views, d.seq)
    out: dict = {"protocol": {"cameras": d.cameras, "train_frames": d.train_frames, "test_frames": d.test_frames,
                              "split": f"every {trainer.preset.holdout}-th frame held out" if d.test_frames
                                       else "train (no held-out frames: 'all' is over the training frames)",
                              "psnr_objects": "PSNR pooled over the moving tracks' pixels (foreground masks)",
                              "lpips": "on" if lpips is not None else "off (no weights given)",
                              "views": list(views)}}

    def score(frames) -> tuple[dict, dict, list]:
        rs, ts, obj = [], [], torch.zeros(2, dtype=torch.float64)
        for i in frames:
            rs.append(trainer.render_frame(i))
            ts.append(d.images[i])
            obj += _sq_err(rs[-1], ts[-1], d.foreground[i])
        all_, per_camera = camera_blocks(image_scores(torch.cat(rs).permute(0, 3, 1, 2),
                                                      torch.cat(ts).permute(0, 3, 1, 2), lpips),
                                         [c for _ in frames for c in d.cameras])
        all_["psnr_objects"] = _pooled_psnr(obj)
        all_["images"] = len(frames) * len(d.cameras)
        return all_, per_camera, rs

    t0 = time.perf_counter()
    show = d.test_frames[len(d.test_frames) // 2] if d.test_frames else d.train_frames[0]
    if "recorded" in views:
        train_all, train_cams, _ = score(d.train_frames)
        out["train"] = {**train_all, "per_camera": train_cams}
    scored = d.test_frames or d.train_frames
    out["all"], out["per_camera"], renders = score(scored)
    # issue 36: per-class object PSNR / SSIM and the worst tracks' sheet, on the same renders
    out["objects"] = object_report(d.seq, d.cameras, scored, renders, [d.images[i] for i in scored],
                                   trainer.preset.dynamic_threshold, trainer.out / SHEET_NAME)
    del renders
    if "recorded" in views:
        r = trainer.render_frame(show)
        make_contact_sheet(r.numpy(), d.images[show].numpy(), trainer.out / "contact_sheet.png", names=d.cameras,
                           title=f"AutoSplat, held-out frame {show}: render | ground truth | error")
        pc = pose_corrections(trainer)
        if pc is not None:
            out["pose_correction"] = pc
    if "far-side" in views:
        out["far_side"] = far_side(trainer, trainer.out / "far_side.png")
    if "lane-change" in views:
        out["lane_change"] = lane_change(trainer, show, trainer.out)
    if "appearance" in views:
        out["appearance"] = appearance(trainer)
    out["eval_seconds"] = time.perf_counter() - t0
    bg = trainer.model.background
    out["gaussians"] = {**{name: int((bg.labels == c).sum()) for c, name in enumerate(BG_CLASSES)},
                        "objects": int(sum(len(o) for o in trainer.model.objects)),
                        "objects_rendered_with_mirrors": int(sum(len(o) for o in trainer.model.objects)
                                                             * (2 if trainer.switches.symmetry else 1)),
                        "tracks": len(trainer.tracks),
                        "dynamic_tracks": sum(t.dynamic for t in trainer.tracks)}
    out["gaussians"]["total"] = len(bg) + out["gaussians"]["objects"]
    return out


def trainer_from_checkpoint(ck: dict, ck_path: Path, run: Path, data: str | None, out_dir: Path | None = None,
                            device=None, arg: str = "PATH", safe_pickle: bool = True,
                            scale: float | None = None) -> Trainer:
    """The :class:`Trainer` of a run rebuilt from its checkpoint ``ck`` (read from ``ck_path`` in
    the run folder ``run``) on the run's data: ``--data``, ``--scale`` and ``--frames`` recorded in
    the run's ``metrics.json`` (else the built-in street at the preset's scale, cut to the run's
    training frames), or ``data`` when given (PandaSet's pickles allow-listed unless
    ``safe_pickle=False``); ``scale`` (``--scale``) overrides the recorded or preset image scale
    (a checkpoint taken during training has no ``metrics.json`` beside it to record one).
    Its sheets go to ``out_dir`` (default the run folder). ValueError naming ``arg`` when the data
    does not give the run's training frames or tracked objects."""
    preset = preset_from_saved("autosplat", ck["preset"])
    ex = checkpoint_extra(ck)
    given_scale = scale
    spec, scale, frames = "synthetic", preset.scale, None
    metrics = run / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        recorded = m.get("protocol", m)   # schema 1 keeps them in "protocol"; earlier runs at the top
        spec, scale, frames = recorded.get("data", spec), recorded.get("scale", scale), recorded.get("frames")
    if given_scale is not None:
        scale = given_scale
    if data is not None and data != spec:
        spec, frames = data, None
    want = list(ex.get("train_frames") or [0])
    if frames is not None:      # the run's recorded frame range: the same sequence
        d = prepare_data(load_sequence(spec, ex.get("cameras"), tuple(frames), scale, seed=preset.seed,
                                       safe_pickle=safe_pickle),
                         ex.get("cameras"), preset.holdout, preset.dynamic_threshold,
                         preset.road_classes)
    else:   # not recorded (an unfinished run, or --data named): the first cut whose split gives the frames
        d = None
        seq = load_sequence(spec, ex.get("cameras"), None, scale, seed=preset.seed, safe_pickle=safe_pickle)
        for n in range(max(want) + 1, len(seq.frames) + 1):
            d = prepare_data(DrivingSequence(seq.cameras, seq.frames[:n], seq.name, seq.metadata),
                             ex.get("cameras"), preset.holdout, preset.dynamic_threshold, preset.road_classes)
            if d.train_frames == want:
                break
    if d is None or d.train_frames != want:
        raise ValueError(f"{arg} {str(ck_path)!r}: its training frames {want} are not those of "
                         f"--data {spec!r}; name the run's data with --data")
    tr = Trainer(d, preset, Switches(**ex["switches"]), out_dir or run, device=device, progress=False)
    if [t.track_id for t in tr.tracks] != ex.get("tracks"):
        raise ValueError(f"{arg} {str(ck_path)!r}: its tracked objects differ from those of --data {spec!r}")
    tr.model.resize_(ex["sizes"])
    tr.model.load_state_dict(ck["model"])
    tr.step = int(ck.get("step", tr.total))
    tr.model.eval()
    return tr
