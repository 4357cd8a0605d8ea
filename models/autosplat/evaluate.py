"""Evaluation of an AutoSplat run: held-out and training frames per camera and overall (PSNR,
SSIM, LPIPS when weights are given, PSNR over the tracked objects' pixels), renders of the rig
shifted 1-3 m sideways scored against the generator's exact images where it is at hand, Gaussian
counts per class; and a run rebuilt from its checkpoint (``clsplat eval autosplat``, the viewer).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from clsplat.data.scene import DrivingSequence

from ..common.metrics import psnr as psnr_metric, ssim as ssim_metric
from .data import ROAD_SEMANTIC, load_sequence, prepare_data
from .init import BG_CLASSES
from .model import Switches
from ..common.presets import preset_from_saved
from .trainer import Trainer, checkpoint_extra

__all__ = ["evaluate_run", "lateral_shift_poses", "trainer_from_checkpoint", "LATERAL_SHIFTS_M"]

LATERAL_SHIFTS_M: tuple[float, ...] = (1.0, 2.0, 3.0)


def lateral_shift_poses(seq: DrivingSequence, frame: int, cameras: list[str], shift: float) -> np.ndarray:
    """``[C, 4, 4]`` cam-to-world of the rig at ``frame`` moved ``shift`` metres along ego +y (left)."""
    f = seq.frames[frame]
    S = np.eye(4)
    S[1, 3] = shift
    return np.stack([f.ego_to_world @ S @ np.linalg.inv(f.ego_to_world) @ seq.cam_to_world(frame, c) for c in cameras])


def _squared_error(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``[2]`` float64 (sum of squared errors, number of values) of ``render``/``target``
    ``[C, 3, H, W]`` (clipped to [0, 1]) over ``mask`` ``[C, H, W]``."""
    m = mask[:, None].to(torch.float64)
    err = (render.clamp(0, 1) - target.clamp(0, 1)).to(torch.float64) ** 2
    return torch.stack([(err * m).sum(), m.sum() * render.shape[1]])


def _pooled_psnr(acc: torch.Tensor) -> float | None:
    """PSNR of pooled ``(sum of squared errors, count)``; None when nothing was counted."""
    return None if float(acc[1]) == 0 else float(-10 * torch.log10(acc[0] / acc[1]))


