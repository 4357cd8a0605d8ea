"""Depth sort once (``RenderConfig.sort_impl="depth"``) against the per-tile sort ("tiles"),
interleaved in one process: the sort stage's table of bench/notes/engine_render_plan.md §5.

    python bench/experiments/depth_sort_ab.py [--ns 10000,100000,300000,1000000] [--rounds 7] [--render]
        [--tiny ROUNDS]

For each N, one scene of :func:`clsplat.bench.scenes.sweep_n` (one 640x352 camera, Gaussians
of scene A's sizes) is projected once, up front; then each of ``--rounds`` rounds calls
:func:`clsplat.stages.tile_lists` once per implementation and N, the order of the two
flipping every round, after one warm-up call of each (every N in every round: a change of
the machine's load hits all sizes alike, which keeps the slopes fair). Per call: the device milliseconds of each stage from the
profiling events (the "sort" stage: every event whose name starts with ``sort``, i.e.
``sort_serial`` / ``sort_local`` / ``sort_merge`` against ``sort_depth``; "bin": ``bin_*``)
("stage": both), the wall time of the whole call with the queue drained before and after
(it includes the host's scans and waits, which no event holds), the process's CPU time
over the call (all threads, PoCL's included: the work done, which waiting for a core on a
loaded machine does not stretch), the device milliseconds of each kernel ("kernels_ms", medians; a kernel launched several
times summed per call), and in a second call per round the CPU time of each stage's
kernels ("sort_cpu", "bin_cpu": each kernel waited for after its launch, the CPU time from
its enqueue to its end; the sort kernels are :data:`SORT_KERNELS`); with ``--render``, the
wall time of a whole forward render (``clsplat.rasterization``, no graph; the images of the
two must be equal); with ``--tiny``, the fixed cost per call (:func:`tiny_calls`). The two implementations' tile lists must be equal, key for
key (checked on every call). Prints one JSON line per N with the medians, the depth / tiles
ratios of the medians and the median of the per-round ratios, then the log-log slopes of
each median against N (a fit over every N >= 100000, and over all N).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import torch

import clsplat  # first: thread defaults before torch loads
from clsplat import stages
from clsplat.bench import scenes as S
from clsplat.bench.timing import event_ms
from clsplat.runtime import get_runtime

__all__ = ["main"]

IMPLS = ("tiles", "depth")
KEYS = ("sort", "bin", "stage", "wall", "cpu", "sort_cpu", "bin_cpu")


def _one_call(rt, cfg, p, scene) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """Wall ms, device ms per stage group, and the tile lists of one :func:`tile_lists` call."""
    events: list = []
    launched: list = []  # (kernel name, event) of every rt.launch: the per-kernel breakdown
    launch = rt.launch

    def named(kernel, *args):
        ev = launch(kernel, *args)
        launched.append((kernel.function_name, ev))
        return ev
    rt.launch = named
    try:
        rt.finish()
        c0, t0 = time.process_time(), time.perf_counter()
        off, keys = stages.tile_lists(rt, cfg, p.rects, p.depths, scene["width"], scene["height"], 16,
                                      events=events)
        rt.finish()
        wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
    finally:
        del rt.launch
    t = {"wall": wall, "cpu": cpu, "sort": 0.0, "bin": 0.0, "_kernels": {}}
    for name, ev in events:
        t["sort" if name.startswith("sort") else "bin"] += event_ms(ev)
    t["stage"] = t["sort"] + t["bin"]
    for name, ev in launched:
        t["_kernels"][name] = t["_kernels"].get(name, 0.0) + event_ms(ev)
    return t, off.host().clone(), keys.host().clone()


#: kernels of the sort stage; every other kernel of a tile_lists call is binning ("bin")
SORT_KERNELS = ("depth_count_pairs", "depth_scatter_pairs", "depth_count", "depth_scatter", "order_small",
                "scan_counters", "sort_serial", "sort_local", "sort_merge")


def _kernel_cpu_call(rt, cfg, p, scene) -> dict:
    """Process CPU ms per stage, each kernel waited for right after its launch: the CPU time
    from its enqueue to its end (PoCL's threads included), host glue between kernels apart.
    A load-robust measure: a descheduled kernel's CPU time does not grow, its event time does."""
    t = {"sort_cpu": 0.0, "bin_cpu": 0.0}
    launch = rt.launch

    def timed(kernel, *args):
        rt.finish()
        c0 = time.process_time()
        ev = launch(kernel, *args)
        ev.wait()
        t["sort_cpu" if kernel.function_name in SORT_KERNELS else "bin_cpu"] += (time.process_time() - c0) * 1e3
        return ev
    rt.launch = timed
    try:
        stages.tile_lists(rt, cfg, p.rects, p.depths, scene["width"], scene["height"], 16)
        rt.finish()
    finally:
        del rt.launch
    return t


def _render_call(cfg, scene, x) -> dict:
    """Wall ms of one whole forward render (:func:`clsplat.rasterization`, no graph)."""
    rt = get_runtime(None)
    rt.finish()
    t0 = time.perf_counter()
    with torch.no_grad():
        img, _, _ = clsplat.rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                          x["viewmats"], x["Ks"], scene["width"], scene["height"],
                                          sh_degree=scene["sh_degree"], config=cfg)
    rt.finish()
    return {"render": (time.perf_counter() - t0) * 1e3, "_img": img}


