"""Depth sort once (``RenderConfig.sort_impl="depth"``) against the per-tile sort ("tiles"),
interleaved in one process: the sort stage's table of bench/notes/engine_render_plan.md §5.

    python bench/experiments/depth_sort_ab.py [--ns 10000,100000,300000,1000000] [--rounds 7]

For each N, one scene of :func:`clsplat.bench.scenes.sweep_n` (one 640x352 camera, Gaussians
of scene A's sizes) is projected once; then ``--rounds`` rounds each call
:func:`clsplat.stages.tile_lists` once per implementation, the order flipping every round,
after one warm-up call of each. Per call: the device milliseconds of each stage from the
profiling events (the "sort" stage: every event whose name starts with ``sort``, i.e.
``sort_serial`` / ``sort_local`` / ``sort_merge`` against ``sort_depth``; "bin": ``bin_*``)
("stage": both), the wall time of the whole call with the queue drained before and after
(it includes the host's scans and waits, which no event holds) and the process's CPU time
over the call (all threads, PoCL's included: the work done, which waiting for a core on a
loaded machine does not stretch). The two implementations' tile lists must be equal, key for
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
KEYS = ("sort", "bin", "stage", "wall", "cpu")


def _one_call(rt, cfg, p, scene) -> tuple[dict, torch.Tensor, torch.Tensor]:
    """Wall ms, device ms per stage group, and the tile lists of one :func:`tile_lists` call."""
    events: list = []
    rt.finish()
    c0, t0 = time.process_time(), time.perf_counter()
    off, keys = stages.tile_lists(rt, cfg, p.rects, p.depths, scene["width"], scene["height"], 16,
                                  events=events)
    rt.finish()
    wall, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
    t = {"wall": wall, "cpu": cpu, "sort": 0.0, "bin": 0.0}
    for name, ev in events:
        t["sort" if name.startswith("sort") else "bin"] += event_ms(ev)
    t["stage"] = t["sort"] + t["bin"]
    return t, off.host().clone(), keys.host().clone()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python bench/experiments/depth_sort_ab.py",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--ns", default="10000,100000,300000,1000000")
    ap.add_argument("--rounds", type=int, default=7)
    a = ap.parse_args(argv)
    ns = [int(x) for x in a.ns.split(",")]
    if a.rounds < 1 or any(n < 1 for n in ns):
        ap.error("--rounds and --ns must be positive")
    rt = get_runtime(None)
    cfgs = {impl: clsplat.RenderConfig(precision="float32", sort_impl=impl) for impl in IMPLS}
    rows = []
    for sc in S.sweep_n(tuple(ns)):
        arr = rt.array
        p = stages.project(rt, cfgs["depth"], arr(sc["means"].float().contiguous()),
                           arr(sc["quats"].float().contiguous()), arr(sc["scales"].float().contiguous()),
                           arr(sc["opacities"].float().contiguous()), arr(sc["viewmats"].float().contiguous()),
                           arr(sc["Ks"].float().contiguous()), sc["width"], sc["height"], 16,
                           near_plane=0.01, far_plane=1e10, eps2d=0.3, radius_clip=0.0, antialiased=False)
        times = {impl: [] for impl in IMPLS}
        for impl in IMPLS:  # warm-up: builds, JIT, first-touch of the buffers
            _one_call(rt, cfgs[impl], p, sc)
        for r in range(a.rounds):
            got = {}
            for impl in (IMPLS if r % 2 == 0 else IMPLS[::-1]):
                t, off, keys = _one_call(rt, cfgs[impl], p, sc)
                times[impl].append(t)
                got[impl] = (off, keys)
            if not (torch.equal(got["tiles"][0], got["depth"][0]) and torch.equal(got["tiles"][1], got["depth"][1])):
                raise SystemExit(f"N={sc['means'].shape[0]}: the tile lists differ between the implementations")
        row = {"n": int(sc["means"].shape[0]), "intersections": int(got["depth"][1].numel()), "rounds": a.rounds}
        for key in KEYS:
            med = {impl: statistics.median(t[key] for t in times[impl]) for impl in IMPLS}
            row[key] = {"tiles_ms": round(med["tiles"], 3), "depth_ms": round(med["depth"], 3),
                        "ratio": round(med["depth"] / med["tiles"], 4),
                        "ratio_per_round_median": round(statistics.median(
                            d[key] / t[key] for d, t in zip(times["depth"], times["tiles"])), 4)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    if len(rows) > 1:
        x = np.log10([r["n"] for r in rows])
        slopes = {}
        big = np.array([r["n"] >= 100_000 for r in rows])
        for key in KEYS:
            for impl in IMPLS:
                y = np.log10([max(r[key][f"{impl}_ms"], 1e-6) for r in rows])
                slopes[f"{key}_{impl}_all"] = round(float(np.polyfit(x, y, 1)[0]), 3)
                if big.sum() > 1:
                    slopes[f"{key}_{impl}_from_100k"] = round(float(np.polyfit(x[big], y[big], 1)[0]), 3)
        print(json.dumps({"loglog_slope": slopes}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
