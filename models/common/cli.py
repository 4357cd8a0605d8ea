"""What every ``clsplat train FAMILY`` / ``clsplat eval FAMILY`` command shares.

:func:`add_common_args` and :func:`add_eval_args` add the arguments every family takes, so that
the commands read alike (the skeleton that runs them is :mod:`.command`)::

    clsplat train drivingforward --data synthetic --preset tiny --steps 100 --out runs/df
    clsplat eval pgt --checkpoint runs/pgt/checkpoint.pt --data synthetic --out runs/pgt-eval
"""
from __future__ import annotations

import argparse

__all__ = ["add_common_args", "add_view_args", "add_eval_args",
           "add_lpips_args", "lpips_from_args", "positive_int", "add_trust_pickle_arg",
           "add_eval_scenes_arg", "add_eval_split_arg"]


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def add_trust_pickle_arg(p: argparse.ArgumentParser) -> None:
    """--trust-pickle: the explicit opt-out of allow-listed unpickling (PandaSet data)."""
    p.add_argument("--trust-pickle", action="store_true",
                   help="unpickle PandaSet's .pkl.gz files with pandas' own reader, which runs any code a file "
                        "names; only for data from a source you trust (default: allow-listed, safe)")


def add_common_args(p: argparse.ArgumentParser, default_preset: str = "small") -> None:
    """The flags every ``clsplat train FAMILY`` takes: --data, --preset, --set, --steps, --out,
    --resume, --seed, --device, --threads, --checkpoint-every, --batch-size, --weights,
    --no-progress, --trust-pickle, --lpips-vgg, --lpips-lin."""
    p.add_argument("--data", default="synthetic",
                   help="synthetic | pandaset:PATH | nuscenes:PATH (default: synthetic)")
    p.add_argument("--preset", default=default_preset, help=f"preset name (default: {default_preset})")
    p.add_argument("--set", action="append", default=None, metavar="FIELD=VALUE",
                   help="change one preset field for this run (a Python literal; repeatable; stored in the "
                        "checkpoint)")
    p.add_argument("--steps", type=positive_int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--out", required=True, help="run directory (checkpoint.pt, log.jsonl, loss.png, metrics.json)")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt, bitwise")
    p.add_argument("--seed", type=int, default=0, help="seed for initialisation and data (default: 0)")
    p.add_argument("--device", default=None, help="OpenCL device (default: CLSPLAT_DEVICE, else GPU, else PoCL)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="torch threads (default: 1 on a CPU OpenCL device, where PoCL needs the cores)")
    p.add_argument("--checkpoint-every", type=positive_int, default=100, help="steps between checkpoints")
    p.add_argument("--batch-size", type=positive_int, default=None, help="global batch (default: the preset's)")
    p.add_argument("--weights", default=None,
                   help="local pretrained backbone weights (torchvision names) for the family's encoders; "
                        "nothing is downloaded (default: random initialisation)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_trust_pickle_arg(p)
    add_lpips_args(p)


def add_eval_scenes_arg(p: argparse.ArgumentParser) -> None:
    """--eval-scenes: held-out scenes a feed-forward family evaluates at the end of training."""
    p.add_argument("--eval-scenes", type=int, default=2,
                   help="held-out scenes evaluated at the end into OUT/metrics.json (default 2; 0: none)")


def add_eval_split_arg(p: argparse.ArgumentParser) -> None:
    """--eval-split: the held-out split scored (``val``, where preset fields are chosen, or ``test``,
    reported once per recipe)."""
    p.add_argument("--eval-split", choices=("val", "test"), default="test",
                   help="held-out split to score: val (choose preset fields here) or test (report once; default)")


def add_view_args(p: argparse.ArgumentParser) -> None:
    """--view, --view-host, --view-port, --view-every: watch the run in the browser (clsplat view)."""
    p.add_argument("--view", action="store_true", help="serve the scene as it trains (needs the view extra)")
    p.add_argument("--view-host", default="127.0.0.1", help="address of the viewer (default 127.0.0.1)")
    p.add_argument("--view-port", type=int, default=8080, help="port of the viewer (default 8080)")
    p.add_argument("--view-every", type=positive_int, default=10,
                   help="steps between refreshes of the Gaussians shown (default 10; only while a browser is open)")


def add_eval_args(p: argparse.ArgumentParser, scenes: bool = True) -> None:
    """The flags every ``clsplat eval FAMILY`` takes: --checkpoint, --data, --out, --device,
    --threads, --seed, --no-progress, --trust-pickle, --lpips-vgg, --lpips-lin, and with
    ``scenes`` (the feed-forward families) --num-scenes."""
    p.add_argument("--checkpoint", required=True, help="checkpoint.pt written by clsplat train")
    p.add_argument("--data", default="synthetic", help="synthetic | pandaset:PATH | nuscenes:PATH")
    p.add_argument("--out", required=True, help="output folder (metrics.json, contact sheets)")
    p.add_argument("--device", default=None, help="OpenCL device")
    p.add_argument("--threads", type=positive_int, default=None, help="torch threads")
    p.add_argument("--seed", type=int, default=0, help="seed of the held-out scenes")
    if scenes:
        p.add_argument("--num-scenes", type=positive_int, default=4, help="held-out scenes to evaluate")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_trust_pickle_arg(p)
    add_lpips_args(p)


def add_lpips_args(p: argparse.ArgumentParser) -> None:
    """--lpips-vgg, --lpips-lin: LPIPS runs only when both local files are given."""
    p.add_argument("--lpips-vgg", default=None,
                   help="local torchvision VGG-16 state dict for LPIPS (without it LPIPS is off)")
    p.add_argument("--lpips-lin", default=None, help="local lpips v0.1 linear layers (lpips/weights/v0.1/vgg.pth)")


def lpips_from_args(args: argparse.Namespace):
    """The :class:`~.metrics.LPIPS` module named by ``--lpips-vgg/--lpips-lin``, or None; prints
    which, so that a run says whether LPIPS is on."""
    from .metrics import lpips_or_none

    module, message = lpips_or_none(args.lpips_vgg, args.lpips_lin)
    print(message, flush=True)
    return module
