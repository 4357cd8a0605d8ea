"""The ``clsplat`` console command.

    clsplat info                      OpenCL platforms, devices and the features clsplat uses
    clsplat demo [--out DIR]          the main job: AutoSplat reconstruction of the built-in
                                      street (PoCL CPU by default), against the oracle-depth baseline
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

    from .models.autosplat.demo import run_demo
    torch.set_num_threads(1)  # torch and PoCL's workers otherwise fight over the cores
    m = run_demo(a.out, seed=a.seed, device=a.device)
    g, b = m["gaussians"], m["baseline"]
    print(f"AutoSplat reconstruction of the built-in street: {len(m['cameras'])} cameras, "
          f"{len(m['train_frames'])} training frames, held-out frames {m['test_frames']}")
    print(f"  {g['total']} Gaussians (road {g['road']}, sky {g['sky']}, other {g['other']}, "
          f"{g['tracks']} tracked objects {g['objects']}), {m['iterations']} iterations")
    print(f"held-out PSNR {m['test_psnr']:.2f} dB  SSIM {m['test_ssim']:.3f}   "
          f"(oracle-depth baseline, pixel_recon: PSNR {b['test_psnr']:.2f} dB  SSIM {b['test_ssim']:.3f})")
    print("lane-change renders (rig shifted left), PSNR vs the generator: "
          + "  ".join(f"{k} {v['psnr']:.2f} dB" for k, v in m["lateral_shift"].items()))
    print("seconds per stage: " + json.dumps({k: round(v, 1) for k, v in m["seconds_per_stage"].items()}))
    print(f"outputs in {a.out} (contact_sheet.png, lateral_shift_*m.png, scene.ply, metrics.json, loss.png)")
    return 0


#: optional packages and the setup.cfg extra that installs each
_EXTRAS = {"OpenImageIO": "io", "matplotlib": "io", "pandas": "data", "kornia": "models", "tqdm": "models"}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        return _main(argv)
    except ModuleNotFoundError as e:
        top = (e.name or "").split(".")[0]
        if top not in _EXTRAS:
            raise
        raise SystemExit(f"clsplat {' '.join(argv[:1])}: needs the optional package {top!r}, "
                         f"installed by: pip install 'clsplat[{_EXTRAS[top]}]'") from None


def _main(argv: list[str]) -> int:
    if argv[:1] == ["bench"]:
        from .bench_cli import main as bench
        return bench(argv[1:])
    if argv[:1] in (["train"], ["eval"]):
        from .models.common.cli import dispatch
        return dispatch(argv[0], argv[1:])
    if argv[:1] == ["data"]:
        from .data.synthetic_cache import main as data
        return data(argv[1:])
    if argv[:1] == ["fit"]:
        from .fit_image import _cli
        _cli(argv[1:])
        return 0
    p = argparse.ArgumentParser(prog="clsplat", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("info", help="list OpenCL devices and features").set_defaults(fn=_info)
    d = sub.add_parser("demo", help="AutoSplat reconstruction of the built-in street")
    d.add_argument("--out", default="out", help="output folder (default: out)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--device", default=None, help="OpenCL device (default: CLSPLAT_DEVICE, else GPU, else PoCL)")
    d.set_defaults(fn=_demo)
    sub.add_parser("fit", help="fit Gaussians to an image (see clsplat fit --help)")
    sub.add_parser("bench", help="benchmark reports (see clsplat bench --help)")
    sub.add_parser("data", help="data tools: clsplat data synth --count N --out DIR (a cache of synthetic streets)")
    sub.add_parser("train", help="train a model: clsplat train {drivingforward,pgt,autosplat} --help")
    sub.add_parser("eval", help="evaluate a model: clsplat eval {drivingforward,pgt,autosplat} --help")
    a = p.parse_args(argv)
    return a.fn(a)


if __name__ == "__main__":
    sys.exit(main())