def tiny_calls(rounds: int, calls: int = 10) -> dict:
    """The fixed cost per call: 100 Gaussians at 64 x 48, forward + backward of ``img.sum() +
    alpha.sum()`` through :func:`clsplat.rasterization`, per implementation; ``rounds``
    rounds of ``calls`` calls each (the round's median kept), the order flipping every round."""
    g = torch.Generator().manual_seed(0)
    N, W, H = 100, 64, 48
    xs = [torch.cat([(torch.rand(N, 2, generator=g) - 0.5) * 2, 2 + 2 * torch.rand(N, 1, generator=g)], 1),
          torch.randn(N, 4, generator=g), 0.05 + 0.1 * torch.rand(N, 3, generator=g),
          0.3 + 0.6 * torch.rand(N, generator=g), torch.rand(N, 3, generator=g)]
    vm, K = torch.eye(4)[None], torch.tensor([[[50.0, 0, 32], [0, 50, 24], [0, 0, 1]]])
    cfgs = {impl: clsplat.RenderConfig(sort_impl=impl) for impl in IMPLS}

    def call(cfg) -> float:
        p = [x.clone().requires_grad_() for x in xs]
        t0 = time.perf_counter()
        img, alpha, _ = clsplat.rasterization(*p, vm, K, W, H, config=cfg)
        (img.sum() + alpha.sum()).backward()
        return (time.perf_counter() - t0) * 1e3
    for impl in IMPLS:  # warm-up
        for _ in range(5):
            call(cfgs[impl])
    res = {impl: [] for impl in IMPLS}
    for r in range(rounds):
        for impl in (IMPLS if r % 2 == 0 else IMPLS[::-1]):
            res[impl].append(statistics.median(call(cfgs[impl]) for _ in range(calls)))
    med = {impl: statistics.median(v) for impl, v in res.items()}
    return {"tiny_fwd_bwd_ms": {impl: round(v, 3) for impl, v in med.items()},
            "ratio": round(med["depth"] / med["tiles"], 4),
            "ratio_per_round_median": round(statistics.median(d / t for d, t in zip(res["depth"], res["tiles"])), 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python bench/experiments/depth_sort_ab.py",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--ns", default="10000,100000,300000,1000000")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--render", action="store_true",
                    help="also time a whole forward render per implementation and N (images must be equal)")
    ap.add_argument("--tiny", type=int, default=0, metavar="ROUNDS",
                    help="also time ROUNDS rounds of 10 tiny calls (100 Gaussians, 64x48, fwd+bwd) per implementation")
    a = ap.parse_args(argv)
    ns = [int(x) for x in a.ns.split(",")]
    if a.rounds < 1 or any(n < 1 for n in ns):
        ap.error("--rounds and --ns must be positive")
    rt = get_runtime(None)
    cfgs = {impl: clsplat.RenderConfig(precision="float32", sort_impl=impl) for impl in IMPLS}
    arr = rt.array
    setups = []  # every scene projected once, up front
    for sc in S.sweep_n(tuple(ns)):
        p = stages.project(rt, cfgs["depth"], arr(sc["means"].float().contiguous()),
                           arr(sc["quats"].float().contiguous()), arr(sc["scales"].float().contiguous()),
                           arr(sc["opacities"].float().contiguous()), arr(sc["viewmats"].float().contiguous()),
                           arr(sc["Ks"].float().contiguous()), sc["width"], sc["height"], 16,
                           near_plane=0.01, far_plane=1e10, eps2d=0.3, radius_clip=0.0, antialiased=False)
        for impl in IMPLS:  # warm-up: builds, JIT, first-touch of the buffers
            _one_call(rt, cfgs[impl], p, sc)
        setups.append((sc, p))
    inputs = [{k: sc[k].float().contiguous() for k in ("means", "quats", "scales", "opacities", "colors",
                                                       "viewmats", "Ks")} for sc, _ in setups]
    times = [{impl: [] for impl in IMPLS} for _ in setups]
    n_isect = [0] * len(setups)
    for r in range(a.rounds):  # every N in every round: a change of load hits all sizes alike
        for j, (sc, p) in enumerate(setups):
            got = {}
            for impl in (IMPLS if r % 2 == 0 else IMPLS[::-1]):
                t, off, keys = _one_call(rt, cfgs[impl], p, sc)
                t.update(_kernel_cpu_call(rt, cfgs[impl], p, sc))
                if a.render:
                    t.update(_render_call(cfgs[impl], sc, inputs[j]))
                times[j][impl].append(t)
                got[impl] = (off, keys, t.pop("_img", None))
            if not all(x is None and y is None or torch.equal(x, y) for x, y in zip(got["tiles"], got["depth"])):
                raise SystemExit(f"N={sc['means'].shape[0]}: the tile lists differ between the implementations")
            n_isect[j] = int(got["depth"][1].numel())
    rows = []
    for j, (sc, _) in enumerate(setups):
        row = {"n": int(sc["means"].shape[0]), "intersections": n_isect[j], "rounds": a.rounds}
        for key in KEYS + (("render",) if a.render else ()):
            med = {impl: statistics.median(t[key] for t in times[j][impl]) for impl in IMPLS}
            row[key] = {"tiles_ms": round(med["tiles"], 3), "depth_ms": round(med["depth"], 3),
                        "ratio": round(med["depth"] / med["tiles"], 4),
                        "ratio_per_round_median": round(statistics.median(
                            d[key] / t[key] for d, t in zip(times[j]["depth"], times[j]["tiles"])), 4)}
        row["kernels_ms"] = {impl: {name: round(statistics.median(t["_kernels"].get(name, 0.0) for t in times[j][impl]), 3)
                                    for name in times[j][impl][0]["_kernels"]} for impl in IMPLS}
        print(json.dumps(row), flush=True)
        rows.append(row)
    if len(rows) > 1:
        x = np.log10([r["n"] for r in rows])
        slopes = {}
        big = np.array([r["n"] >= 100_000 for r in rows])
        for key in KEYS + (("render",) if a.render else ()):
            for impl in IMPLS:
                y = np.log10([max(r[key][f"{impl}_ms"], 1e-6) for r in rows])
                slopes[f"{key}_{impl}_all"] = round(float(np.polyfit(x, y, 1)[0]), 3)
                if big.sum() > 1:
                    slopes[f"{key}_{impl}_from_100k"] = round(float(np.polyfit(x[big], y[big], 1)[0]), 3)
        print(json.dumps({"loglog_slope": slopes}), flush=True)
    if a.tiny:
        print(json.dumps(tiny_calls(a.tiny)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
