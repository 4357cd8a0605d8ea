"""The per-Gaussian backward (``RenderConfig.backward_impl="gaussian"``,
kernels/composite_bwd_gauss.cl) against the per-pixel one ("pixel", kernels/composite_bwd.cl),
interleaved in one process: the table of bench/notes/engine_cpu_speed.md, "per-Gaussian
backward" (issue 35 item 1).

    python bench/experiments/backward_ab.py [--scenes A,B,10000,100000,1000000] [--rounds 5]
        [--layouts packed,unpacked]

Scenes: A and B of :mod:`clsplat.bench.scenes`, and scene-A-like scenes of N Gaussians
(:func:`clsplat.bench.scenes.sweep_n`, 640x352, SH3). Every parameter requires grad; the loss is
``sum(render * w) + sum(alpha * wa)`` with fixed random weights (as ``clsplat bench stages``).
After one warm-up call of each variant, each of ``--rounds`` rounds runs one forward + backward
per (scene, layout, implementation), the implementations' order flipping every round and every
scene in every round (a change of the machine's load hits all alike). Per call: the device ms
of the backward's compositing kernel ("composite_bwd", profiling events), of all backward kernels
and of all forward kernels; and, in a second call per round, the process CPU time (all threads,
PoCL's included) of the backward's compositing kernel waited for alone ("bwd_cpu"): the work
done, which waiting for a core on a loaded machine does not stretch. Each call's gradients are
compared: "gaussian" against "pixel" of the same round (relative L2 and largest absolute
difference per parameter; float32 rounding), and each implementation against its own first call (bitwise). The 1-minute load
average is read before and after each round. Prints one JSON line per (scene, layout) with the
medians, the gaussian / pixel ratios of the medians, and the slot memory (the same array for
both: M x slot width x 4 bytes).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

import clsplat  # first: thread defaults before torch loads
from clsplat import stages
from clsplat.bench import scenes as S
from clsplat.bench.timing import event_ms
from clsplat.config import RenderConfig
from clsplat.runtime import get_runtime

__all__ = ["main"]

IMPLS = ("pixel", "gaussian")
PARAMS = ("means", "quats", "scales", "opacities", "colors")
FWD_STAGES_SKIP = ("composite_bwd", "reduce", "sh_bwd", "project_bwd")
BWD_KERNELS = ("composite_bwd", "composite_bwd_gauss")


def _scene(name: str) -> dict:
    if name == "A":
        return S.scene_a()
    if name == "B":
        return S.scene_b()
    return next(S.sweep_n((int(name),)))


def _call(rt, scene: dict, impl: str, packed: bool, w, wa, cpu: bool = False) -> dict:
    """One forward + backward: device ms per group, the gradients, and with ``cpu`` the
    process CPU ms of the backward's compositing kernel(s), each waited for alone."""
    cfg = RenderConfig(backward_impl=impl)
    leaves = {k: scene[k].clone().requires_grad_() for k in PARAMS}
    events: list = []
    enqueue, cpu_ms = rt.enqueue, [0.0]

    def timed(kernel, *args):
        if kernel.function_name not in BWD_KERNELS:
            return enqueue(kernel, *args)
        rt.finish()
        c0 = time.process_time()
        ev = enqueue(kernel, *args)
        ev.wait()
        cpu_ms[0] += (time.process_time() - c0) * 1e3
        return ev
    if cpu:
        rt.enqueue = timed
    try:
        out, alpha, meta = clsplat.rasterization(
            *(leaves[k] for k in PARAMS), scene["viewmats"], scene["Ks"], scene["width"], scene["height"],
            sh_degree=scene["sh_degree"], device=rt, config=cfg, events=events, packed=packed)
        n_fwd = len(events)
        ((out * w).sum() + (alpha * wa).sum()).backward()
        rt.finish()
    finally:
        if cpu:
            del rt.enqueue
    fwd = sum(event_ms(ev) for _, ev in events[:n_fwd])
    bwd = sum(event_ms(ev) for _, ev in events[n_fwd:])
    comp = sum(event_ms(ev) for n, ev in events[n_fwd:] if n == "composite_bwd")
    M = int(meta["flatten_ids"].numel())
    return {"fwd": fwd, "bwd": bwd, "composite_bwd": comp, "bwd_cpu": cpu_ms[0], "M": M,
            "_grads": {k: v.grad.clone() for k, v in leaves.items()}}


