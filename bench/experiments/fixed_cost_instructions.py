"""User-space instructions of the calling thread per tiny call, per tree: a load-proof A/B of the
fixed cost (issue 35, deliverable 3).

    POCL_MAX_WORK_GROUP_SIZE=256 .venv/bin/python bench/experiments/fixed_cost_instructions.py \\
        TREE [TREE ...] [--calls 1000] [--rounds 2]

Wall and thread-CPU times of a 2 ms call move by 10-30 % with what other processes run on the
shared cores; the instructions a thread retires do not (two runs of one tree agree to ~0.1 %).
Per tree and round, a child process (``run_tree.py``, so ``TREE`` is a ``git archive`` checkout
with its ``clsplat/kernels``, ``clsplat/bench`` and ``clsplat/models`` symlinks, or ``.`` for this
checkout's installed package) renders percall's ``tiny`` scene (100 Gaussians at 64 x 48, plain
RGB, packed, forward + backward of ``img.sum() + alpha.sum()``) 50 times to warm up, then
``--calls`` times while ``perf stat --per-thread -e instructions:u`` counts; printed: millions of
instructions per call of the calling thread and of the other threads (PoCL's workers: kernels and
their scheduling). Needs ``perf`` with access to the hardware counters (Linux).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

__all__ = ["main"]

_CHILD = r'''
import os, sys, time, torch
import clsplat
from clsplat.bench.scenes import random_frustum_scene, render_args
torch.set_num_threads(1)
args = render_args(random_frustum_scene(100, 64, 48, sh_degree=None, seed=0))
for k in ("means", "quats", "scales", "opacities", "colors"):
    args[k] = args[k].clone().requires_grad_()
def once():
    img, alpha, _ = clsplat.rasterization(**args, packed=True)
    (img.sum() + alpha.sum()).backward()
    for k in ("means", "quats", "scales", "opacities", "colors"):
        args[k].grad = None
for _ in range(50):
    once()
open(sys.argv[2], "w").write(str(os.getpid()))
time.sleep(2.0)  # perf attaches meanwhile
for _ in range(int(sys.argv[1])):
    once()
'''


def _count(tree: str, calls: int, script: str) -> tuple[float, float]:
    """(main-thread, other threads) millions of user instructions per call."""
    here = os.path.dirname(os.path.abspath(__file__))
    with tempfile.TemporaryDirectory() as tmp:
        pid_file = os.path.join(tmp, "pid")
        cmd = [sys.executable, os.path.join(here, "run_tree.py"), tree, script, str(calls), pid_file]
        if tree == ".":
            cmd = [sys.executable, script, str(calls), pid_file]
        child = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
        while not (os.path.exists(pid_file) and os.path.getsize(pid_file)):
            if child.poll() is not None:
                raise SystemExit(f"{tree}: the render process ended early (exit {child.returncode})")
            time.sleep(0.1)
        pid = open(pid_file).read().strip()
        perf = subprocess.Popen(["perf", "stat", "--per-thread", "-x,", "-e", "instructions:u", "-p", pid],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        child.wait()  # (reaped here: perf waits for the process to be gone)
        out = perf.communicate()[1]
    main = other = 0
    for line in out.splitlines():
        f = line.split(",")
        if len(f) > 2 and "instructions" in line and f[1].isdigit():
            if f[0].endswith(f"-{pid}"):
                main += int(f[1])
            else:
                other += int(f[1])
    if not main:
        raise SystemExit(f"{tree}: perf counted nothing (no hardware counters here?)\n{out}")
    return main / calls / 1e6, other / calls / 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trees", nargs="+", help="trees to compare ('.' = this checkout)")
    p.add_argument("--calls", type=int, default=1000, help="counted calls per process (default 1000)")
    p.add_argument("--rounds", type=int, default=2, help="processes per tree, alternating (default 2)")
    a = p.parse_args(argv)
    if a.calls < 1 or a.rounds < 1:
        p.error("--calls, --rounds: expected positive numbers")
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(_CHILD)
    try:
        for r in range(a.rounds):
            for tree in a.trees:
                m, o = _count(tree, a.calls, f.name)
                print(f"{tree} round {r + 1}: calling thread {m:.3f} M instructions/call, other threads {o:.3f}")
    finally:
        os.unlink(f.name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
