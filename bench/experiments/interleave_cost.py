"""The 10k render's forward and backward right after other torch work, as in a training loop or in
``clsplat bench peers``' interleaved rounds (issue 35; bench/notes/engine_peers.md, session 18).

    .venv/bin/python bench/experiments/interleave_cost.py none|compute|alloc|touch|hot

Before each timed call: nothing (``none``), ~100 ms of two-thread elementwise torch work over 16 MB
arrays (``compute``), or that and 400 MB of fresh tensors touched and freed (``alloc``); or, one
thread, a sum over 400 MB made once (``touch``: caches cold, no allocation) or ~100 ms of vector
maths on 1 MB (``hot``: one core busy, the caches not flushed, the other core idle), or the same
while another process spins on the other core until just before the call (``hotspin``: no core
idle; if ``hot``'s cost goes with it, an idle core's wake-up is what the call pays). One
forward + backward of ``random_frustum_scene(10_000)`` (640x352, SH 3), one torch thread for it;
prints the medians of 12 calls. ``MALLOPT=BYTES``: glibc's mmap and trim thresholds raised first.
"""
import os, ctypes
if os.environ.get("MALLOPT"):
    _l = ctypes.CDLL("libc.so.6"); _v = int(os.environ["MALLOPT"]); _l.mallopt(-3, _v); _l.mallopt(-1, 2 * _v)
import subprocess, sys, time
MODES = ("none", "compute", "alloc", "touch", "hot", "hotspin")
mode = sys.argv[1] if len(sys.argv) == 2 else ""
if mode not in MODES:
    sys.exit(f"interleave_cost.py: mode: expected one of {', '.join(MODES)}, got {' '.join(sys.argv[1:])!r}")
import clsplat  # (before torch: its thread and allocator defaults, clsplat/threads.py)
import torch
from clsplat.bench.scenes import random_frustum_scene, render_args
sc = random_frustum_scene(10_000, name="x"); a = render_args(sc)
w = torch.rand(1, sc["height"], sc["width"], 3)
big = torch.rand(4_000_000)
huge = torch.rand(100_000_000) if mode == "touch" else None   # 400 MB, made once
small = torch.rand(250_000)
def other():
    if mode == "none": return
    if mode == "touch":                                            # read 400 MB, one thread, no allocation
        torch.set_num_threads(1); float(huge.sum()); return
    if mode in ("hot", "hotspin"):                                 # ~100 ms of vector maths in cache, one thread
        torch.set_num_threads(1)
        spin = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if mode == "hotspin" else None
        for _ in range(400): small.sin_()
        if spin is not None:
            spin.kill(); spin.wait()
        return
    torch.set_num_threads(2)
    x = big
    for _ in range(20): x = (x * 1.0001 + 0.5).sin()      # ~100+ ms of 2-thread torch work
    if mode == "alloc":
        y = [torch.rand(2_000_000) for _ in range(50)]  # touch ~400 MB
def one():
    torch.set_num_threads(1)
    b = dict(a)
    for k in ("means","quats","scales","opacities","colors"):
        b[k] = a[k].clone().requires_grad_(True)
    t0 = time.perf_counter(); img = clsplat.rasterization(**b)[0]; t1 = time.perf_counter()
    (img * w).sum().backward(); t2 = time.perf_counter()
    return (t1 - t0) * 1e3, (t2 - t1) * 1e3
for _ in range(3): other(); one()
v = []
for _ in range(12):
    other(); v.append(one())
f = sorted(x[0] for x in v)[6]; b = sorted(x[1] for x in v)[6]
print(f"{mode:6s} fwd {f:.1f} bwd {b:.1f} ms")
