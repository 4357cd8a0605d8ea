"""Pixel-aligned reconstruction with oracle depth: the embedded default job.

1. Generate the synthetic street (:mod:`clsplat.data.synthetic`): 6 cameras, 2 frames
   (t = 0 s and t = 0.1 s, the ego drives 0.8 m and changes lane), default 176 x 320.
2. Lift every non-sky pixel of the 6 cameras at frame 0 into one Gaussian, using the
   generator's ground-truth z-depth: mean = the pixel centre ``(x + 0.5, y + 0.5)`` unprojected
   to world, isotropic scale ``scale_px * depth / f`` (about one pixel footprint; ``f`` the
   mean focal length), opacity 0.95, colour = the pixel's RGB (plain colours, no SH).
3. Render the 6 cameras of frame 1 with :func:`clsplat.rasterization`; the background is the
   mean sky colour of frame 0 (sky pixels are not lifted).
4. Report PSNR and SSIM (:mod:`clsplat.image_metrics`, the models' metrics: 11x11 Gaussian
   window, 'valid' padding) against frame 1's ground truth, over all pixels of all cameras and
   per camera, ``psnr_masked`` over the pixels that are neither sky nor a moving vehicle in
   frame 1, plus wall time per step.  Errors come
   from disocclusions, the moving vehicles (lifted at their frame-0 place), the blinking lights
   and the stretched footprint of surfaces seen at grazing angles.
5. Write ``contact_sheet.png`` (render | ground truth | |error| per camera), ``renders/<CAM>.png``,
   ``ground_truth/<CAM>.png`` and ``metrics.json`` into the output folder.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from .data.scene import SEMANTIC_CLASSES, DrivingSequence, unproject_depth
from .data.synthetic import SyntheticConfig, generate_sequence
from .image_metrics import psnr, ssim

__all__ = ["lift_pixels", "main", "evaluate"]


def lift_pixels(seq: DrivingSequence, frame_index: int = 0, opacity: float = 0.95, scale_px: float = 0.5,
                max_depth: float = 1e4) -> dict[str, torch.Tensor]:
    """One Gaussian per finite-depth pixel of every camera of a frame.

    Args:
        seq: sequence with depth maps (e.g. from :func:`~clsplat.data.synthetic.generate_sequence`).
        frame_index: frame to lift.
        opacity: opacity of every Gaussian, in (0, 1].
        scale_px: Gaussian standard deviation in pixels of the source view.
        max_depth: pixels deeper than this (metres) are skipped, like the sky.
    Returns:
        float32 tensors ``means [N,3]``, ``quats [N,4]`` (identity), ``scales [N,3]``,
        ``opacities [N]``, ``colors [N,3]``.
    """
    if not 0 < opacity <= 1:
        raise ValueError(f"opacity must be in (0, 1], got {opacity!r}")
    if not scale_px > 0:
        raise ValueError(f"scale_px must be > 0, got {scale_px!r}")
    f = seq.frames[frame_index] if -len(seq.frames) <= frame_index < len(seq.frames) else None
    if f is None:
        raise ValueError(f"frame_index {frame_index} out of range for {len(seq.frames)} frames")
    means, scales, colors = [], [], []
    for cam in seq.cameras:
        if cam.name not in f.depths:
            raise ValueError(f"frame {frame_index} has no depth for camera {cam.name}; lifting needs depth")
        d = f.depths[cam.name]
        ok = np.isfinite(d) & (d > 0) & (d < max_depth)
        pts = unproject_depth(np.where(ok, d, 1.0), cam.K, seq.cam_to_world(frame_index, cam.name))
        focal = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
        means.append(pts[ok])
        scales.append(np.repeat((scale_px * d[ok] / focal)[:, None], 3, axis=1))
        colors.append(f.images[cam.name][ok])
    m = torch.from_numpy(np.concatenate(means).astype(np.float32))
    n = m.shape[0]
    quats = torch.zeros((n, 4), dtype=torch.float32)
    quats[:, 0] = 1.0
    return {"means": m, "quats": quats, "scales": torch.from_numpy(np.concatenate(scales).astype(np.float32)),
            "opacities": torch.full((n,), float(opacity), dtype=torch.float32),
            "colors": torch.from_numpy(np.concatenate(colors).astype(np.float32))}


def evaluate(renders: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None = None) -> dict:
    """PSNR (dB) and SSIM of ``renders`` vs ``targets``, both ``[C, H, W, 3]`` in [0, 1], with the
    metrics the model families report (:mod:`clsplat.image_metrics`: SSIM over 11x11 Gaussian
    windows with 'valid' padding, so H, W >= 11).

    Returns ``{"psnr", "ssim", "psnr_per_camera": [C], "ssim_per_camera": [C]}``; the overall
    PSNR is over all pixels of all cameras (not the mean of per-camera values), the overall SSIM
    the mean over all cameras' windows.  With a boolean ``mask`` ``[C, H, W]`` also
    ``psnr_masked``: PSNR over the masked pixels only (NaN when the mask is empty).
    """
    if not (isinstance(renders, torch.Tensor) and isinstance(targets, torch.Tensor)) \
            or renders.shape != targets.shape or renders.ndim != 4 or renders.shape[-1] != 3:
        raise ValueError(f"renders {list(getattr(renders, 'shape', []))} and targets "
                         f"{list(getattr(targets, 'shape', []))} must both be [C, H, W, 3] tensors")
    a = renders.detach().float().permute(0, 3, 1, 2)
    b = targets.detach().float().permute(0, 3, 1, 2)

    def side_by_side(x: torch.Tensor) -> torch.Tensor:
        """[C, ch, H, W] -> [1, ch, H, C*W]: one image holding every camera (pooled PSNR)."""
        return torch.cat(list(x), dim=-1)[None]

    extra = {}
    if mask is not None:
        if not isinstance(mask, torch.Tensor) or mask.shape != renders.shape[:3]:
            raise ValueError(f"mask must have shape {list(renders.shape[:3])}, got {list(getattr(mask, 'shape', []))}")
        extra["psnr_masked"] = float(psnr(side_by_side(a), side_by_side(b), side_by_side(mask[:, None])))
    ssim_per_camera = ssim(a, b)
    return {**extra,
        "psnr": float(psnr(side_by_side(a), side_by_side(b))),
        "ssim": float(ssim_per_camera.mean()),
        "psnr_per_camera": [float(v) for v in psnr(a, b)],
        "ssim_per_camera": [float(v) for v in ssim_per_camera],
    }


def main(out_dir: str | Path, height: int = 176, width: int = 320, seed: int = 0, device=None,
         scale_px: float = 0.5, opacity: float = 0.95, progress: bool = True) -> dict:
    """Run the pixel-aligned reconstruction and write its outputs to ``out_dir``.

    Args:
        out_dir: output folder (created).
        height, width: image size of each of the 6 cameras.
        seed: synthetic scene seed.
        device: OpenCL device passed to :func:`clsplat.rasterization` (default: its default).
        scale_px, opacity: see :func:`lift_pixels`.
        progress: show a tqdm progress bar over the steps.
    Returns:
        metrics dict: ``psnr``, ``ssim``, per-camera lists, ``num_gaussians``, ``coverage``
        (mean render alpha), ``timings_s`` (seconds per step), ``cameras``, ``height``, ``width``,
        ``seed``, ``out_dir``.
    """
    from tqdm import tqdm

    import clsplat
    from .io.contact_sheet import make_contact_sheet
    from .io.atomic import write_text_atomic
    from .io.images import write_image

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir {str(out)!r} exists and is not a folder")
    timings: dict[str, float] = {}
    steps = ["generate scene", "lift pixels", "rasterize", "metrics", "write outputs"]
    bar = tqdm(total=len(steps), desc="pixel_recon", unit="step", disable=not progress)

    def tick(name: str, t0: float) -> None:
        timings[name] = round(time.perf_counter() - t0, 4)
        bar.set_postfix_str(f"{name}: {timings[name]:.2f}s")
        bar.update(1)

    t0 = time.perf_counter()
    cfg = SyntheticConfig(height=height, width=width, num_frames=2, seed=seed, lidar=False)
    seq = generate_sequence(cfg)
    tick("generate scene", t0)

    t0 = time.perf_counter()
    g = lift_pixels(seq, 0, opacity=opacity, scale_px=scale_px)
    sky_id = SEMANTIC_CLASSES.index("sky")
    f0 = seq.frames[0]
    sky = [f0.images[c][f0.semantics[c] == sky_id] for c in seq.camera_names]
    sky = np.concatenate(sky) if sum(len(s) for s in sky) else np.full((1, 3), 0.8, np.float32)
    bg_color = torch.from_numpy(sky.mean(axis=0).astype(np.float32))
    tick("lift pixels", t0)

    t0 = time.perf_counter()
    C = len(seq.cameras)
    viewmats = torch.from_numpy(seq.viewmats(1).astype(np.float32))
    Ks = torch.from_numpy(seq.Ks().astype(np.float32))
    renders, alphas, _ = clsplat.rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                               viewmats, Ks, width, height, backgrounds=bg_color.expand(C, 3).contiguous(),
                                               device=device)
    tick("rasterize", t0)

    t0 = time.perf_counter()
    target = torch.from_numpy(seq.images(1))
    moving = [v.track_id for v in seq.metadata["scene"].vehicles if v.speed > 0]
    f1 = seq.frames[1]
    mask = np.stack([(f1.semantics[c] != sky_id) & ~np.isin(f1.instances[c], moving) for c in seq.camera_names])
    metrics = evaluate(renders, target, torch.from_numpy(mask))
    tick("metrics", t0)

    t0 = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    (out / "renders").mkdir(exist_ok=True)
    (out / "ground_truth").mkdir(exist_ok=True)
    r_np = renders.detach().clamp(0, 1).numpy()
    for i, name in enumerate(seq.camera_names):
        write_image(out / "renders" / f"{name}.png", r_np[i])
        write_image(out / "ground_truth" / f"{name}.png", seq.frames[1].images[name])
    make_contact_sheet(r_np, target.numpy(), out / "contact_sheet.png", names=seq.camera_names,
                       title=f"pixel-aligned oracle-depth recon: frame 0 -> frame 1, PSNR {metrics['psnr']:.2f} dB, "
                             f"SSIM {metrics['ssim']:.3f}")
    tick("write outputs", t0)
    bar.close()
    metrics.update({
        "num_gaussians": int(g["means"].shape[0]),
        "coverage": float(alphas.mean()),
        "timings_s": timings,
        "cameras": seq.camera_names,
        "height": height,
        "width": width,
        "seed": seed,
        "out_dir": str(out),
    })
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=2))
    return metrics
