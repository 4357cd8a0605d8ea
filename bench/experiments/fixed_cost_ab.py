"""The fixed cost per call, two trees side by side (issue 35, deliverable 3's must-show).

    POCL_MAX_WORK_GROUP_SIZE=256 .venv/bin/python bench/experiments/fixed_cost_ab.py \\
        --before /tmp/pc_base --after . [--procs 6] [--tiny-calls 40] [--medium-calls 3]

Each of ``--procs`` rounds starts one process per tree (the order flipping every round), with
the tree first on ``PYTHONPATH`` (a tree is a checkout whose ``clsplat/kernels`` and
``clsplat/bench`` resolve, e.g. ``git archive`` of a commit plus the two symlinks). A process
draws percall's ``tiny`` scene (100 Gaussians at 64 x 48) and ``medium`` scene (100k at
640 x 352, bench scene A's size), plain RGB, one camera, warms both up, then alternates
``--tiny-calls`` tiny calls with one medium call ``--medium-calls`` times; every call is
``rasterization()`` then ``(img.sum() + alpha.sum()).backward()`` (the wall time of both,
and the calling thread's CPU time). Per process: the medians, and tiny / medium (the
issue's share, target <= 1 %). Prints one JSON line per process, then per tree the medians
over processes and after / before of the tiny call. The images and gradients of the tiny
call are hashed so that the two trees can be seen to agree bit for bit.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import time

__all__ = ["main"]


def _worker(tiny_calls: int, medium_calls: int) -> dict:
    import torch

    import clsplat
    from clsplat.bench.scenes import random_frustum_scene, render_args

    torch.set_num_threads(1)

    def leaves(n: int, w: int, h: int) -> dict:
        a = render_args(random_frustum_scene(n, w, h, sh_degree=None, seed=0))
        for k in ("means", "quats", "scales", "opacities", "colors"):
            a[k] = a[k].clone().requires_grad_()
        return a

    tiny, medium = leaves(100, 64, 48), leaves(100_000, 640, 352)

    def call(args: dict) -> tuple[float, float, tuple]:
        c0, t0 = time.thread_time(), time.perf_counter()
        img, alpha, _ = clsplat.rasterization(**args)
        (img.sum() + alpha.sum()).backward()
        t1, c1 = time.perf_counter(), time.thread_time()
        grads = tuple(args[k].grad for k in ("means", "quats", "scales", "opacities", "colors"))
        for k in ("means", "quats", "scales", "opacities", "colors"):
            args[k].grad = None
        return (t1 - t0) * 1e3, (c1 - c0) * 1e3, (img.detach(), alpha.detach()) + grads

    for _ in range(10):
        _, _, outs = call(tiny)
    h = hashlib.sha256()
    for t in outs:
        h.update(t.contiguous().numpy().tobytes())
    call(medium)
    tw, tc, mw = [], [], []
    for _ in range(medium_calls):
        for _ in range(tiny_calls):
            w, c, _ = call(tiny)
            tw.append(w)
            tc.append(c)
        mw.append(call(medium)[0])
    t, m = statistics.median(tw), statistics.median(mw)
    return {"tiny_ms": round(t, 3), "tiny_cpu_ms": round(statistics.median(tc), 3),
            "medium_ms": round(m, 1), "share": round(t / m, 5), "tiny_hash": h.hexdigest()[:16]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", help="tree of the baseline")
    ap.add_argument("--after", help="tree of the change")
    ap.add_argument("--procs", type=int, default=6)
    ap.add_argument("--tiny-calls", type=int, default=40)
    ap.add_argument("--medium-calls", type=int, default=3)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        print(json.dumps(_worker(a.tiny_calls, a.medium_calls)))
        return
    trees = {"before": os.path.abspath(a.before), "after": os.path.abspath(a.after)}
    res: dict = {k: [] for k in trees}
    for r in range(a.procs):
        for name in (("before", "after") if r % 2 == 0 else ("after", "before")):
            env = dict(os.environ, PYTHONPATH=trees[name])
            out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker",
                                  "--tiny-calls", str(a.tiny_calls), "--medium-calls",
                                  str(a.medium_calls)], env=env, cwd="/tmp", check=True,
                                 capture_output=True, text=True).stdout
            d = json.loads(out.strip().splitlines()[-1])
            d.update(tree=name, round=r, load=open("/proc/loadavg").read().split()[0])
            print(json.dumps(d), flush=True)
            res[name].append(d)
    summary = {name: {k: statistics.median(d[k] for d in v)
                      for k in ("tiny_ms", "tiny_cpu_ms", "medium_ms", "share")}
               for name, v in res.items()}
    summary["after/before tiny_ms"] = round(summary["after"]["tiny_ms"] / summary["before"]["tiny_ms"], 3)
    summary["after/before tiny_cpu_ms"] = round(
        summary["after"]["tiny_cpu_ms"] / summary["before"]["tiny_cpu_ms"], 3)
    summary["hashes equal"] = len({d["tiny_hash"] for v in res.values() for d in v}) == 1
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