@torch.no_grad()
def evaluate_run(trainer: Trainer, lpips=None) -> dict:
    """The ``metrics.json`` sections of this run (:mod:`clsplat.models.common.report`):
    ``all``/``per_camera`` over the held-out frames (PSNR, SSIM[, LPIPS], PSNR over the tracked
    objects' pixels ``psnr_objects``), ``train`` the same over the training frames,
    ``lateral_shift`` errors and sheets, Gaussian counts per class."""
    from clsplat.io.contact_sheet import make_contact_sheet

    from ..common.report import camera_blocks, image_scores

    d = trainer.data
    out: dict = {"protocol": {"cameras": d.cameras, "train_frames": d.train_frames, "test_frames": d.test_frames,
                              "split": f"every {trainer.preset.holdout}-th frame held out" if d.test_frames
                                       else "train (no held-out frames: 'all' is over the training frames)",
                              "psnr_objects": "PSNR pooled over the tracked objects' pixels (foreground masks)",
                              "lpips": "on" if lpips is not None else "off (no weights given)"}}

    def score(frames) -> tuple[dict, dict]:
        rs, ts, obj = [], [], torch.zeros(2, dtype=torch.float64)
        for i in frames:
            rs.append(trainer.render_frame(i).permute(0, 3, 1, 2))
            ts.append(d.images[i].permute(0, 3, 1, 2))
            obj += _squared_error(rs[-1], ts[-1], d.foreground[i])
        all_, per_camera = camera_blocks(image_scores(torch.cat(rs), torch.cat(ts), lpips),
                                         [c for _ in frames for c in d.cameras])
        all_["psnr_objects"] = _pooled_psnr(obj)
        all_["images"] = len(frames) * len(d.cameras)
        return all_, per_camera

    t0 = time.perf_counter()
    train_all, train_cams = score(d.train_frames)
    out["train"] = {**train_all, "per_camera": train_cams}
    out["all"], out["per_camera"] = score(d.test_frames) if d.test_frames else (train_all, train_cams)
    show = d.test_frames[len(d.test_frames) // 2] if d.test_frames else d.train_frames[0]
    r = trainer.render_frame(show)
    make_contact_sheet(r.numpy(), d.images[show].numpy(), trainer.out / "contact_sheet.png", names=d.cameras,
                       title=f"AutoSplat, held-out frame {show}: render | ground truth | error")
    out["lateral_shift"] = _lateral(trainer, show, make_contact_sheet)
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

def _lateral(trainer: Trainer, show: int, make_sheet) -> dict:
    """Renders of the rig shifted 1/2/3 m left. With the generator at hand, errors against its
    exact renders, averaged over the held-out frames (PSNR also over object and road pixels
    only, pooled); sheets of frame ``show``."""
    d = trainer.data
    scene = d.seq.metadata.get("scene")
    frames = d.test_frames or [show]
    res = {}
    for shift in LATERAL_SHIFTS_M:
        ps, ss = [], []
        obj, road = torch.zeros(2, dtype=torch.float64), torch.zeros(2, dtype=torch.float64)
        for frame in (frames if scene is not None else [show]):
            c2w = lateral_shift_poses(d.seq, frame, d.cameras, shift)
            r = trainer.render_frame(frame, torch.from_numpy(np.linalg.inv(c2w).astype(np.float32)))
            if scene is None:
                gt = d.images[frame].numpy()
                title = f"rig shifted {shift:g} m left, frame {frame}: render | unshifted image (no ground truth) | diff"
            else:
                views = [scene.render(d.seq.camera(c).K, c2w[j], d.width, d.height, d.seq.frames[frame].timestamp)
                         for j, c in enumerate(d.cameras)]
                gt = np.stack([v.rgb for v in views])
                g, rr = torch.from_numpy(gt).permute(0, 3, 1, 2), r.permute(0, 3, 1, 2)
                ps.append(psnr_metric(rr, g))
                ss.append(ssim_metric(rr, g))
                obj += _squared_error(rr, g, torch.from_numpy(np.stack([v.instance > 0 for v in views])))
                road += _squared_error(rr, g, torch.from_numpy(np.stack([v.semantic == ROAD_SEMANTIC
                                                                         for v in views])))
                title = f"rig shifted {shift:g} m left, frame {frame}: render | generator ground truth | error"
            if frame == show:
                make_sheet(r.numpy(), gt, trainer.out / f"lateral_shift_{shift:g}m.png", names=d.cameras, title=title)
        res[f"{shift:g}m"] = None if scene is None else {
            "psnr": float(torch.cat(ps).mean()), "ssim": float(torch.cat(ss).mean()),
            "psnr_objects": _pooled_psnr(obj), "psnr_road": _pooled_psnr(road), "frames": frames}
    return res


def trainer_from_checkpoint(ck: dict, ck_path: Path, run: Path, data: str | None, out_dir: Path | None = None,
                            device=None, arg: str = "PATH", safe_pickle: bool = True) -> Trainer:
    """The :class:`Trainer` of a run rebuilt from its checkpoint ``ck`` (read from ``ck_path`` in
    the run folder ``run``) on the run's data: ``--data``, ``--scale`` and ``--frames`` recorded in
    the run's ``metrics.json`` (else the built-in street at the preset's scale, cut to the run's
    training frames), or ``data`` when given (PandaSet's pickles allow-listed unless
    ``safe_pickle=False``).
    Its sheets go to ``out_dir`` (default the run folder). ValueError naming ``arg`` when the data
    does not give the run's training frames or tracked objects."""
    preset = preset_from_saved("autosplat", ck["preset"])
    ex = checkpoint_extra(ck)
    spec, scale, frames = "synthetic", preset.scale, None
    metrics = run / "metrics.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        recorded = m.get("protocol", m)   # schema 1 keeps them in "protocol"; earlier runs at the top
        spec, scale, frames = recorded.get("data", spec), recorded.get("scale", scale), recorded.get("frames")
    if data is not None and data != spec:
        spec, frames = data, None
    want = list(ex.get("train_frames") or [0])
    if frames is not None:      # the run's recorded frame range: the same sequence
        d = prepare_data(load_sequence(spec, ex.get("cameras"), tuple(frames), scale, seed=preset.seed,
                                       safe_pickle=safe_pickle),
                         ex.get("cameras"), preset.holdout, preset.dynamic_threshold)
    else:   # not recorded (an unfinished run, or --data named): the first cut whose split gives the frames
        d = None
        seq = load_sequence(spec, ex.get("cameras"), None, scale, seed=preset.seed, safe_pickle=safe_pickle)
        for n in range(max(want) + 1, len(seq.frames) + 1):
            d = prepare_data(DrivingSequence(seq.cameras, seq.frames[:n], seq.name, seq.metadata),
                             ex.get("cameras"), preset.holdout, preset.dynamic_threshold)
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
