"""Where the tiny call's calling-thread CPU goes, part by part (issue 35, deliverable 3).

    POCL_MAX_WORK_GROUP_SIZE=256 .venv/bin/python bench/experiments/fixed_cost_parts.py \\
        [--calls 2000] [--unpacked]

Percall's ``tiny`` scene (100 Gaussians at 64 x 48, plain RGB, one camera): ``rasterization()``
then ``(img.sum() + alpha.sum()).backward()``, ``--calls`` times after 20 warm-ups. The runtime's
own methods (``Runtime.empty``, ``array``, ``staged``, ``finish``) are wrapped to add up the
calling thread's CPU time (``time.thread_time_ns``) and wall time they take, and ``enqueue`` is
split into pyopencl's argument setting (``Kernel.set_args``, with the scalar dtypes the runtime
declared) and the OpenCL enqueue itself (``clEnqueueNDRangeKernel``), per kernel. The wrappers add
~1 us per call of their own; nested parts (``staged`` calls ``empty``) are counted in both.
Prints one line per part: calls per render, thread CPU and wall per render.
"""
from __future__ import annotations

import argparse
import collections
import time

__all__ = ["main"]

_PARTS = ("empty", "array", "staged", "finish")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--calls", type=int, default=2000, help="timed calls (default 2000)")
    p.add_argument("--unpacked", action="store_true", help="packed=False (default: packed)")
    a = p.parse_args(argv)
    if a.calls < 1:
        p.error(f"--calls: expected a positive number, got {a.calls}")

    import numpy as np
    import pyopencl as cl
    import torch

    import clsplat
    from clsplat import runtime as R
    from clsplat.bench.scenes import random_frustum_scene, render_args

    acc: dict = collections.defaultdict(lambda: [0, 0, 0])  # thread ns, wall ns, calls

    def wrap(name: str) -> None:
        orig = getattr(R.Runtime, name)

        def timed(self, *args, **kw):
            c, t = time.thread_time_ns(), time.perf_counter_ns()
            out = orig(self, *args, **kw)
            x = acc[name]
            x[0] += time.thread_time_ns() - c
            x[1] += time.perf_counter_ns() - t
            x[2] += 1
            return out
        setattr(R.Runtime, name, timed)

    def enqueue(self, kernel, global_size, local_size, *args):
        sig = tuple(map(type, args))  # as Runtime.enqueue: the scalar dtypes declared once
        if self._arg_dtypes.get(kernel.int_ptr) != sig:
            kernel.set_scalar_arg_dtypes([np.dtype(t) if issubclass(t, np.generic) else None for t in sig])
            self._arg_dtypes[kernel.int_ptr] = sig
        c0 = time.thread_time_ns()
        kernel.set_args(*args)
        c1 = time.thread_time_ns()
        self._in_flight.append(args)
        self.launches += 1
        ev = cl.enqueue_nd_range_kernel(self.queue, kernel, (global_size,), (local_size,))
        c2 = time.thread_time_ns()
        for key, ns in ((f"set_args {kernel.function_name}", c1 - c0), (f"enqueue {kernel.function_name}", c2 - c1)):
            x = acc[key]
            x[0] += ns
            x[2] += 1
        return ev

    for name in _PARTS:
        wrap(name)
    R.Runtime.enqueue = enqueue

    torch.set_num_threads(1)
    args = render_args(random_frustum_scene(100, 64, 48, sh_degree=None, seed=0))
    for k in ("means", "quats", "scales", "opacities", "colors"):
        args[k] = args[k].clone().requires_grad_()

    def once() -> None:
        img, alpha, _ = clsplat.rasterization(**args, packed=not a.unpacked)
        (img.sum() + alpha.sum()).backward()
        for k in ("means", "quats", "scales", "opacities", "colors"):
            args[k].grad = None

    for _ in range(20):
        once()
    acc.clear()
    c, t = time.thread_time_ns(), time.perf_counter_ns()
    for _ in range(a.calls):
        once()
    n = a.calls
    print(f"whole call: thread CPU {(time.thread_time_ns() - c) / n / 1e6:.3f} ms, "
          f"wall {(time.perf_counter_ns() - t) / n / 1e6:.3f} ms")
    for key, (cpu, wall, cnt) in sorted(acc.items()):
        w = f", wall {wall / n / 1e6:.3f} ms" if wall else ""
        print(f"{key}: {cnt / n:.1f} per call, thread CPU {cpu / n / 1e6:.3f} ms{w}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