def _load() -> float:
    return os.getloadavg()[0]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="A,B,10000,100000,1000000")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--layouts", default="packed,unpacked")
    args = ap.parse_args(argv)
    rt = get_runtime(None)
    scenes = {n: _scene(n) for n in args.scenes.split(",")}
    layouts = [x == "packed" for x in args.layouts.split(",")]
    weights = {}
    for n, sc in scenes.items():
        g = torch.Generator().manual_seed(1)
        C, H, W = int(sc["viewmats"].shape[0]), sc["height"], sc["width"]
        weights[n] = (torch.rand((C, H, W, 3), generator=g), torch.rand((C, H, W, 1), generator=g))
    rows: dict = {(n, p, i): [] for n in scenes for p in layouts for i in IMPLS}
    first: dict = {}
    checks: dict = {(n, p): {"rel": {k: 0.0 for k in PARAMS}, "max_abs": {k: 0.0 for k in PARAMS},
                             "bitwise_repeat": True} for n in scenes for p in layouts}
    for n, sc in scenes.items():  # warm-up: builds, JIT, and each variant's first gradients
        for p in layouts:
            for i in IMPLS:
                first[(n, p, i)] = _call(rt, sc, i, p, *weights[n])["_grads"]
    loads = []
    for r in range(args.rounds):
        loads.append(_load())
        order = IMPLS if r % 2 == 0 else IMPLS[::-1]
        for n, sc in scenes.items():
            for p in layouts:
                got = {}
                for i in order:
                    t = _call(rt, sc, i, p, *weights[n])
                    t["bwd_cpu"] = _call(rt, sc, i, p, *weights[n], cpu=True)["bwd_cpu"]
                    got[i] = t["_grads"]
                    ch = checks[(n, p)]
                    ch["bitwise_repeat"] &= all(torch.equal(t["_grads"][k], first[(n, p, i)][k]) for k in PARAMS)
                    rows[(n, p, i)].append({k: v for k, v in t.items() if not k.startswith("_")})
                for k in PARAMS:  # (a parameter whose true gradient is 0, e.g. the quats of
                    # isotropic Gaussians (scene B), compares rounding noise: see max_abs)
                    a, b = got["gaussian"][k].double(), got["pixel"][k].double()
                    ch = checks[(n, p)]
                    ch["rel"][k] = max(ch["rel"][k], float((a - b).norm() / b.norm().clamp_min(1e-30)))
                    ch["max_abs"][k] = max(ch["max_abs"][k], float((a - b).abs().max()))
        loads.append(_load())
    for n in scenes:
        for p in layouts:
            med = {i: {k: statistics.median(x[k] for x in rows[(n, p, i)])
                       for k in ("fwd", "bwd", "composite_bwd", "bwd_cpu")} for i in IMPLS}
            for i in IMPLS:
                med[i]["bwd/fwd"] = med[i]["bwd"] / med[i]["fwd"]
            ratio = {k: med["gaussian"][k] / med["pixel"][k] for k in ("composite_bwd", "bwd", "bwd_cpu", "bwd/fwd")}
            M = rows[(n, p, "pixel")][0]["M"]
            print(json.dumps({"scene": n, "layout": "packed" if p else "unpacked", "rounds": args.rounds,
                              "intersections": M, "slot_MiB": M * 9 * 4 / 2 ** 20,
                              "median": med, "gaussian/pixel": ratio, "checks": checks[(n, p)],
                              "load_1min": [min(loads), max(loads)]}), flush=True)


if __name__ == "__main__":
    main()
