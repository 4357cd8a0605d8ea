"""PoCL's kernel-cache race between processes, and what a retried build does with it (the reason
for ``clsplat.runtime.BUILD_RETRIES``; bench/notes/hardening.md, "PoCL's kernel cache across
processes").

PoCL 3.0 keeps built programs under ``POCL_CACHE_DIR`` (``~/.cache/pocl``) and its writes there are
not safe when several processes build the same program at once (pocl/pocl#1480): a build then
fails with ``BUILD_PROGRAM_FAILURE`` and no compiler diagnostic. ``--procs`` processes start at
one instant and build the same ``--programs`` small programs in the same order into one empty
cache; each counts the builds that failed the first time and those that still failed after
``--retries`` more tries (as ``Runtime.program`` makes them on PoCL).

    .venv/bin/python bench/experiments/pocl_cache_race.py [--procs 6] [--programs 150] [--retries 2] [--rounds 2]

Prints one line per round: first-try failures and failures left after the retries, over all builds.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

_CHILD = r'''
import sys, time
import pyopencl as cl
start, programs, retries = float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
dev = [d for p in cl.get_platforms() if "portable" in p.name.lower() for d in p.get_devices()][0]
ctx = cl.Context([dev])
while time.time() < start:
    time.sleep(0.001)
first = left = 0
for i in range(programs):
    src = "__kernel void f(__global int *a) { a[get_global_id(0)] = %d; }" % i
    for attempt in range(retries + 1):
        try:
            cl.Program(ctx, src).build()
            break
        except (cl.RuntimeError, cl.LogicError):
            first += attempt == 0
    else:
        left += 1
print(first, left)
'''


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--procs", type=int, default=6)
    ap.add_argument("--programs", type=int, default=150)
    ap.add_argument("--retries", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    a = ap.parse_args(argv)
    for name in ("procs", "programs", "rounds"):
        if getattr(a, name) < 1:
            ap.error(f"--{name} must be at least 1")
    if a.retries < 0:
        ap.error("--retries must be 0 or more")
    for r in range(a.rounds):
        with tempfile.TemporaryDirectory() as cache:
            # pyopencl's own binary cache off, so that every build reaches PoCL's
            env = dict(os.environ, POCL_CACHE_DIR=cache, PYOPENCL_NO_CACHE="1")
            start = f"{time.time() + 5.0:.3f}"   # after every interpreter has imported pyopencl
            procs = [subprocess.Popen([sys.executable, "-c", _CHILD, start, str(a.programs), str(a.retries)],
                                      env=env, stdout=subprocess.PIPE, text=True) for _ in range(a.procs)]
            counts = [tuple(map(int, p.communicate()[0].split())) for p in procs]
        builds = a.procs * a.programs
        print(f"round {r}: {builds} builds by {a.procs} processes: {sum(c[0] for c in counts)} failed the "
              f"first time, {sum(c[1] for c in counts)} still failed after {a.retries} retries")
    return 0


if __name__ == "__main__":
    sys.exit(main())
