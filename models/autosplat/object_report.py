"""Per-object reporting of an AutoSplat run (issue 36, deliverable 3): how well each moving track
is reconstructed on the held-out frames, pooled by class, and a contact sheet of the worst ones.

* :func:`object_class` maps a track's label (the data's: ``"car"`` on the generated street,
  PandaSet's ``"Pickup Truck"``, nuScenes' ``"pedestrian"``) to one of :data:`OBJECT_CLASSES`:
  ``car`` (cars, vans, pickups), ``pedestrian`` (people, with or without an object) and ``other``
  (trucks, buses, two-wheelers, anything else).
* :func:`track_masks` gives each track's pixels at a frame: the data's instance mask when it has
  one (the generator's, exact also under tracker noise), else the pixels whose ray hits the
  track's box (:func:`.background.foreground_mask`); boxes of different tracks may overlap, and a
  pixel in two boxes then counts for both.
* :func:`object_scores` is the arithmetic, on tensors alone: per track and per class, PSNR pooled
  over the pixels (``-10 log10`` of the mean squared error over every pixel and channel, images
  clipped to [0, 1], as ``psnr_objects``) and SSIM as the mean over those pixels of the per-pixel
  SSIM map (11x11 Gaussian window, reflect padding: :func:`clsplat.image_metrics.ssim_map` with
  ``padding="same"``, averaged over channels).
* :func:`object_report` is the ``objects`` section of ``metrics.json``
  (:func:`.evaluate.evaluate_run` calls it on the held-out frames' renders) and writes
  ``objects_worst.png``: for the :data:`WORST` tracks of lowest PSNR (among those that cover at least
  :data:`MIN_TRACK_PIXELS` pixels of some held-out view), the held-out view (frame, camera) where
  each covers the most pixels, cropped around it: render | truth | error.

The tracks scored are the moving ones (``moving_track_ids`` with the preset's
``dynamic_threshold``), those ``psnr_objects`` pools over, also for plain 3DGS (``--no-decompose``),
whose numbers stand beside the decomposed model's on the same pixels.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import torch

from clsplat.data.scene import DrivingSequence
from clsplat.image_metrics import ssim_map

from .background import box_hit_masks
from .init import moving_track_ids

__all__ = ["OBJECT_CLASSES", "WORST", "MIN_TRACK_PIXELS", "SHEET_NAME", "object_class", "track_masks",
           "object_scores", "object_report", "worst_tracks_sheet"]

OBJECT_CLASSES: tuple[str, ...] = ("car", "pedestrian", "other")
#: tracks shown on the worst-tracks sheet
WORST = 5
#: a track is ranked for the sheet only when one held-out view shows at least this many of its pixels
#: (about 7 x 7: on a busy street the tracks of a few pixels far away were all the sheet showed)
MIN_TRACK_PIXELS = 48
SHEET_NAME = "objects_worst.png"
#: the sheet's crop size (pixels, height x width) and the margin around a track's pixels (share of its extent)
CROP_HW = (96, 128)
CROP_MARGIN = 0.3

_CAR_WORDS = ("car", "van", "pickup", "suv", "sedan", "taxi")
_PEDESTRIAN_WORDS = ("pedestrian", "person", "human", "child", "adult")


def object_class(label: str) -> str:
    """The :data:`OBJECT_CLASSES` name of a track label (case, punctuation and a nuScenes-style
    ``vehicle.``/``human.`` prefix ignored): ``pedestrian`` when a word names a person, ``car``
    when one names a car, van or pickup (not a truck, bus or two-wheeler), else ``other``."""
    words = [w for w in str(label).lower().replace(".", " ").replace("-", " ").replace("/", " ").split() if w]
    if any(w.startswith(p) for w in words for p in _PEDESTRIAN_WORDS):
        return "pedestrian"
    if any(w in _CAR_WORDS or w in ("cars", "vans") for w in words):
        return "car"
    return "other"


def track_masks(seq: DrivingSequence, frame: int, cameras: Sequence[str], tracks: Sequence[int]) -> dict[int, np.ndarray]:
    """``{track: [C, H, W] bool}``: each track's pixels at ``frame`` in ``cameras`` (instance masks
    where the frame has them, else the pixels whose centre ray hits the track's box, as
    :func:`.background.foreground_mask` computes them, with each camera's rays made once for all
    boxes); tracks without a pixel are left out. The cameras must share one image size."""
    f = seq.frames[frame]
    want = {int(t) for t in tracks}
    boxes = [b for b in f.boxes if b.track_id in want]
    sizes = {(seq.camera(c).height, seq.camera(c).width) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"cameras: expected one image size, got {sorted(sizes)}")
    H, W = sizes.pop()
    out: dict[int, np.ndarray] = {}

    def put(t: int, k: int, m: np.ndarray) -> None:
        if m.any():
            out.setdefault(t, np.zeros((len(cameras), H, W), bool))[k] |= m

    for k, c in enumerate(cameras):
        if c in f.instances:
            inst = f.instances[c]
            for t in np.unique(inst[inst > 0]):
                if int(t) in want:
                    put(int(t), k, inst == t)
            continue
        if not boxes:
            continue
        cam = seq.camera(c)
        T = seq.cam_to_world(frame, c)
        for b, hit in box_hit_masks(cam, T, boxes, W, H):
            put(b.track_id, k, hit)
    return out


def _per_pixel(render: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(squared error summed over channels, SSIM averaged over channels)``, each ``[C, H, W]``
    float64, of ``[C, H, W, 3]`` images clipped to [0, 1]."""
    r = render.detach().to(torch.float32).clamp(0, 1)
    g = truth.detach().to(torch.float32).clamp(0, 1)
    sq = ((r.double() - g.double()) ** 2).sum(-1)
    s = ssim_map(r.permute(0, 3, 1, 2), g.permute(0, 3, 1, 2), padding="same").mean(1).double()
    return sq, s


