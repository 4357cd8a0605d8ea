"""Per-call cost of :func:`clsplat.rasterization`: forward and backward, small to large scenes.

    clsplat bench percall [--scenes tiny,small,medium,large] [--repeats 30]
        [--layout packed|unpacked|both] [--profile] [--json FILE]

For each scene and layout it times ``repeats`` forward passes and ``repeats`` backward passes
(after 3 warm-up calls) and reports medians of

* ``fwd_ms`` / ``bwd_ms``: wall time of ``rasterization(...)`` and of ``loss.backward()``;
* ``cpu_ms``: CPU time of the calling thread over forward + backward (``time.thread_time``):
  the Python glue, argument checks and enqueues, without the waits on the device;
* ``kernel_ms``: the device time of every launch (OpenCL profiling events, end - start);

so ``fwd_ms + bwd_ms - cpu_ms - kernel_ms`` is roughly what the waits cost (queue wake-ups,
which the scheduler stretches on a loaded machine). ``--profile`` adds the cProfile entries
with the most own time over the timed loop.

Scenes: ``tiny`` 100 Gaussians at 64x48 (the fixed cost), ``small`` 10k at 160x88,
``medium`` 100k at 640x352 (bench scene A's size), ``large`` 1M at 640x352; plain RGB
colours (no SH), one camera, drawn by :func:`clsplat.bench.scenes.random_frustum_scene`.
"""
from __future__ import annotations

import cProfile
import io
import json
import pstats
import statistics
import time

import torch

import clsplat
from clsplat.argparser import ArgumentParser

from .scenes import random_frustum_scene, render_args
from .timing import event_ms

__all__ = ["SCENES", "time_calls", "main"]

SCENES = {"tiny": (100, 64, 48), "small": (10_000, 160, 88), "medium": (100_000, 640, 352),
          "large": (1_000_000, 640, 352)}


def _leaves(scene: dict) -> dict:
    args = render_args(scene)
    for k in ("means", "quats", "scales", "opacities", "colors"):
        args[k] = args[k].clone().requires_grad_()
    return args


def time_calls(name: str, packed: bool, repeats: int, profile: bool = False) -> dict:
    """Medians over ``repeats`` forward + backward calls of scene ``name`` (see module doc)."""
    n, w, h = SCENES[name]
    args = _leaves(random_frustum_scene(n, w, h, sh_degree=None, seed=0))
    fwd, bwd, cpu, kern = [], [], [], []

    def once(record: bool) -> None:
        events: list = []
        c0 = time.thread_time()
        t0 = time.perf_counter()
        img, alpha, _ = clsplat.rasterization(**args, packed=packed, events=events)
        t1 = time.perf_counter()
        (img.sum() + alpha.sum()).backward()
        t2 = time.perf_counter()
        c1 = time.thread_time()
        if record:
            fwd.append(t1 - t0)
            bwd.append(t2 - t1)
            cpu.append(c1 - c0)
            kern.append(sum(event_ms(e) for _, e in events))
        for k in ("means", "quats", "scales", "opacities", "colors"):
            args[k].grad = None

    for _ in range(3):
        once(False)
    prof = cProfile.Profile() if profile else None
    if prof is not None:
        prof.enable()
    for _ in range(repeats):
        once(True)
    if prof is not None:
        prof.disable()
    med = lambda xs: statistics.median(xs) * 1e3  # noqa: E731
    out = {"scene": name, "N": n, "size": f"{w}x{h}", "packed": packed, "repeats": repeats,
           "fwd_ms": med(fwd), "bwd_ms": med(bwd), "total_ms": med([a + b for a, b in zip(fwd, bwd)]),
           "cpu_ms": med(cpu), "kernel_ms": statistics.median(kern)}
    if prof is not None:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(12)
        out["profile"] = s.getvalue()
    return out


def main(argv: list[str] | None = None) -> int:
    p = ArgumentParser(prog="clsplat bench percall", description=__doc__.split("\n")[0])
    p.add_argument("--scenes", default="tiny,small,medium", help=f"comma-separated, of {sorted(SCENES)}")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--layout", choices=("packed", "unpacked", "both"), default="packed")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--json", default=None, help="append one JSON line per result to this file")
    a = p.parse_args(argv)
    names = [s for s in a.scenes.split(",") if s]
    bad = [s for s in names if s not in SCENES]
    if bad or a.repeats < 1:
        p.error(f"--scenes: unknown {bad}" if bad else "--repeats: must be >= 1")
    torch.set_num_threads(1)
    layouts = {"packed": (True,), "unpacked": (False,), "both": (True, False)}[a.layout]
    for name in names:
        for packed in layouts:
            r = time_calls(name, packed, a.repeats, a.profile)
            prof = r.pop("profile", None)
            print(json.dumps(r), flush=True)
            if prof:
                print(prof)
            if a.json:
                with open(a.json, "a") as f:
                    f.write(json.dumps(r) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
