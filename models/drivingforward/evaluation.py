"""Evaluation of a DrivingForward model on held-out windows: novel views, depth, two baselines.

For each held-out window (frames t-1, t, t+1), the model reconstructs Gaussians from the input
frames (default: SF t, MF t-1 and t+1) with the *true* ego motion (the pose network is a training
device), renders the target frame (SF t+1, MF t) with the true camera poses, and compares with
the real images: PSNR, SSIM (and LPIPS with user weights). Depth at t is compared with the data's
depth (synthetic ground truth, or the LiDAR sweep at t projected into each camera on real data,
:func:`~.data.lidar_depth`) in metric units without median
scaling: AbsRel, SqRel, RMSE, delta<1.25, and the median scale ratio. Pixels are pooled per camera
over all windows and over everything for ``all``.

Pose (beside the depth in ``all``): the pose network's camera-0 motion from frame t to t+1 against
the data's (``E_0^-1 M_{t->t+1} E_0``), as the mean over windows of the translation error in metres
and in % of the true translation, and of the rotation error in degrees (``pose_t_err_m``,
``pose_t_err_pct``, ``pose_r_err_deg``; also the mean predicted and true translation norms). A
model trained with ``pose_source`` "dataset" has no trained pose network, and reports none; one
trained with "geometric" reports the motion its fit measures from the held-out window's images
(:mod:`~.geometric_pose`) in the same keys.

The oracle-depth baseline of ``make demo`` (:func:`clsplat.pixel_recon.lift_pixels`: every non-sky
pixel of the input frame lifted at its true depth, one pixel's footprint, opacity 0.95, rendered
with the mean sky colour behind) is run on the same windows at the same resolution when the
data has depth, so that ``oracle_psnr`` can be read beside ``psnr``.

The image-blind layout baseline (:func:`layout_depth`): per camera and pixel, the median ground-truth
depth of the first ``layout`` training windows, the same map for every held-out window. It scores
what a depth that never looks at the image scores (``layout_abs_rel``, ``layout_delta1``,
``layout_scale_ratio`` beside the model's): on a street whose layout barely changes, such as the
synthetic streets, it is a strong baseline (issue 17: AbsRel 0.11, delta<1.25 0.87 at ``small``'s
size), and a model that does not beat it has not learned depth from its images.

The constant-motion control (:func:`training_controls`): the mean over the same training windows
of camera 0's true motion from t to t+1 (translation and axis-angle rotation averaged), predicted
for every held-out window whatever its images show: ``constant_motion_t_err_m`` and
``constant_motion_t_err_pct`` beside the pose network's ``pose_t_err_m`` and ``pose_t_err_pct``.
A pose network that has not learned motion from its images scores about what this scores.

Speed bins: every held-out window is put in one bin by the ego's true speed from t to t+1
(:data:`clsplat.data.synthetic.SPEED_BINS`: ``standing`` below 0.5 m/s, ``0.5-5``, ``5-10``, ``10-15`` m/s), and
``speed_bins`` in ``metrics.json`` holds, per bin, the same keys as ``all`` (pooled over that bin's
windows only) and ``windows``, the count (a bin without windows holds only ``windows: 0``). Pose
percentages are undefined where the true motion is below 1 mm, so the ``standing`` bin is read in
metres. Medians over windows (``pose_t_err_pct_median``, ``constant_motion_t_err_pct_median``, and
the ``_m`` forms) stand beside the means.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from clsplat.data.synthetic import SPEED_BINS, speed_bin

from ..common.metrics import depth_metrics, pose_errors, psnr
from ..common.report import camera_blocks, image_scores, mean_scores, metrics_report, write_metrics
from .data import camera0_motion, ego_speed, gt_ego_motion, load_triplet
from .geometric_pose import geometric_size as _geometric_size
from .geometric_pose import load_window_motions

FAMILY = "drivingforward"

__all__ = ["evaluate_model", "layout_depth", "training_controls", "validation_point", "OFFSETS"]

#: frame offset -> index in a triplet
OFFSETS = {-1: 0, 0: 1, 1: 2}
_POSE_KEYS = ("t_err_m", "t_err_pct", "r_err_deg", "t_pred_m", "t_true_m")


def _oracle_render(sample: dict, inputs: Sequence[int], target: int, device=None) -> Tensor:
    """The oracle-depth baseline: input frames lifted at true depth, rendered at the target."""
    import clsplat
    from clsplat.data.scene import unproject_depth

    means, colours, scales, sky = [], [], [], []
    for f in inputs:
        for c in range(sample["Ks"].shape[0]):
            d = sample["depths"][f, c].numpy()
            img = sample["images"][f, c].permute(1, 2, 0).numpy()
            K = sample["Ks"][c].double().numpy()
            c2w = torch.linalg.inv(sample["viewmats"][f, c].double()).numpy()
            ok = np.isfinite(d) & (d > 0)
            pts = unproject_depth(np.where(ok, d, 1.0), K, c2w)
            means.append(pts[ok])
            colours.append(img[ok])
            scales.append(0.5 * d[ok] / (0.5 * (K[0, 0] + K[1, 1])))
            sky.append(img[~ok])
    sky_all = np.concatenate(sky)
    bg = torch.from_numpy(sky_all.mean(0) if len(sky_all) else np.full(3, 0.8)).float()
    m = torch.from_numpy(np.concatenate(means)).float()
    n = m.shape[0]
    quats = torch.zeros(n, 4)
    quats[:, 0] = 1
    sc = torch.from_numpy(np.concatenate(scales)).float()[:, None].expand(n, 3).contiguous()
    V = sample["Ks"].shape[0]
    out, _, _ = clsplat.rasterization(m, quats, sc, torch.full((n,), 0.95), torch.from_numpy(np.concatenate(colours)),
                                      sample["viewmats"][target], sample["Ks"], sample["images"].shape[-1],
                                      sample["images"].shape[-2], backgrounds=bg.expand(V, 3).contiguous(),
                                      device=device)
    return out.permute(0, 3, 1, 2)


def _depth_colour(depth: Tensor, max_depth: float = 80.0) -> np.ndarray:
    """``[V, H, W]`` depth -> ``[V, H, W, 3]`` colour (inverse depth through magma; sky black)."""
    from matplotlib import colormaps

    d = depth.detach().double().numpy()
    inv = np.where(np.isfinite(d), 1.0 / np.clip(d, 1.0, max_depth), 0.0)
    return colormaps["magma"](np.clip(inv / inv.max() if inv.max() > 0 else inv, 0, 1))[..., :3].astype(np.float32)


def _check_layout_windows(windows) -> None:
    if isinstance(windows, bool) or not isinstance(windows, int) or windows < 0:
        raise ValueError(f"--layout-windows: expected an int >= 0, got {windows!r}")


@torch.no_grad()
def training_controls(source, preset, windows: int, cameras: Sequence[str] | None = None,
                      layout: bool = True) -> tuple[Tensor | None, Tensor | None]:
    """The two image-blind controls, from training windows ``0 .. windows-1``.

    * the layout depth: per camera and pixel, the median true depth at frame t: of the depth maps
      (sky counts as ``preset.max_depth``, since a layout that puts the sky far is what an
      image-blind guess would do), or, where there are none, of the windows whose projected LiDAR
      has a return at that pixel (a pixel without a return is unknown, not far;
      ``preset.max_depth`` where no window has one);
    * the constant motion: camera 0's true motion from t to t+1, translation and axis-angle rotation
      averaged over the windows (what a pose network that ignores its images would best predict).

    Returns ``(layout [V, H, W] or None, motion [4, 4] float64 or None)``: None when the data has no
    depth (layout) or ``windows`` is 0.
    """
    from ..common.geometry import matrix_to_axis_angle, se3_exp
    from .data import camera0_motion

    _check_layout_windows(windows)
    maps, moves, no_depth = [], [], not layout
    for i in range(windows):
        s = load_triplet(source, i, preset, split="train", cameras=cameras, depth_only=True)
        moves.append(camera0_motion(s))
        if no_depth:
            continue
        if "depths" in s:
            d = s["depths"][1].double()
            maps.append(torch.nan_to_num(d, nan=preset.max_depth).clamp(max=preset.max_depth))
        elif "lidar_depth" in s:
            d = s["lidar_depth"].double()
            maps.append(torch.where(torch.isfinite(d), d.clamp(max=preset.max_depth), torch.nan))
        else:
            no_depth = True
    if not moves:
        return None, None
    T = torch.stack(moves)
    aa = torch.stack([matrix_to_axis_angle(R) for R in T[:, :3, :3]]).mean(0)
    motion = se3_exp(aa, T[:, :3, 3].mean(0)).double()
    lay = None if no_depth or not maps else \
        torch.stack(maps).nanmedian(0).values.nan_to_num(nan=preset.max_depth).float()
    return lay, motion


def layout_depth(source, preset, windows: int, cameras: Sequence[str] | None = None) -> Tensor | None:
    """The image-blind layout baseline alone (:func:`training_controls`): ``[V, H, W]`` or None."""
    return training_controls(source, preset, windows, cameras)[0]


def _pose_summary(records: list[dict], prefix: str) -> dict:
    """Means (and medians of the translation errors) over windows of :func:`pose_errors` records."""
    out = {}
    if not records:
        return out
    for k in _POSE_KEYS:
        vals = [q[k] for q in records if q[k] is not None]
        # None where no window defines it (a percentage of a standing ego's zero motion)
        out[f"{prefix}{k}"] = float(np.mean(vals)) if vals else None
        if k in ("t_err_m", "t_err_pct"):
            out[f"{prefix}{k}_median"] = float(np.median(vals)) if vals else None
    return out


@torch.no_grad()
def evaluate_model(model, source, num_scenes: int = 4, cameras: Sequence[str] | None = None,
                   frames: Sequence[int] | None = None, target: int | None = None, lpips=None,
                   out_dir: str | Path | None = None, oracle: bool = True, progress: bool = False,
                   step: int = 0, supersample: int | None = None, layout: int | None = None, split: str = "test") -> dict:
    """Novel-view, depth and pose metrics on held-out windows ``0 .. num_scenes-1`` of ``split``.

    Args:
        model: a :class:`~.model.DrivingForward` (eval mode is set here).
        source: a ``DataSource``; cameras: names (default all).
        frames: input frame offsets in {-1, 0, 1} (default SF: (0,), MF: (-1, 1)).
        target: target offset (default SF: +1, MF: 0).
        lpips: optional LPIPS module; out_dir: where to write ``metrics.json`` and the contact sheets.
        oracle: also run the oracle-depth baseline (needs depth in the data).
        step: the training steps behind the model (recorded).
        layout: training windows behind the image-blind controls (:func:`training_controls`: the
            layout depth and the constant motion; default: the preset's ``layout_windows``); 0: not run.
        split: "val" (where preset fields are chosen) or "test" (reported once per recipe).
        supersample: synthetic streets only: rays per pixel side of the held-out images (default:
            the model's preset, i.e. the images it trained on); depth ground truth is the centre
            ray's either way, so models trained on different images can be scored on the same ones.
    Returns:
        the ``metrics.json`` dict (:mod:`clsplat.models.common.report`): ``all`` and
        ``per_camera`` hold PSNR/SSIM[/LPIPS], depth errors and ``oracle_psnr`` (when run),
        ``all`` also the pose errors, the layout baseline's ``layout_abs_rel``, ``layout_delta1``,
        ``layout_scale_ratio`` and the constant-motion control's ``constant_motion_*`` (when run);
        ``speed_bins`` the same per ego-speed bin; ``protocol`` the settings used.
    """
    from clsplat.io.contact_sheet import make_contact_sheet

    _check_layout_windows(model.preset.layout_windows if layout is None else layout)   # before any window is loaded
    p = model.preset
    layout = p.layout_windows if layout is None else layout
    if split not in ("val", "test"):
        raise ValueError(f"--eval-split: expected 'val' or 'test', got {split!r}")
    model.eval()
    if supersample is not None:
        if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
            raise ValueError(f"--supersample: expected an int >= 1, got {supersample!r}")
        if not source.synthetic_streets:
            raise ValueError(f"--supersample: only synthetic streets are rendered here, not {source.name!r}")
    data_preset = p if supersample is None else dataclasses.replace(p, supersample=supersample)
    frames = tuple(frames) if frames is not None else ((0,) if p.mode == "SF" else (-1, 1))
    target = target if target is not None else (1 if p.mode == "SF" else 0)
    bad = [f for f in (*frames, target) if f not in OFFSETS]
    if bad or not frames:
        raise ValueError(f"--offsets/--target: offsets must be in {{-1, 0, 1}}, got {list(frames)} and {target}")
    fi = [OFFSETS[f] for f in frames]
    ti = OFFSETS[target]
    renders, gts, preds, gdepths, oracles, names = [], [], [], [], [], None
    poses: list[dict] = []
    truths: list[Tensor] = []                                  # camera 0's true motion t -> t+1 per window
    speeds: list[float] = []
    pose_source = getattr(p, "pose_source", "network")
    first = None
    iterator = range(num_scenes)
    if progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc="eval", unit="scene")
    for i in iterator:
        s = load_triplet(source, i, data_preset, split=split, cameras=cameras)
        names = s["names"]
        Ks, E = s["Ks"], s["cam_to_ego"]
        M = gt_ego_motion(s)                                   # ego_t -> ego_f
        to_ref = torch.stack([torch.linalg.inv(M[f].double()).float() for f in fi])
        V, HW = E.shape[0], p.height * p.width
        g = model.reconstruct(s["images"][fi], Ks, E, frame_to_ref=to_ref, ref=0 if 1 not in fi else fi.index(1))
        # cameras at the target instant: world-to-camera composed with ego_t -> world
        viewmats = s["viewmats"][ti] @ s["ego_to_world"][1]
        if p.mode == "MF":
            rows = []
            for c in range(V):
                idx = torch.cat([torch.arange((k * V + c) * HW, (k * V + c + 1) * HW) for k in range(len(fi))])
                rows.append(model.render(g.index(idx), viewmats[c:c + 1], Ks[c:c + 1])[0])
            r = torch.cat(rows)
        else:
            r = model.render(g, viewmats, Ks)[0]
        T_true = camera0_motion(s)
        truths.append(T_true)
        speeds.append(ego_speed(s))
        if pose_source == "network":
            poses.append(pose_errors(model.pose_net(s["images"][1], s["images"][2], Ks, E), T_true))
        elif pose_source == "geometric":
            M_next = load_window_motions(source, i, data_preset, split, cameras, s)[1].double()
            E0 = E[0].double()
            poses.append(pose_errors(torch.linalg.inv(E0) @ M_next @ E0, T_true.double()))
        renders.append(r.clamp(0, 1))
        gts.append(s["images"][ti])
        gt_depth = s["depths"][1] if "depths" in s else s.get("lidar_depth")
        if gt_depth is not None:
            preds.append(model.depth_net(s["images"][1], Ks, E)["depth"][:, 0])
            gdepths.append(gt_depth)
        if "depths" in s and oracle:
            oracles.append(_oracle_render(s, fi, ti, model.render_device).clamp(0, 1))
        if first is None:
            first = (r, s, (preds[-1], gdepths[-1]) if preds else None)
    R, G = torch.stack(renders), torch.stack(gts)              # [S, V, 3, H, W]
    S, V = R.shape[:2]
    cams = [n for _ in range(S) for n in names]                # image i of R.flatten(0, 1) is cams[i]
    scores = image_scores(R.flatten(0, 1), G.flatten(0, 1), lpips)
    if oracles:
        scores["oracle_psnr"] = psnr(torch.stack(oracles).flatten(0, 1), G.flatten(0, 1)).double()
    _, per_camera = camera_blocks(scores, cams)
    lay, motion = training_controls(source, data_preset, layout, cameras, layout=bool(preds)) if layout else (None, None)
    constant = [pose_errors(motion.to(T.dtype), T) for T in truths] if motion is not None else []
    P = torch.stack(preds) if preds else None                  # [S, V, H, W]
    D = torch.stack(gdepths) if preds else None

    def block(windows: list[int]) -> dict:
        """Every ``all`` key over the held-out windows ``windows`` (images, pixels pooled)."""
        w = torch.tensor(windows, dtype=torch.long)
        images = (w[:, None] * V + torch.arange(V)[None]).reshape(-1)
        out = mean_scores(scores, images)
        if P is not None:
            out.update(depth_metrics(P[w], D[w], min_depth=1e-3, max_depth=p.max_depth))
            if lay is not None:
                m = depth_metrics(lay.expand_as(D[w]), D[w], min_depth=1e-3, max_depth=p.max_depth)
                out.update({f"layout_{k}": m[k] for k in ("abs_rel", "delta1", "scale_ratio")})
        if poses:
            out.update(_pose_summary([poses[j] for j in windows], "pose_"))
        if constant:
            out.update(_pose_summary([constant[j] for j in windows], "constant_motion_"))
        out["speed_mps"] = float(np.mean([speeds[j] for j in windows]))
        out["windows"] = len(windows)
        return out

    all_ = block(list(range(S)))
    if P is not None:
        for c, name in enumerate(names):
            per_camera[name].update(depth_metrics(P[:, c], D[:, c], min_depth=1e-3, max_depth=p.max_depth))
    by_bin: dict[str, list[int]] = {name: [] for name in SPEED_BINS}
    for j, v in enumerate(speeds):
        by_bin[speed_bin(v)].append(j)
    speed_bins = {name: block(ws) if ws else {"windows": 0} for name, ws in by_bin.items()}
    protocol = {"data": source.name, "split": split, "scenes": num_scenes, "images": S * V, "cameras": names,
                "mode": p.mode, "frames": list(frames), "target": target,
                **({"supersample": data_preset.supersample} if source.synthetic_streets else {}),
                "lpips": "on" if lpips is not None else "off (no weights given)",
                "depth_gt": "none" if not preds else ("depth maps of the data" if "depths" in s
                                                      else "projected LiDAR at t (nearest return per pixel)"),
                "oracle_psnr": "oracle-depth pixel reconstruction of the same target" if oracles else "not run",
                "layout": (f"image-blind: per-pixel median true depth of {layout} training windows"
                           if lay is not None else "not run"),
                "constant_motion": (f"image-blind: camera 0's true motion t -> t+1 averaged over {layout} "
                                    "training windows, for every held-out window" if constant else "not run"),
                "speed_bins": "held-out windows by the ego's true speed t -> t+1: " + ", ".join(
                    f"{n} [{lo:g}, {hi:g}) m/s" for n, (lo, hi) in SPEED_BINS.items()),
                "pose_source": getattr(p, "pose_source", "network"),
                "pose": ({"network": "pose network, camera 0, t -> t+1, against the data's ego motion; mean over "
                                     "windows",
                          "geometric": "the images' own motion (ground-plane fit at "
                                       f"{'x'.join(map(str, _geometric_size(p)))}), camera 0, t -> t+1, against the "
                                       "data's ego motion; mean over windows"}.get(pose_source)
                         or "not evaluated (pose_source 'dataset': the pose network is not trained)")}
    out = metrics_report(FAMILY, p.name, step, protocol, all_, per_camera, speed_bins=speed_bins)
    if out_dir is not None:
        od = Path(out_dir)
        od.mkdir(parents=True, exist_ok=True)
        write_metrics(od, out)
        r, s, d = first
        t = s["images"][ti]
        make_contact_sheet(r.clamp(0, 1).permute(0, 2, 3, 1), t.permute(0, 2, 3, 1), od / "contact_sheet.png",
                           names=names, title=f"DrivingForward {p.name} ({p.mode}): frames {list(frames)} -> {target:+d}, "
                                             f"PSNR {out['all']['psnr']:.2f} dB")
        if d is not None:
            make_contact_sheet(_depth_colour(d[0]), _depth_colour(d[1]), od / "depth_sheet.png", names=names,
                               title=f"depth at t: prediction | ground truth (inverse depth); AbsRel {out['all']['abs_rel']:.3f}")
    return out


@torch.no_grad()
def validation_point(model, source, num_scenes: int, cameras: Sequence[str] | None = None) -> dict:
    """One point of the validation learning curve: depth at t and the pose network's camera-0 motion
    t -> t+1 on validation windows ``0 .. num_scenes-1`` (no rendering, no controls; cheap enough to
    run every few steps). The model's train/eval mode is restored.

    Returns ``{"abs_rel", "delta1", "scale_ratio", ["pose_t_err_m", "pose_t_err_pct", ...]}``.
    """
    was_training = model.training
    model.eval()
    p = model.preset
    preds, gts, poses = [], [], []
    try:
        for i in range(num_scenes):
            s = load_triplet(source, i, p, split="val", cameras=cameras)
            gt = s["depths"][1] if "depths" in s else s.get("lidar_depth")
            if gt is not None:
                preds.append(model.depth_net(s["images"][1], s["Ks"], s["cam_to_ego"])["depth"][:, 0])
                gts.append(gt)
            if getattr(p, "pose_source", "network") == "network":
                T = model.pose_net(s["images"][1], s["images"][2], s["Ks"], s["cam_to_ego"])
                poses.append(pose_errors(T, camera0_motion(s).to(T.dtype)))
    finally:
        model.train(was_training)
    out = {}
    if preds:
        m = depth_metrics(torch.stack(preds), torch.stack(gts), min_depth=1e-3, max_depth=p.max_depth)
        out.update({k: m[k] for k in ("abs_rel", "delta1", "scale_ratio")})
    out.update(_pose_summary(poses, "pose_"))
    return out