def _block(acc: np.ndarray) -> dict:
    """``{"psnr", "ssim", "pixels"}`` of an accumulator ``[squared error sum, SSIM sum, pixels]``."""
    n = int(acc[2])
    if n == 0:
        return {"psnr": None, "ssim": None, "pixels": 0}
    mse = acc[0] / (3 * n)
    return {"psnr": float("inf") if mse == 0 else float(-10 * np.log10(mse)), "ssim": float(acc[1] / n), "pixels": n}


def object_scores(renders: Sequence[torch.Tensor], truths: Sequence[torch.Tensor],
                  masks: Sequence[Mapping[int, np.ndarray | torch.Tensor]], labels: Mapping[int, str]) -> dict:
    """Per-track and per-class scores over views.

    Args:
        renders, truths: per view (a frame), ``[C, H, W, 3]`` images.
        masks: per view, ``{track: [C, H, W] bool}`` (:func:`track_masks`).
        labels: track -> label (:func:`object_class` maps it to a class).
    Returns:
        ``{"per_class": {class: {"psnr", "ssim", "pixels", "tracks"}}, "per_track": {track: {"label",
        "class", "psnr", "ssim", "pixels", "best_view": (view index, camera index, pixels)}}}``;
        PSNR pooled over pixels (None without any), SSIM the mean of the per-pixel map over them.
    """
    if not (len(renders) == len(truths) == len(masks)):
        raise ValueError(f"renders, truths, masks: expected one entry per view each, got {len(renders)}, "
                         f"{len(truths)}, {len(masks)}")
    acc = {t: np.zeros(3) for m in masks for t in m}
    best: dict[int, tuple[int, int, int]] = {}
    for v, (r, g, m) in enumerate(zip(renders, truths, masks)):
        if not m:
            continue
        if r.shape != g.shape:
            raise ValueError(f"renders[{v}] {list(r.shape)} and truths[{v}] {list(g.shape)} differ in shape")
        sq, s = _per_pixel(r, g)
        for t, mk in m.items():
            mk = torch.as_tensor(np.asarray(mk), dtype=torch.bool)
            if mk.shape != sq.shape:
                raise ValueError(f"masks[{v}][{t}]: expected shape {list(sq.shape)}, got {list(mk.shape)}")
            acc[t] += [float(sq[mk].sum()), float(s[mk].sum()), int(mk.sum())]
            per_cam = mk.flatten(1).sum(1)
            c = int(per_cam.argmax())
            if int(per_cam[c]) > best.get(t, (0, 0, 0))[2]:
                best[t] = (v, c, int(per_cam[c]))
    per_track = {}
    cls_acc = {c: np.zeros(3) for c in OBJECT_CLASSES}
    cls_n = {c: 0 for c in OBJECT_CLASSES}
    for t in sorted(acc):
        cls = object_class(labels.get(t, ""))
        per_track[t] = {"label": labels.get(t, ""), "class": cls, **_block(acc[t]), "best_view": best.get(t)}
        cls_acc[cls] += acc[t]
        cls_n[cls] += int(acc[t][2] > 0)
    return {"per_class": {c: {**_block(cls_acc[c]), "tracks": cls_n[c]} for c in OBJECT_CLASSES},
            "per_track": per_track}


