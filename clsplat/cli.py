"""The ``clsplat`` console command.

    clsplat info                      OpenCL platforms, devices and the features clsplat uses
    clsplat demo [--out DIR]          the main job: pixel-aligned reconstruction of the built-in
                                      surround-view scene (PoCL CPU by default)
    clsplat fit OUT [...]             fit Gaussians to an image (the optimisation example)
    clsplat bench REPORT [...]        benchmark reports (stages, precision, stability, all)
    clsplat train FAMILY [...]        train a model (drivingforward, pgt, autosplat)
    clsplat eval FAMILY [...]         evaluate a trained model
"""
from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main"]


def _info(_: argparse.Namespace) -> int:
    from .runtime import describe_devices
    print(describe_devices())
    return 0


def _demo(a: argparse.Namespace) -> int:
    import torch

    from .pixel_recon import main as recon
    torch.set_num_threads(1)  # torch and PoCL's workers otherwise fight over the cores
    m = recon(a.out, height=a.height, width=a.width, seed=a.seed, device=a.device)
    print(f"pixel-aligned reconstruction: {m['num_gaussians']} Gaussians from frame t, "
          f"rendered at t+1 into {len(m['cameras'])} cameras of {m['width']}x{m['height']}")
    print(f"PSNR {m['psnr']:.2f} dB  SSIM {m['ssim']:.3f}")
    print("seconds per step: " + json.dumps({k: round(v, 3) for k, v in m["timings_s"].items()}))
    print(f"outputs in {m['out_dir']} (contact_sheet.png, renders/, metrics.json)")
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["bench"]:
        from .bench_cli import main as bench
        return bench(argv[1:])
    if argv[:1] in (["train"], ["eval"]):
        from .models.common.cli import dispatch
        return dispatch(argv[0], argv[1:])
    if argv[:1] == ["fit"]:
        from .fit_image import _cli
        _cli(argv[1:])
        return 0
    p = argparse.ArgumentParser(prog="clsplat", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info", help="list OpenCL devices and features").set_defaults(fn=_info)
    d = sub.add_parser("demo", help="pixel-aligned reconstruction of the built-in scene")
    d.add_argument("--out", default="out", help="output folder (default: out)")
    d.add_argument("--height", type=int, default=176)
    d.add_argument("--width", type=int, default=320)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--device", default=None, help="OpenCL device (default: CLSPLAT_DEVICE, else GPU, else PoCL)")
    d.set_defaults(fn=_demo)
    sub.add_parser("fit", help="fit Gaussians to an image (see clsplat fit --help)")
    sub.add_parser("bench", help="benchmark reports (see clsplat bench --help)")
    sub.add_parser("train", help="train a model: clsplat train {drivingforward,pgt,autosplat} --help")
    sub.add_parser("eval", help="evaluate a model: clsplat eval {drivingforward,pgt,autosplat} --help")
    a = p.parse_args(argv)
    return a.fn(a)


if __name__ == "__main__":
    sys.exit(main())
