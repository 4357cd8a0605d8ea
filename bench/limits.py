"""The machine's limits: memory bandwidth (copy kernel) and peak FLOP/s (dense FMA kernel).

Both kernels are tiny OpenCL programs built here, timed with profiling events; the median
over repeats is reported. Bandwidth counts bytes read plus bytes written.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

__all__ = ["measure_limits"]

_SRC = r"""
__kernel void copy16(__global const float16 *src, __global float16 *dst, const int n) {
    const int i = get_global_id(0);
    if (i < n) dst[i] = src[i];
}
/* 8 independent multiply-add chains (mul+add, contracted to FMA with -cl-mad-enable; PoCL 3.0
 * aborts in instruction selection on the fma() builtin for float16) on VT vectors of type T:
 * 8 * lanes * 2 flops per iteration. The lanes are summed into out so that nothing is dead. */
#define FMA_PEAK(NAME, T, VT)                                                                       \
__kernel void NAME(__global T *out, const int iters, const T a, const T b) {                        \
    const int i = get_global_id(0);                                                                 \
    const VT va = (VT)(a), vb = (VT)(b);                                                            \
    VT x0 = (VT)(i * (T)1e-9), x1 = x0 + (T)1e-3, x2 = x0 + (T)2e-3, x3 = x0 + (T)3e-3;               \
    VT x4 = x0 + (T)4e-3, x5 = x0 + (T)5e-3, x6 = x0 + (T)6e-3, x7 = x0 + (T)7e-3;                   \
    for (int k = 0; k < iters; ++k) {                                                               \
        x0 = x0 * va + vb; x1 = x1 * va + vb; x2 = x2 * va + vb; x3 = x3 * va + vb;                 \
        x4 = x4 * va + vb; x5 = x5 * va + vb; x6 = x6 * va + vb; x7 = x7 * va + vb;                 \
    }                                                                                               \
    const VT s = ((x0 + x1) + (x2 + x3)) + ((x4 + x5) + (x6 + x7));                                 \
    T lanes[sizeof(VT) / sizeof(T)];                                                                \
    *(VT *)lanes = s;                                                                               \
    T sum = 0;                                                                                      \
    for (int k = 0; k < (int)(sizeof(VT) / sizeof(T)); ++k) sum += lanes[k];                        \
    out[i] = sum;                                                                                   \
}
FMA_PEAK(fma_peak, float, float16)
#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
FMA_PEAK(fma_peak_f64, double, double8)
#endif
"""


def _time(ev: cl.Event) -> float:
    ev.wait()
    return (ev.profile.end - ev.profile.start) * 1e-9


def measure_limits(rt, repeats: int = 5, copy_mib: int = 256, quick: bool = False) -> dict:
    """{"bandwidth_GBps", "flops_f32_G", "flops_f64_G", ...} for runtime ``rt`` (medians)."""
    if quick:
        copy_mib, repeats = 16, 2
    prog = cl.Program(rt.context, _SRC).build(options=["-cl-std=CL1.2", "-cl-denorms-are-zero", "-cl-mad-enable"])
    mf = cl.mem_flags
    nbytes = copy_mib << 20
    n16 = nbytes // 64
    src = cl.Buffer(rt.context, mf.READ_WRITE, nbytes)
    dst = cl.Buffer(rt.context, mf.READ_WRITE, nbytes)
    cl.enqueue_fill_buffer(rt.queue, src, np.float32(1.0), 0, nbytes).wait()
    cl.enqueue_fill_buffer(rt.queue, dst, np.float32(0.0), 0, nbytes).wait()
    local = 64
    gsz = -(-n16 // local) * local
    copy16, fma32 = cl.Kernel(prog, "copy16"), cl.Kernel(prog, "fma_peak")
    copy_t = [_time(copy16(rt.queue, (gsz,), (local,), src, dst, np.int32(n16))) for _ in range(repeats + 1)][1:]
    bw = 2 * nbytes / np.median(copy_t)

    units = rt.device.max_compute_units
    items = units * 64 * 16
    iters = 256 if quick else 4096
    out = cl.Buffer(rt.context, mf.READ_WRITE, items * 8)
    f32_t = [_time(fma32(rt.queue, (items,), (64,), out, np.int32(iters), np.float32(0.999),
                                 np.float32(1e-4))) for _ in range(repeats + 1)][1:]
    flops32 = items * iters * 8 * 16 * 2 / np.median(f32_t)
    flops64 = None
    if rt.has_fp64:
        f64_t = [_time(cl.Kernel(prog, "fma_peak_f64")(rt.queue, (items,), (64,), out, np.int32(iters), np.float64(0.999),
                                         np.float64(1e-4))) for _ in range(repeats + 1)][1:]
        flops64 = items * iters * 8 * 8 * 2 / np.median(f64_t)
    return {"bandwidth_GBps": float(bw) / 1e9, "copy_MiB": copy_mib, "copy_ms": [t * 1e3 for t in copy_t],
            "flops_f32_G": float(flops32) / 1e9, "flops_f64_G": (float(flops64) / 1e9) if flops64 else None,
            "fma_ms": [t * 1e3 for t in f32_t], "compute_units": units}