def _crop_rect(mask: np.ndarray, hw: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` around ``mask [H, W]``'s pixels, widened by :data:`CROP_MARGIN` and to
    the aspect of ``hw``, shifted (and if need be cut) into the image."""
    H, W = mask.shape
    ys, xs = np.nonzero(mask)
    cy, cx = (ys.min() + ys.max() + 1) / 2, (xs.min() + xs.max() + 1) / 2
    h = (ys.max() - ys.min() + 1) * (1 + 2 * CROP_MARGIN)
    w = (xs.max() - xs.min() + 1) * (1 + 2 * CROP_MARGIN)
    aspect = hw[1] / hw[0]
    h, w = max(h, w / aspect, 8.0), max(w, h * aspect, 8.0 * aspect)
    h, w = min(int(np.ceil(h)), H), min(int(np.ceil(w)), W)
    y0 = int(np.clip(round(cy - h / 2), 0, H - h))
    x0 = int(np.clip(round(cx - w / 2), 0, W - w))
    return y0, y0 + h, x0, x0 + w


def _resize_nearest(img: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """``img [h, w, 3]`` resampled to ``hw`` by nearest pixel centres."""
    h, w = img.shape[:2]
    yi = np.minimum(((np.arange(hw[0]) + 0.5) * h / hw[0]).astype(int), h - 1)
    xi = np.minimum(((np.arange(hw[1]) + 0.5) * w / hw[1]).astype(int), w - 1)
    return img[yi][:, xi]


def worst_tracks_sheet(renders: Sequence[torch.Tensor], truths: Sequence[torch.Tensor],
                       masks: Sequence[Mapping[int, np.ndarray]], scores: dict, frames: Sequence[int],
                       cameras: Sequence[str], path: Path, worst: int = WORST) -> list[int]:
    """Write the sheet of the ``worst`` tracks of lowest PSNR in ``scores`` (:func:`object_scores`
    of these views) to ``path``, one row per track (its best view, cropped); returns their ids in
    row order (none written when no track covers :data:`MIN_TRACK_PIXELS` pixels of a view)."""
    from clsplat.io.contact_sheet import make_contact_sheet

    ranked = sorted((v["psnr"], t) for t, v in scores["per_track"].items()
                    if v["best_view"] is not None and v["best_view"][2] >= MIN_TRACK_PIXELS and v["psnr"] is not None)
    rows = [t for _, t in ranked[:worst]]
    if not rows:
        return []
    rs, gs, names = [], [], []
    for t in rows:
        v, c, _ = scores["per_track"][t]["best_view"]
        y0, y1, x0, x1 = _crop_rect(np.asarray(masks[v][t][c]), CROP_HW)
        rs.append(_resize_nearest(renders[v][c, y0:y1, x0:x1].clamp(0, 1).numpy(), CROP_HW))
        gs.append(_resize_nearest(truths[v][c, y0:y1, x0:x1].clamp(0, 1).numpy(), CROP_HW))
        p = scores["per_track"][t]
        names.append(f"track {t} ({p['class']}, {p['psnr']:.1f} dB) frame {frames[v]} {cameras[c]}")
    make_contact_sheet(np.stack(rs), np.stack(gs), path, names=names,
                       title=f"worst {len(rows)} moving tracks, held-out frames: render | ground truth | error")
    return rows


@torch.no_grad()
def object_report(seq: DrivingSequence, cameras: Sequence[str], frames: Sequence[int],
                  renders: Sequence[torch.Tensor], truths: Sequence[torch.Tensor], dynamic_threshold: float,
                  sheet: Path | None = None) -> dict:
    """The ``objects`` section of ``metrics.json`` over ``frames`` (their ``renders`` and
    ``truths``, ``[C, H, W, 3]`` each, cameras ``cameras``): ``per_class`` (:data:`OBJECT_CLASSES`,
    each ``{"psnr", "ssim", "pixels", "tracks"}``), ``per_track`` (track id as a string ->
    ``{"label", "class", "psnr", "ssim", "pixels", "pixels_per_view"}``), ``worst`` (the sheet's
    track ids), ``sheet`` (its file name, None when none was written) and ``static_per_class``: the
    same per-class scores over the tracks that stand still (parked vehicles: objects of the same
    kind whose pixels the background reconstructs, the control that tells the cost of motion from
    that of the objects' own detail). With ``sheet`` the worst-tracks contact sheet is written there."""
    moving = sorted(moving_track_ids(seq, dynamic_threshold))
    labels: dict[int, str] = {}
    for f in seq.frames:
        for b in f.boxes:
            labels.setdefault(b.track_id, b.label)
    masks = [track_masks(seq, i, cameras, moving) for i in frames]
    scores = object_scores(renders, truths, masks, labels)
    still = sorted(set(labels) - set(moving))
    static = object_scores(renders, truths, [track_masks(seq, i, cameras, still) for i in frames], labels)
    views = max(len(frames) * len(cameras), 1)
    rows = worst_tracks_sheet(renders, truths, masks, scores, frames, cameras, sheet) if sheet is not None else []
    per_track = {str(t): {k: v for k, v in p.items() if k != "best_view"} | {"pixels_per_view": p["pixels"] / views}
                 for t, p in scores["per_track"].items()}
    return {"protocol": "moving tracks' pixels on the held-out frames (instance masks, else box pixels); PSNR "
                        "pooled over them, SSIM the mean of the per-pixel SSIM map (11x11, reflect padding) over them",
            "frames": list(frames), "per_class": scores["per_class"], "per_track": per_track, "worst": rows,
            "sheet": sheet.name if rows and sheet is not None else None,
            "static_per_class": static["per_class"]}
