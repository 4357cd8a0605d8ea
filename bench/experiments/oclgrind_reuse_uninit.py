"""Oclgrind's uninitialised-value checker after a buffer's memory is reused: a standalone case
(why ``Runtime.device_only_arrays`` is False on Oclgrind; bench/notes/engine_gpu.md).

Three cases, each: write every entry of buffer A and of buffer B with a kernel, release A,
allocate C, then read B with a kernel. Every entry of B was written, so a correct checker
reports nothing; the case (80, 3072, 80) is reported from B's 80th byte on (Oclgrind 21.10,
Debian). Also: a kernel reading a buffer filled by ``clEnqueueFillBuffer`` is reported.

    OCL_ICD_VENDORS=DIR_WITH_oclgrind.icd OCLGRIND_UNINITIALIZED=1 \\
        .venv/bin/python bench/experiments/oclgrind_reuse_uninit.py
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

_SOURCE = """
__kernel void w(__global int *b) { int i = get_global_id(0); b[i] = i; }
__kernel void r(__global const int *b, __global int *o) { int i = get_global_id(0); o[i] = b[i] + 1; }
"""


def main() -> None:
    ctx = cl.Context([cl.get_platforms()[0].get_devices()[0]])
    q = cl.CommandQueue(ctx)
    prg = cl.Program(ctx, _SOURCE).build()
    write, read = cl.Kernel(prg, "w"), cl.Kernel(prg, "r")
    out = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 4 * 1024)
    for sizes in [(3072, 80, 3072), (3072, 80, 4000), (80, 3072, 80)]:
        a = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, sizes[0])
        write(q, (sizes[0] // 4,), None, a)
        b = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, sizes[1])
        write(q, (sizes[1] // 4,), None, b)
        q.finish()
        del a
        c = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, sizes[2])
        print(f"--- reading B after A released and C allocated, sizes (A, B, C) = {sizes}", flush=True)
        read(q, (sizes[1] // 4,), None, b, out)
        q.finish()
        del b, c
    f = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 64)
    cl.enqueue_fill_buffer(q, f, np.zeros(1, np.uint8), 0, 64)
    print("--- reading a filled buffer", flush=True)
    read(q, (16,), None, f, out)
    q.finish()
    print("--- done", flush=True)


if __name__ == "__main__":
    main()
