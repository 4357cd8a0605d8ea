"""The oracle-depth baseline's SSIM (``clsplat.pixel_recon``) before and after issue 20's "one
SSIM": before, kornia's map with 'same' (reflect) padding and eps 1e-12, averaged over every
pixel; after, :func:`clsplat.image_metrics.ssim` ('valid' padding, eps 0), the metric the model
families report. PSNR is computed both ways too (kornia's pooled PSNR against the engine's).
Runs ``pixel_recon.main`` once per size and scores its renders with both definitions.

    .venv/bin/python bench/experiments/baseline_ssim.py --sizes 176x320 32x64
"""
from __future__ import annotations

import argparse
import sys
import tempfile

import kornia
import torch

import clsplat.pixel_recon as pr


def before(renders: torch.Tensor, targets: torch.Tensor) -> dict:
    """The pre-issue-20 ``pixel_recon.evaluate``: kornia, 'same' padding, default eps."""
    a = renders.detach().float().clamp(0, 1).permute(0, 3, 1, 2)
    b = targets.detach().float().clamp(0, 1).permute(0, 3, 1, 2)
    smap = kornia.metrics.ssim(a, b, window_size=11, max_val=1.0)
    return {"psnr": float(kornia.metrics.psnr(a, b, max_val=1.0)), "ssim": float(smap.mean()),
            "ssim_per_camera": [float(smap[i].mean()) for i in range(a.shape[0])]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", default=["176x320"], help="HxW per camera (default 176x320)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    captured: dict = {}
    evaluate = pr.evaluate

    def capture(renders, targets, mask=None):
        captured.update(renders=renders, targets=targets)
        return evaluate(renders, targets, mask)

    pr.evaluate = capture
    print("| size | PSNR before (kornia) | PSNR after | SSIM before ('same', all pixels) | SSIM after ('valid') |")
    print("|---|---|---|---|---|")
    for size in args.sizes:
        try:
            h, w = (int(v) for v in size.split("x"))
        except ValueError:
            print(f"--sizes: expected HxW, got {size!r}", file=sys.stderr)
            return 2
        with tempfile.TemporaryDirectory() as out:
            after = pr.main(out, height=h, width=w, seed=args.seed, progress=False)
        old = before(captured["renders"], captured["targets"])
        print(f"| {h}x{w} | {old['psnr']:.3f} dB | {after['psnr']:.3f} dB | {old['ssim']:.4f} | {after['ssim']:.4f} |")
        print(f"|   per camera | | | {', '.join(f'{v:.3f}' for v in old['ssim_per_camera'])} | "
              f"{', '.join(f'{v:.3f}' for v in after['ssim_per_camera'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
