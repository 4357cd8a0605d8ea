"""The main job (``make demo``): AutoSplat on the built-in street, against the oracle-depth baseline.

1. Generate the synthetic street (6 cameras, 16 frames at 0.2 s = 3 s of driving with a lane
   change, two moving vehicles, one with blinking hazard lights, six parked ones), at the demo
   preset's scale (88 x 160 per camera); every 4th frame (2, 6, 10, 14) is held out.
2. Reconstruct it with the ``demo`` preset (:func:`.cli.reconstruct`): LiDAR-initialised
   background in two phases with flatness (the parked cars in it, as LiDAR points), one Gaussian
   set per moving track with mirror copies and residual SH, fusion with pose corrections,
   densification.
3. The baseline it replaces (:mod:`clsplat.pixel_recon`): every pixel of the previous (training)
   frame lifted with the generator's **ground-truth depth** and rendered into the held-out frame.
4. Print and store held-out PSNR / SSIM of both, write the contact sheet and the lateral-shift
   sheets.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from clsplat.argparser import ArgumentParser

__all__ = ["run_demo", "oracle_baseline", "command"]


@torch.no_grad()
def oracle_baseline(data, device=None) -> dict:
    """Held-out PSNR / SSIM of :func:`clsplat.pixel_recon.lift_pixels` from frame i-1 to frame i."""
    import clsplat
    from clsplat.pixel_recon import lift_pixels

    from ..common.metrics import psnr, ssim
    from .init import SKY

    ps, ss = [], []
    for i in data.test_frames:
        src = i - 1 if i > 0 else i + 1
        g = lift_pixels(data.seq, src)
        sky = data.classes[src] == SKY
        bg = data.images[src][sky].mean(0) if bool(sky.any()) else torch.full((3,), 0.8)
        C = len(data.cameras)
        col, _, _ = clsplat.rasterization(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"],
                                          data.viewmats[i], data.Ks, data.width, data.height,
                                          backgrounds=bg.expand(C, 3).contiguous(), device=device)
        r = col.clamp(0, 1).permute(0, 3, 1, 2)
        t = data.images[i].permute(0, 3, 1, 2)
        ps.append(psnr(r, t))
        ss.append(ssim(r, t))
    return {"psnr": float(torch.cat(ps).mean()), "ssim": float(torch.cat(ss).mean()),
            "method": "pixel_recon.lift_pixels: frame i-1 lifted with ground-truth depth, rendered at frame i"}


def run_demo(out_dir: str | Path, seed: int = 0, device=None, progress: bool = True) -> dict:
    """Run the main job into ``out_dir``; returns the metrics (also in ``out_dir/metrics.json``)."""
    from ..common.presets import get_preset
    from ..common.runfolder import RunFolder
    from ..common.report import write_metrics
    from .cli import reconstruct
    from .data import load_sequence
    from .model import Switches
    from .data import prepare_data

    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir: {str(out)!r} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    preset = get_preset("autosplat", "demo")
    if seed != preset.seed:
        preset = preset.replace(seed=seed)
    t0 = time.perf_counter()
    seq = load_sequence("synthetic", None, None, preset.scale, seed=seed)
    data = prepare_data(seq, None, preset.holdout, preset.dynamic_threshold, preset.road_classes)
    load_s = time.perf_counter() - t0
    with RunFolder(out, arg="--out") as rf:  # the lock; outputs staged, then published as a group
        m = reconstruct(data, preset, Switches(), rf.stage, device=device, progress=progress,
                        extra={"data": "synthetic", "scale": preset.scale, "load_seconds": load_s})
        m["baseline"] = oracle_baseline(data, device)
        write_metrics(rf.stage, m)
        rf.publish()
    return m


def command(argv: list[str]) -> int:
    """the main job: AutoSplat reconstruction of the built-in street (``clsplat demo``)"""
    p = ArgumentParser(prog="clsplat demo", description=command.__doc__)
    p.add_argument("--out", default="out", help="output folder (default: out)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default=None, help="OpenCL device (default: CLSPLAT_DEVICE, else GPU, else PoCL)")
    a = p.parse_args(argv)
    torch.set_num_threads(1)  # torch and PoCL's workers otherwise fight over the cores
    m = run_demo(a.out, seed=a.seed, device=a.device)
    g, b = m["gaussians"], m["baseline"]
    pr = m["protocol"]
    print(f"AutoSplat reconstruction of the built-in street: {len(pr['cameras'])} cameras, "
          f"{len(pr['train_frames'])} training frames, held-out frames {pr['test_frames']}")
    print(f"  {g['total']} Gaussians (road {g['road']}, sky {g['sky']}, other {g['other']}, "
          f"{g['tracks']} tracked objects {g['objects']}), {m['step']} iterations")
    print(f"held-out PSNR {m['all']['psnr']:.2f} dB  SSIM {m['all']['ssim']:.3f}   "
          f"(oracle-depth baseline, pixel_recon: PSNR {b['psnr']:.2f} dB  SSIM {b['ssim']:.3f})")
    print("lane-change renders (rig shifted left), PSNR vs the generator: "
          + "  ".join(f"{k} {v['psnr']:.2f} dB" for k, v in m["lane_change"].items()))
    print("seconds per stage: " + json.dumps({k: round(v, 1) for k, v in m["seconds_per_stage"].items()}))
    print(f"outputs in {a.out} (contact_sheet.png, lateral_shift_*m.png, scene.ply, metrics.json, loss.png)")
    return 0
