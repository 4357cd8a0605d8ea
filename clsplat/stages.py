"""Thin drivers, one per kernel stage: they specialise, launch and return device arrays.

Shapes use C cameras, N Gaussians, T = tiles_x * tiles_y tiles per camera, M intersections
(camera, Gaussian, tile) and CH composited channels. Every driver takes ``events``, a list to
which it appends ``(stage, cl.Event)`` pairs for profiling (the bench reads them).
Nothing here validates user input: :mod:`clsplat.validate` has done that.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import torch

from . import constants as K
from .config import RenderConfig
from .plan import check_intersection_memory
from .runtime import DeviceArray, Runtime

__all__ = ["Projection", "project", "sh_colors", "bin_tiles", "sort_segments", "depth_tiles",
           "tile_lists", "tile_ranges", "EarlyTiles", "early_tile_lists", "EARLY_TILES_MAX",
           "composite", "LOCAL_1D"]

LOCAL_1D = 64  # work-group size of the per-Gaussian stages; any size works, 64 suits both kinds


def _np_real(cfg: RenderConfig):
    return np.float64 if cfg.precision == "float64" else np.float32


def _record(events, name: str, ev: cl.Event) -> None:
    if events is not None:
        events.append((name, ev))


@dataclass
class Projection:
    """Per (camera, Gaussian) results of :func:`project`.

    means2d [C,N,2], conics [C,N,3], depths [C,N], radii [C,N,2] int32 (0 = culled),
    opacities [C,N] (times the antialiasing compensation when enabled), rects [C,N,4] int32
    tile rectangle (x0, y0, x1, y1), half-open, extents [C,N,2] screen distances in x and y
    beyond which the sample's alpha is below ALPHA_MIN (-1: nowhere above it), tiles [C,N]
    int32 the tiles in each rectangle (0 = culled), or None below :data:`TILE_COUNTS_MIN_PAIRS`.
    """

    means2d: DeviceArray
    conics: DeviceArray
    depths: DeviceArray
    radii: DeviceArray
    opacities: DeviceArray
    rects: DeviceArray
    extents: DeviceArray
    tiles: DeviceArray | None


#: pairs (C * N) from which the projection also writes each pair's tile count (Projection.tiles):
#: summing it beats reading the rectangles from ~1e5 pairs on (scene B's 1.95M: 1 against 20 ms),
#: while below, one more array per call is a share of a small call's fixed cost
TILE_COUNTS_MIN_PAIRS = 1 << 15


def project(rt: Runtime, cfg: RenderConfig, means: DeviceArray, quats: DeviceArray,
            scales: DeviceArray, opacities: DeviceArray, viewmats: DeviceArray, Ks: DeviceArray,
            width: int, height: int, tile_size: int, *, near_plane: float, far_plane: float,
            eps2d: float, radius_clip: float, antialiased: bool,
            events: list | None = None) -> Projection:
    """World to screen for every (camera, Gaussian).

    means [N,3], quats [N,4] wxyz, scales [N,3], opacities [N], viewmats [C,4,4], Ks [C,3,3].
    """
    C, N = viewmats.tensor.shape[0], means.tensor.shape[0]
    dt = cfg.dtype
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    # the kernel writes every entry, a culled pair's as zeros: no host fill
    e = lambda shape, t=dt: rt.empty(shape, t, zero=False)  # noqa: E731
    out = Projection(
        means2d=e((C, N, 2)), conics=e((C, N, 3)), depths=e((C, N)), radii=e((C, N, 2), torch.int32),
        opacities=e((C, N)), rects=e((C, N, 4), torch.int32), extents=e((C, N, 2)),
        tiles=e((C, N), torch.int32) if C * N >= TILE_COUNTS_MIN_PAIRS else None)
    k = rt.kernel("project", "project", cfg.defines(tile_size) | {
        "ANTIALIASED": antialiased, "CLS_POCL_CPU": rt.is_pocl_cpu,
        "TILE_COUNTS": out.tiles is not None}, cfg.fast_math)
    R = _np_real(cfg)
    _record(events, "project", rt.launch(
        k, C * N, LOCAL_1D, np.int32(C), np.int32(N), means.buffer, quats.buffer, scales.buffer,
        opacities.buffer, viewmats.buffer, Ks.buffer, np.int32(width), np.int32(height),
        R(near_plane), R(far_plane), R(eps2d), R(radius_clip), np.int32(tiles_x), np.int32(tiles_y),
        out.means2d.buffer, out.conics.buffer, out.depths.buffer, out.radii.buffer,
        out.opacities.buffer, out.rects.buffer, out.extents.buffer,
        (out.rects if out.tiles is None else out.tiles).buffer))  # (without TILE_COUNTS the last argument is not read)
    return out


def sh_colors(rt: Runtime, cfg: RenderConfig, means: DeviceArray, viewmats: DeviceArray,
              coeffs: DeviceArray, radii: DeviceArray, sh_degree: int,
              events: list | None = None) -> DeviceArray:
    """Colours [C,N,3] from SH coefficients [N,K,3] (K >= (sh_degree+1)^2) of visible pairs.

    radii [C,N,2]: culled pairs (radii 0) are skipped and keep colour 0.
    """
    C, N = viewmats.tensor.shape[0], means.tensor.shape[0]
    colors = rt.empty((C, N, 3), cfg.dtype, zero=False)  # every entry written (culled: zeros)
    defines = {"REAL_DOUBLE": cfg.precision == "float64", "SH_DEGREE": sh_degree,
               "SH_COEFFS": coeffs.tensor.shape[1]}
    k = rt.kernel("sh", "sh_colors", defines, cfg.fast_math)
    _record(events, "sh", rt.launch(k, C * N, LOCAL_1D, np.int32(C), np.int32(N), means.buffer,
                                    viewmats.buffer, coeffs.buffer, radii.buffer, colors.buffer))
    return colors


def _host_scan(rt: Runtime) -> bool:
    """Whether the tile-offset scan runs on the host: ``CLSPLAT_HOST_SCAN`` 1 (always; for tools
    that cannot run pyopencl's scan, such as Oclgrind's uninitialised-memory checker) or 0
    (never), else where the device computes in host memory (PoCL's CPU device). There the
    counts are in the tensor's own memory once the queue finishes, the offsets are read back
    right after the scan anyway, and a host prefix sum over one count per tile costs
    microseconds, against pyopencl's scan: three launches, their wake-ups and its Python glue,
    a sixth of a small render's fixed cost (bench/RESULTS.md, "Issue 21")."""
    mode = os.environ.get("CLSPLAT_HOST_SCAN", "")
    if mode not in ("", "0", "1"):
        raise ValueError(f"CLSPLAT_HOST_SCAN: expected 0, 1 or unset, got {mode!r}")
    return mode == "1" or (mode != "0" and rt.computes_in_host_memory)


def _scan_exclusive(rt: Runtime, src: DeviceArray, dst: DeviceArray, events) -> None:
    """dst = exclusive prefix sum of src (int32), on the host or by pyopencl's scan on the
    device (see :func:`_host_scan`). Host scan: dst's tensor holds the result on return."""
    n = src.tensor.numel()
    rt.launches += 1  # writes dst (see Runtime.launches)
    if _host_scan(rt):
        c = src.host().to(torch.int64)
        ex = (torch.cumsum(c, 0) - c).to(torch.int32)
        if dst.zero_copy and rt.computes_in_host_memory:  # the tensor is the device's memory
            dst.tensor.copy_(ex)
            dst.synced_at = rt.launches
        else:
            cl.enqueue_copy(rt.queue, dst.buffer, ex.contiguous().numpy(), is_blocking=True)
        return
    a = cl_array.Array(rt.queue, (n,), np.int32, data=src.buffer)
    b = cl_array.Array(rt.queue, (n,), np.int32, data=dst.buffer)
    rt.hold(src.buffer, dst.buffer)
    _record(events, "scan", rt.checked_scan_int32()(a, b, queue=rt.queue))


def _intersections(rt: Runtime, rects: DeviceArray, per_intersection: int, reserve: int,
                   per_pair: int = 0, per_touching: int = 0, unused: int = 0,
                   pair_tiles: list | None = None, tiles: DeviceArray | None = None) -> tuple[int, int]:
    """(intersections M, pairs that touch a tile) from rects [C,N,4], after the memory checks.

    The exact total from the rectangles, in int64 and before any per-tile work: an int32
    scan would wrap silently, and counting ~1e9 intersections only to refuse them is slow.
    ``tiles``: the projection's tile count per pair ([C,N] int32, :class:`Projection`), summed
    instead of the rectangles (one contiguous 4-byte read a pair against four strided ones and
    their temporaries: 1.0 against 20 ms on scene B's 1.95M pairs). In numpy: torch's
    element-wise ops over 1M pairs cost 10-100 ms of CPU time on the 2-core VM (its threads
    spin), numpy's one thread a few. ``per_pair`` bytes per pair and ``per_touching`` per pair
    that touches a tile (the depth sort's arrays), less ``unused`` of the ``per_intersection``
    bytes per intersection (the per-tile sort's scratch, which the depth sort does not allocate),
    are checked with them, spread over the intersections. ``pair_tiles``: a list that receives
    each pair's tile count [C*N] int32 (``tiles`` itself where given, else a numpy array), from
    which :func:`isect_offsets` needs no second pass over the rects.
    """
    if tiles is not None:
        t = tiles.host().reshape(-1).numpy()
        total, n = int(t.sum(dtype=np.int64)), int(np.count_nonzero(t))
        counts, pairs = tiles, t.size
    else:
        r = rects.host().reshape(-1, 4).numpy()
        w, h = r[:, 2] - r[:, 0], r[:, 3] - r[:, 1]
        total = int(np.dot(w.astype(np.int64), h))
        n = int(np.count_nonzero((w > 0) & (h > 0)))
        counts, pairs = (w * h if pair_tiles is not None else None), len(r)
    if total >= 2**31 - 1:
        raise ValueError(f"means, scales: {total} (camera, Gaussian, tile) intersections exceed the "
                         "int32 index range; render fewer cameras, fewer or smaller Gaussians per call")
    if pair_tiles is not None:
        pair_tiles.append(counts)  # (int32: the total, their sum, is below 2^31 - 1)
    extra = max(0, per_pair * pairs + per_touching * n - unused * total)
    check_intersection_memory(rt, total, per_intersection + (-(-extra // total) if total else 0), reserve)
    rt.check_memory(total * 8, f"means, scales: the keys of {total} (camera, Gaussian, tile) "
                    "intersections (render fewer cameras, fewer or smaller Gaussians per call)")
    return total, n


def bin_tiles(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, depths: DeviceArray,
              width: int, height: int, tile_size: int,
              events: list | None = None, per_intersection: int = 16,
              reserve: int = 0, pair_tiles: list | None = None,
              tiles: DeviceArray | None = None) -> tuple[DeviceArray, DeviceArray]:
    """Count, scan and scatter (camera, Gaussian, tile) intersections into tile segments.

    rects [C,N,4] int32 tile rectangles and depths [C,N] from :func:`project`. Before any
    per-tile work, the intersections' ``per_intersection`` bytes each (keys, the sort's scratch,
    the backward's slots: :func:`clsplat.plan.intersection_bytes`) and ``reserve`` bytes still
    to come (the pixel buffers) are checked against what may be allocated.

    Returns ``tile_offsets`` [C*T+1] int32 (segment of tile t is offsets[t]:offsets[t+1]) and
    ``keys`` [M] int64 holding ulong keys (float32 depth bits << 32 | c*N+g), unsorted within
    each segment. The offsets have been read back: their tensor holds them.
    """
    C, N = depths.tensor.shape
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    tpc = tiles_x * tiles_y
    counts = rt.empty((C * tpc + 1,), torch.int32)
    offsets = rt.empty((C * tpc + 1,), torch.int32)
    defines = cfg.defines(tile_size)
    total, _ = _intersections(rt, rects, per_intersection, reserve, pair_tiles=pair_tiles, tiles=tiles)
    common = (np.int32(C * N), np.int32(tiles_x), np.int32(tpc), np.int32(N), rects.buffer)
    _record(events, "bin_count", rt.launch(rt.kernel("bin", "count_tiles", defines), C * N, LOCAL_1D,
                                           *common, counts.buffer))
    _scan_exclusive(rt, counts, offsets, events)
    check_tile_offsets(offsets.host(), total)
    keys = rt.empty((total,), torch.int64, zero=False)
    cursor = rt.empty((C * tpc,), torch.int32)
    if total:
        _record(events, "bin_scatter", rt.launch(
            rt.kernel("bin", "scatter_keys", defines), C * N, LOCAL_1D, *common,
            depths.buffer, offsets.buffer, cursor.buffer, keys.buffer))
    return offsets, keys


def check_tile_offsets(off: torch.Tensor, total: int) -> None:
    """Refuse tile offsets [C*T+1] that are not a non-decreasing run from 0 to ``total``:
    every later kernel indexes the intersection list with them, so a faulty scan (a driver
    bug, a miscompiled kernel) would make them read and write out of bounds."""
    o = off.numpy()  # numpy: a few us against ~40 for torch's ops; compared, never subtracted
    if o.size == 0 or int(o[0]) != 0 or int(o[-1]) != total or bool((o[1:] < o[:-1]).any()):
        raise RuntimeError(
            f"bin: the device's prefix scan returned inconsistent tile offsets (first "
            f"{int(o[0]) if o.size else None}, last {int(o[-1]) if o.size else None}, "
            f"expected 0 .. {total}, non-decreasing); the OpenCL implementation miscomputed "
            "pyopencl's scan, refusing to index with them")


def _sort_local_size(rt: Runtime, cfg: RenderConfig) -> tuple[int, int]:
    """(keys per local sort, work-group size) that fit this device."""
    budget = rt.local_mem // 2 // 8  # half the local memory, 8-byte keys
    sl = cfg.sort_local or min(4096, 1 << (budget.bit_length() - 1))
    return sl, max(1, min(sl // 2, rt.max_group, 256))


def sort_segments(rt: Runtime, cfg: RenderConfig, keys: DeviceArray, offsets: DeviceArray,
                  events: list | None = None, host_offsets: torch.Tensor | None = None) -> None:
    """Sort each tile segment of ``keys`` [M] ascending, in place.

    Serial layout (CPUs by default): one work-item merge-sorts a whole segment.
    Bitonic layout (GPUs): segments up to SORT_LOCAL keys are sorted by one work-group in
    local memory; longer ones are cut into SORT_LOCAL chunks, sorted likewise, then merged by
    ``merge_runs`` passes until one run remains. ``host_offsets``: the offsets as already
    read back (saves a wait on the queue), else they are read here.
    """
    M = keys.tensor.numel()
    if M < 2:
        return
    off = (offsets.host() if host_offsets is None else host_offsets).numpy().astype(np.int64)
    starts, lens = off[:-1], np.diff(off)
    seg = lens >= 2
    starts, lens = starts[seg], lens[seg]
    if len(lens) == 0:
        return
    if _sort_serial(rt, cfg):
        tmp = rt.empty((M,), torch.int64, zero=False)
        k = rt.kernel("sort", "sort_serial", {"SORT_LOCAL": 2})
        _record(events, "sort_serial", rt.launch(
            k, len(lens), 16, keys.buffer, tmp.buffer,
            rt.array(torch.from_numpy(starts.astype(np.int32))).buffer,
            rt.array(torch.from_numpy(lens.astype(np.int32))).buffer, np.int32(len(lens))))
        return
    sl, ls = _sort_local_size(rt, cfg)
    n_chunks = -(-lens // sl)
    chunk_seg = np.repeat(np.arange(len(lens)), n_chunks)
    chunk_idx = np.arange(len(chunk_seg)) - np.repeat(np.cumsum(n_chunks) - n_chunks, n_chunks)
    c_start = starts[chunk_seg] + chunk_idx * sl
    c_len = np.minimum(sl, lens[chunk_seg] - chunk_idx * sl)
    c_start_a = rt.array(torch.from_numpy(c_start.astype(np.int32)))
    c_len_a = rt.array(torch.from_numpy(c_len.astype(np.int32)))
    k = rt.kernel("sort", "sort_local", {"SORT_LOCAL": sl})
    ev = rt.enqueue(k, len(c_start) * ls, ls, keys.buffer, c_start_a.buffer, c_len_a.buffer)
    _record(events, "sort_local", ev)
    big = lens > sl
    if not big.any():
        return
    b_start, b_len = starts[big], lens[big]
    prefix = np.concatenate([[0], np.cumsum(b_len)])
    total = int(prefix[-1])
    b_start_a = rt.array(torch.from_numpy(b_start.astype(np.int32)))
    prefix_a = rt.array(torch.from_numpy(prefix.astype(np.int32)))
    tmp = rt.empty((M,), torch.int64, zero=False)
    merge = rt.kernel("sort", "merge_runs", {"SORT_LOCAL": sl})
    src, dst = keys, tmp
    width = sl
    widths = []
    while width < int(b_len.max()):
        widths.append(width)
        width *= 2
    if len(widths) % 2:  # one extra pass that only copies, so the result lands in ``keys``
        widths.append(width)
    for w in widths:
        _record(events, "sort_merge", rt.launch(
            merge, total, 256 if rt.max_group >= 256 else rt.max_group, src.buffer, dst.buffer,
            np.int32(total), b_start_a.buffer, prefix_a.buffer, np.int32(len(b_len)), np.int32(w)))
        src, dst = dst, src


#: Bits of the depth sorted per pass of kernels/order.cl's radix sort (a divisor of 32): 8
#: keeps a chunk's 256 counters in a CPU core's first-level cache and takes 4 passes over the
#: 32 depth bits; 11 bits would save a pass but zero, scan and scatter through 8x the counters.
ORDER_RADIX_BITS = 8
#: Serial layout (CPUs): chunks per compute unit, so that PoCL's threads, which take whole
#: work-groups (one chunk each), balance chunks of uneven cost (pairs touch 1 to many tiles).
ORDER_CHUNKS_PER_UNIT = 4
#: Serial layout: keys per chunk at least, so that a chunk's walk outweighs the 2^RADIX_BITS
#: counters it zeroes and the scan it adds.
ORDER_MIN_CHUNK = 2048
#: GPU layout: keys per work-item; the radix counters then number about as many as the keys.
ORDER_GPU_CHUNK = 256
#: Serial layout: each scatter work-item scans the counters for itself (kernels/order.cl's
#: own_positions) while all of them together read at most this many counters (bins x
#: chunks^2: the default 8 chunks of 2 cores read 56k for 880 tiles, 64 chunks of 16 cores
#: 3.6M, a millisecond or more); beyond it
#: (many cores' chunks, many tiles) one scan launch is cheaper.
ORDER_OWN_SCAN_MAX = 1 << 20
#: Bits per tile coordinate in kernels/order.cl's packed rectangles (two coordinates a 32-bit
#: word): x up to tiles_x, y up to C * tiles_y must fit (ORDER_PACK_MAX); beyond it (over a
#: million pixels across at tile 16, or C x rows of tiles over 65535) the per-tile sort runs
#: instead; it gives the same lists.
ORDER_PACK_BITS = 16
ORDER_PACK_MAX = (1 << ORDER_PACK_BITS) - 1
#: Serial layout: up to this many pairs that touch a tile, the whole stage runs in one
#: work-item (kernels/order.cl's order_small): one launch instead of two per pass (count,
#: scatter), the gather's and the placement's. Measured on the loaded 2-core VM (medians of 9
#: calls of the stage alone, wall): at 10k pairs 0.8 ms against the chunked passes' 1.6 ms and
#: the per-tile sort's 1.8 ms; at 30k 2.0 against 2.8 ms; at 100k 12.8 against 6.1 ms.
ORDER_SMALL = 1 << 15
#: Small calls: up to this many (camera, Gaussian, tile) slots, C * N pairs times one camera's
#: tiles (the most intersections the call can have), :func:`early_tile_lists` builds the tile
#: lists right after the projection, into keys of that size, before the host has read the
#: rectangles back: the forward then waits on the queue once for both (and never between the
#: sort and the compositor), where it waited after each. 64k slots keep the keys (512 KiB)
#: within the array pool (:data:`clsplat.runtime.POOL_ARRAY_BYTES`), so their memory needs no
#: check; the tiny call of ``clsplat bench percall`` (100 Gaussians, 64 x 48) has 1200.
EARLY_TILES_MAX = 1 << 16


def _order_chunks(rt: Runtime, cfg: RenderConfig, n: int, n_bins: int, total: int) -> int:
    """Chunks (work-items) of a kernels/order.cl pass over ``n`` elements into ``n_bins``
    bins with ``total`` outputs: ``cfg.sort_chunks`` if set, else by layout (a few long
    chunks per compute unit on CPUs, :data:`ORDER_GPU_CHUNK` keys each on GPUs), never more
    counters (bins x chunks) than outputs plus one chunk's, nor more chunks than elements."""
    if cfg.sort_chunks is not None:
        chunks = cfg.sort_chunks
    elif _sort_serial(rt, cfg):
        chunks = min(int(rt.device.max_compute_units) * ORDER_CHUNKS_PER_UNIT, -(-n // ORDER_MIN_CHUNK))
        chunks = min(chunks, max(1, total // n_bins))
    else:
        chunks = min(-(-n // ORDER_GPU_CHUNK), max(1, total // n_bins))
    chunks = max(1, min(chunks, n))
    if n_bins * chunks >= 2**31 - 1:  # the counters are indexed in int32
        chunks = max(1, (2**31 - 2) // n_bins)
    return chunks


def sort_by_depth(rt: Runtime, cfg: RenderConfig) -> bool:
    """Whether the tile lists come from one depth sort of all pairs (kernels/order.cl) rather
    than from binning and a sort per tile (bin.cl + sort.cl): ``RenderConfig.sort_impl``; None:
    "depth" on CPU devices (PoCL, Oclgrind), where it was measured the faster at 1M Gaussians
    (bench/notes/engine_cpu_speed.md), and "tiles" on GPUs, whose counting passes over a few
    chunks leave most of the device idle: on an NVIDIA H200 the per-tile path's kernels took
    0.2 ms against 3.2 ms on scene A (bench/notes/engine_gpu.md)."""
    return (cfg.sort_impl or ("depth" if rt.is_cpu else "tiles")) == "depth"


def _sort_serial(rt: Runtime, cfg: RenderConfig) -> bool:
    """The serial (CPU) layout of the sort stages, else the GPU one (``cfg.sort_layout``)."""
    return (cfg.sort_layout or ("serial" if rt.is_cpu else "bitonic")) == "serial"


def _counting_pass(rt: Runtime, cfg: RenderConfig, k: Callable[[str], cl.Kernel], count: str,
                   scatter: str, n_chunks: int, n_bins: int, head: tuple, count_args: tuple,
                   scatter_args: tuple, name: str, events,
                   after_scan: Callable[[DeviceArray], None] | None = None) -> None:
    """One stable counting pass of kernels/order.cl, all on the device: count (``head +
    count_args + (hist,)``), then scatter (``head + scatter_args`` with the own-scan flag, the
    counts and the positions where ``"own"``, ``"hist"`` and ``"pos"`` stand). Serial layout
    with few chunks (:data:`ORDER_OWN_SCAN_MAX`): each scatter work-item scans for itself;
    else a scan launch in between (pyopencl's on bin-major counters, scan_counters on
    chunk-major ones or where pyopencl's cannot run, see :func:`_host_scan`), then
    ``after_scan(pos)``."""
    serial = _sort_serial(rt, cfg)
    own = serial and n_bins * n_chunks * n_chunks <= ORDER_OWN_SCAN_MAX
    local = 1 if serial else LOCAL_1D  # serial: one chunk per work-group, so PoCL spreads
    # the chunks over its threads (it runs a work-group's items on one thread)
    hist = rt.empty((n_bins * n_chunks,), torch.int32, zero=False)
    pos = rt.empty((n_bins * n_chunks,), torch.int32, zero=False)
    _record(events, name, rt.launch(k(count), n_chunks, local, *head, *count_args, hist.buffer))
    if not own:
        if serial or _host_scan(rt):
            _record(events, name, rt.launch(k("scan_counters"), 1, 1, np.int32(n_bins),
                                            np.int32(n_chunks), hist.buffer, pos.buffer))
        else:
            a = cl_array.Array(rt.queue, (n_bins * n_chunks,), np.int32, data=hist.buffer)
            b = cl_array.Array(rt.queue, (n_bins * n_chunks,), np.int32, data=pos.buffer)
            rt.hold(hist.buffer, pos.buffer)
            rt.launches += 1  # writes pos (see Runtime.launches)
            _record(events, "scan", rt.checked_scan_int32()(a, b, queue=rt.queue))
        if after_scan is not None:
            after_scan(pos)
    sub = {"own": np.int32(own), "hist": hist.buffer, "pos": pos.buffer}
    args = tuple(sub[a] if isinstance(a, str) else a for a in scatter_args)
    _record(events, name, rt.launch(k(scatter), n_chunks, local, *head, *args))


def _order_defines(cfg: RenderConfig, serial: bool) -> dict:
    """The build parameters of kernels/order.cl."""
    return {"REAL_DOUBLE": cfg.precision == "float64", "RADIX_BITS": ORDER_RADIX_BITS,
            "HIST_CHUNK_MAJOR": serial, "PACK_BITS": ORDER_PACK_BITS}


def _order_small(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, depths: DeviceArray,
                 n: int, tiles_x: int, tiles_y: int, offsets: DeviceArray, keys: DeviceArray,
                 events) -> None:
    """Launch kernels/order.cl's order_small (the whole stage in one work-item) for at most
    ``n`` pairs that touch a tile: offsets [C*T+1] and keys (at least M) written on the device."""
    C, N = depths.tensor.shape
    n_tiles = C * tiles_x * tiles_y
    # scratch used inside the one launch only (the in-order queue runs launches one at a
    # time): kept in the render plan, one set per power-of-two size bucket and tile count
    cap, n_cnt = max(1024, 1 << (n - 1).bit_length()), max(1 << ORDER_RADIX_BITS, n_tiles)
    scratch = rt.plan(("order_small_scratch", cap, n_cnt), lambda: (
        rt.empty((cap,), torch.int64, zero=False), rt.empty((cap,), torch.int64, zero=False),
        rt.empty((n_cnt,), torch.int32, zero=False)))
    _record(events, "sort_small", rt.launch(
        rt.kernel("order", "order_small", _order_defines(cfg, True)), 1, 1, np.int32(C * N),
        np.int32(N), np.int32(tiles_x), np.int32(tiles_y), np.int32(n_tiles), rects.buffer,
        depths.buffer, scratch[0].buffer, scratch[1].buffer, scratch[2].buffer, offsets.buffer,
        keys.buffer))


@dataclass
class EarlyTiles:
    """Tile lists launched by :func:`early_tile_lists` for the projection's ``rects`` and
    ``depths``: ``offsets`` [C*T+1] int32 and ``keys`` [C*N*T] int64, of which the first M
    (``offsets[-1]``) are the lists; :func:`depth_tiles` checks and trims them."""

    rects: DeviceArray
    depths: DeviceArray
    offsets: DeviceArray
    keys: DeviceArray


def early_tile_lists(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, depths: DeviceArray,
                     width: int, height: int, tile_size: int,
                     events: list | None = None) -> EarlyTiles | None:
    """For a small call (:data:`EARLY_TILES_MAX`) on a device that computes in the pool's host
    memory, where :func:`depth_tiles` would run order_small: launch it now, queued behind the
    projection that writes ``rects`` and ``depths``, without reading anything back. None where
    the call is not small (the tile lists are built by :func:`tile_lists` as before)."""
    C, N = depths.tensor.shape
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    slots = C * N * tiles_x * tiles_y
    if not (rt.pools and sort_by_depth(rt, cfg) and cfg.sort_chunks is None
            and _sort_serial(rt, cfg) and 0 < C * N <= ORDER_SMALL and slots <= EARLY_TILES_MAX
            and max(tiles_x, C * tiles_y) <= ORDER_PACK_MAX):
        return None
    # (every entry of the offsets is written; of the keys, the first M)
    offsets = rt.empty((C * tiles_x * tiles_y + 1,), torch.int32, zero=False)
    keys = rt.empty((slots,), torch.int64, zero=False)
    _order_small(rt, cfg, rects, depths, C * N, tiles_x, tiles_y, offsets, keys, events)
    return EarlyTiles(rects, depths, offsets, keys)


def depth_tiles(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, depths: DeviceArray,
                width: int, height: int, tile_size: int, events: list | None = None,
                per_intersection: int = 16, reserve: int = 0,
                early: EarlyTiles | None = None,
                pair_tiles: list | None = None,
                tiles: DeviceArray | None = None) -> tuple[DeviceArray, DeviceArray]:
    """Tile lists in depth order, from one depth sort of the pairs (kernels/order.cl).

    rects [C,N,4] int32 and depths [C,N] from :func:`project`; ``per_intersection`` and
    ``reserve`` as in :func:`bin_tiles`. The pairs that touch a tile are radix-sorted once by
    the float32 bits of their depth (ties: ascending c*N+g), then every pair's key is placed
    in each tile of its rectangle by a stable counting pass over tile ids.

    Returns ``tile_offsets`` [C*T+1] int32 (read back: the tensor holds them) and ``keys``
    [M] int64 holding ulong keys (float32 depth bits << 32 | c*N+g), each segment sorted
    ascending: the same arrays as :func:`bin_tiles` then :func:`sort_segments`. ``early``:
    :func:`early_tile_lists`' launch for these ``rects`` and ``depths``, whose offsets are
    checked and whose keys are trimmed to M here (the same arrays, bit for bit).
    """
    C, N = depths.tensor.shape
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    tpc = tiles_x * tiles_y
    n_tiles = C * tpc
    # besides the tile lists: 8-byte packed rectangles per pair; per pair that touches a tile
    # two key arrays and the sorted rectangles (24); the per-tile sort's 8-byte scratch per
    # intersection (in plan.intersection_bytes) is not allocated
    total, n = _intersections(rt, rects, per_intersection, reserve, per_pair=8, per_touching=24, unused=8,
                              pair_tiles=pair_tiles, tiles=tiles)
    if early is not None:
        if early.rects is not rects or early.depths is not depths:
            raise ValueError("early: tile lists launched for other rectangles or depths")
        check_tile_offsets(early.offsets.host(), total)
        return early.offsets, early.keys.prefix(total)
    offsets = rt.empty((n_tiles + 1,), torch.int32)
    keys = rt.empty((total,), torch.int64, zero=False)
    if n == 0:
        return offsets, keys
    # Counters chunk-major in the serial layout (each chunk scans for itself), bin-major in
    # the GPU layout (a scan launch). No pass waits for the host.
    serial = _sort_serial(rt, cfg)
    defines = _order_defines(cfg, serial)
    k = lambda name: rt.kernel("order", name, defines)  # noqa: E731
    bins = 1 << ORDER_RADIX_BITS
    if cfg.sort_chunks is None and serial and n <= ORDER_SMALL:
        _order_small(rt, cfg, rects, depths, n, tiles_x, tiles_y, offsets, keys, events)
        check_tile_offsets(offsets.host(), total)
        return offsets, keys
    # the depth sort: pass 0 builds the keys of the pairs that touch a tile, in c*N+g order
    ch = _order_chunks(rt, cfg, C * N, bins, n)
    chunk = -(-(C * N) // ch)
    src, dst = rt.empty((n,), torch.int64, zero=False), rt.empty((n,), torch.int64, zero=False)
    prects = rt.empty((C * N, 2), torch.int32, zero=False)  # packed rectangles (order.cl)
    head = (np.int32(C * N), np.int32(chunk), np.int32(ch), np.int32(N), np.int32(tiles_y))
    _counting_pass(rt, cfg, k, "depth_count_pairs", "depth_scatter_pairs", ch, bins, head,
                   (rects.buffer, depths.buffer, prects.buffer),
                   (prects.buffer, depths.buffer, "own", "hist", "pos", src.buffer), "sort_depth",
                   events)
    ch = _order_chunks(rt, cfg, n, bins, n)
    chunk = -(-n // ch)
    head = (np.int32(n), np.int32(chunk), np.int32(ch))
    for shift in range(ORDER_RADIX_BITS, 32, ORDER_RADIX_BITS):
        _counting_pass(rt, cfg, k, "depth_count", "depth_scatter", ch, bins, head + (np.int32(shift),),
                       (src.buffer,), (src.buffer, "own", "hist", "pos", dst.buffer), "sort_depth", events)
        src, dst = dst, src
    # the tile placement: bins are the (camera, tile) segments
    srects = rt.empty((n, 2), torch.int32, zero=False)
    _record(events, "bin_gather", rt.launch(k("gather_rects"), ch, 1 if serial else LOCAL_1D, *head,
                                            src.buffer, prects.buffer, srects.buffer))
    ch = _order_chunks(rt, cfg, n, n_tiles, total)
    chunk = -(-n // ch)
    head = (np.int32(n), np.int32(chunk), np.int32(ch), np.int32(tiles_x))

    def starts(pos: DeviceArray) -> None:  # after a scan launch; before the scatter advances them
        _record(events, "bin_starts", rt.launch(
            k("segment_starts"), n_tiles + 1, LOCAL_1D, np.int32(n_tiles), np.int32(ch),
            np.int32(total), pos.buffer, offsets.buffer))

    _counting_pass(rt, cfg, k, "place_count", "place_scatter", ch, n_tiles, head,
                   (np.int32(n_tiles), srects.buffer),
                   (np.int32(n_tiles), np.int32(total), src.buffer, srects.buffer, "own", "hist", "pos",
                    offsets.buffer, keys.buffer), "bin_place", events, after_scan=starts)
    check_tile_offsets(offsets.host(), total)
    return offsets, keys


def tile_lists(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, depths: DeviceArray,
               width: int, height: int, tile_size: int, events: list | None = None,
               per_intersection: int = 16, reserve: int = 0,
               early: EarlyTiles | None = None,
               pair_tiles: list | None = None,
               tiles: DeviceArray | None = None) -> tuple[DeviceArray, DeviceArray]:
    """Every tile's list of (camera, Gaussian) keys in depth order: (offsets [C*T+1] int32,
    read back; keys [M] int64), by :func:`sort_by_depth`: "depth" (:func:`depth_tiles`) or
    "tiles" (the baseline, :func:`bin_tiles` then :func:`sort_segments`). Same result; the
    baseline also where the depth sort's packed rectangles cannot hold the tile coordinates
    (:data:`ORDER_PACK_MAX`). ``early``: see :func:`depth_tiles` (only ever made where it runs);
    ``pair_tiles``, ``tiles``: see :func:`_intersections`."""
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    if sort_by_depth(rt, cfg) and max(tiles_x, depths.tensor.shape[0] * tiles_y) <= ORDER_PACK_MAX:
        return depth_tiles(rt, cfg, rects, depths, width, height, tile_size, events,
                           per_intersection, reserve, early, pair_tiles, tiles)
    offsets, keys = bin_tiles(rt, cfg, rects, depths, width, height, tile_size, events,
                              per_intersection, reserve, pair_tiles, tiles)
    # bin_tiles has read the offsets back and nothing writes them after the scan
    sort_segments(rt, cfg, keys, offsets, events=events, host_offsets=offsets.tensor)
    return offsets, keys


def tile_ranges(offsets: DeviceArray, n_cameras: int, tiles_y: int, tiles_x: int) -> torch.Tensor:
    """[C, tiles_y, tiles_x, 2] (start, end) of each tile's segment in the sorted keys.

    The ranges come straight from the scan of per-tile counts: binning scatters each key into
    its tile's segment, so no pass over the sorted keys is needed to find the boundaries.
    """
    off = offsets.host()
    return torch.stack([off[:-1], off[1:]], -1).reshape(n_cameras, tiles_y, tiles_x, 2)


CHANNEL_CHUNK = 32  # channels per compositing launch at most (gsplat's channel_chunk default)
#: compositing work-items per group that a GPU's default layout (``RenderConfig.pix`` None) stays
#: within: NVIDIA's OpenCL driver gives the float64 compositor a CL_KERNEL_WORK_GROUP_SIZE of 256
#: (its registers; an H200, 2026-11-27, bench/notes/engine_gpu.md) though the device allows 1024,
#: and AMD's GPUs cap groups at 256; a 32x32 tile then takes 4 pixels per item. An explicit pix
#: is kept, and refused with the kernel's own limit where it cannot run.
GPU_DEFAULT_GROUP_MAX = 256


def _planned_layout(rt: Runtime, cfg: RenderConfig, tile_size: int, channels: int,
                    geom_grads: int = 0, color_grad: bool = False,
                    backward: bool = False) -> tuple[int, int, int, int]:
    """:func:`composite_layout`, worked out once per shape and config (the render plan,
    :meth:`Runtime.plan`)."""
    return rt.plan(("composite_layout", cfg, tile_size, channels, geom_grads, color_grad, backward),
                   lambda: composite_layout(rt, cfg, tile_size, channels, geom_grads, color_grad,
                                            backward))


def composite_layout(rt: Runtime, cfg: RenderConfig, tile_size: int, channels: int,
                     geom_grads: int = 0, color_grad: bool = False,
                     backward: bool = False) -> tuple[int, int, int, int]:
    """(pixels per work-item, batch size, channels per launch, waves) for compositing here.

    Sized for :attr:`Runtime.local_mem` (at most 48 KiB, what GPUs offer). ``geom_grads``
    geometry gradient values (backward only) and, with ``color_grad``, one colour gradient
    per channel of a chunk are staged per item and sample in local memory too, in ``waves``
    waves of items (see kernels/composite_bwd.cl). The renders take it from the render plan
    (:func:`_planned_layout`).
    """
    # 8 floats or 4 doubles fill one 256-bit AVX register; PoCL rejects wider double vectors
    # on CPUs without AVX-512 (no kernel is produced).
    real = 8 if cfg.precision == "float64" else 4
    pix = cfg.pix or ((32 // real) if rt.is_cpu else max(1, tile_size * tile_size // GPU_DEFAULT_GROUP_MAX))
    if rt.is_cpu and pix * real > 32:
        raise ValueError(f"pix: {pix} x {cfg.precision} exceeds the 256-bit vectors PoCL builds "
                         f"for this CPU; use at most {32 // real}")
    pix = min(pix, tile_size)
    group = tile_size * tile_size // pix
    if group > rt.max_group:
        raise ValueError(f"tile_size: {tile_size}x{tile_size} tiles need work-groups of {group} "
                         f"items with {pix} pixel(s) per item; the device allows {rt.max_group}")

    tuned = composite_tuned(rt, cfg)
    params = 9 if tuned else 8  # staged per sample besides features (the tuned: l_sm)

    def per_sample(chunk: int, waves: int) -> int:  # local bytes per staged sample (kernels)
        if not backward:
            return (params + chunk) * real
        pg = geom_grads + chunk * color_grad
        staged_f = chunk if channels <= chunk else 1  # features for f . v_out (not WIDE)
        return (params + staged_f + group // waves * pg + (pg if waves > 1 else 0)) * real + 8

    def budget(waves: int) -> int:
        """Local bytes for the staged samples: all but the kernels' scalars and, in the tuned
        kernels, the padding of the 4 extent arrays to words of samples and, backward, of each
        partials block (of the items of a wave, and the wave sum) to whole vectors."""
        if not tuned:
            return rt.local_mem - 64
        vec_pad = (32 // real - 1) * real * (group // waves + (waves > 1)) if backward else 0
        return rt.local_mem - 64 - 4 * (K.EXTENT_WORD - 1) * real - vec_pad

    chunk, waves = min(channels, CHANNEL_CHUNK), 1
    # Fewer channels per launch first (down to 8), then partials handed over in waves.
    while per_sample(chunk, waves) > budget(waves):
        if chunk > 8:
            chunk = -(-chunk // 2)
        elif waves < group:
            waves *= 2
        elif chunk > 1:
            chunk = -(-chunk // 2)
        else:
            raise ValueError(f"tile_size: {tile_size}x{tile_size} tiles with {pix} pixel(s) per "
                             f"item need {per_sample(chunk, waves)} bytes of local memory per "
                             f"sample, over the {rt.local_mem} available; use a smaller tile_size")
    cap = (32 if waves == 1 else 4) if backward else group  # waves keep partials in registers
    batch = max(1, min(cap, budget(waves) // per_sample(chunk, waves)))
    return pix, batch, chunk, waves


def composite_tuned(rt: Runtime, cfg: RenderConfig) -> bool:
    """Whether compositing runs the tuned builds of ``kernels/composite.cl`` and
    ``composite_bwd.cl`` (``RenderConfig.composite_impl``; None: on CPUs) rather than the
    baseline builds (``-DCLS_TUNED=0``)."""
    return (cfg.composite_impl or ("tuned" if rt.is_cpu else "baseline")) == "tuned"


#: inputs of the inline-exp probe: every argument compositing can pass (exp(-sigma), sigma >= 0,
#: and the zero/overflow cut-offs), dense enough to meet every branch of the polynomial's range
#: reduction; a multiple of every PIX
EXP_PROBE_INPUTS = 1 << 18


def inline_exp_exact(rt: Runtime, cfg: RenderConfig, defines: dict) -> bool:
    """Whether the tuned kernels' inline float exp (kernels/common.h, SLEEF's expf_u10 as PoCL's
    library on this host has it) equals this device's library exp bit for bit, so that the tuned
    kernels give the baseline kernels' images exactly; decided once per runtime by the probe
    kernel of composite.cl, built with ``defines`` (a float vector layout). Where it does not
    (another PoCL build or CPU variant), the tuned kernels call the library's exp."""
    if rt.inline_exp_exact is None:
        k = rt.kernel("composite", "exp_probe", defines, cfg.fast_math)
        x = torch.linspace(-110.0, 10.0, EXP_PROBE_INPUTS, dtype=torch.float32)
        x[:8] = torch.tensor([0.0, -0.0, -1e-30, -1e-7, -87.3, -103.9, -104.1, 1e-7])
        xs, out = rt.array(x, read_only=True), rt.empty((EXP_PROBE_INPUTS,), torch.int32, zero=False)
        rt.launch(k, EXP_PROBE_INPUTS // defines["PIX"], LOCAL_1D, xs.buffer, out.buffer)
        rt.inline_exp_exact = not bool(out.host().any())
    return rt.inline_exp_exact


def _composite_kernel(rt: Runtime, cfg: RenderConfig, stage: str, defines: dict, group: int,
                      tile_size: int) -> cl.Kernel:
    """The compositing kernel for ``defines``, looked up once per shape and config (the render
    plan, :meth:`Runtime.plan`; the inline-exp probe's answer is part of the key) and checked
    against the device's group and local memory limits (:meth:`Runtime.check_group_once`)."""
    # (the defines in the order the call site builds them: see Runtime.kernel)
    k = rt.plan(("composite_kernel", stage, cfg, tuple(defines.items()), rt.inline_exp_exact),
                lambda: _build_composite_kernel(rt, cfg, stage, defines, tile_size))
    rt.check_group_once(k, stage, group, f" (tile_size {tile_size}, {defines['PIX']} pixel(s) per "
                        "item; use a smaller tile_size or a larger RenderConfig.pix)")
    return k


def _build_composite_kernel(rt: Runtime, cfg: RenderConfig, stage: str, defines: dict,
                            tile_size: int) -> cl.Kernel:
    """The kernel for ``defines``, its batch shrunk (a rebuild per try) until the compiler's own
    count of its local memory fits :attr:`Runtime.local_mem`: :func:`composite_layout` counts
    the kernel's arrays, which is exact on PoCL, but NVIDIA's compiler reported 1.0-5.1 KiB more
    for six of its layouts on an H200 (bench/notes/engine_gpu.md), which the launch check would
    refuse. The batch only sizes the staging, so images and gradients do not change."""
    k = _build_composite_kernel_once(rt, cfg, stage, defines, tile_size)
    while defines.get("BATCH", 1) > 1:
        used = int(k.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, rt.device))
        if used <= rt.local_mem:
            break
        batch = defines["BATCH"]
        defines = defines | {"BATCH": max(1, min(batch - 1, batch * rt.local_mem // used))}
        k = _build_composite_kernel_once(rt, cfg, stage, defines, tile_size)
    return k


def _build_composite_kernel_once(rt: Runtime, cfg: RenderConfig, stage: str, defines: dict,
                                 tile_size: int) -> cl.Kernel:
    name = "composite_fwd" if stage == "composite" else stage
    if stage == "composite_bwd_gauss":
        # One build for every device (no CLS_TUNED staging); on PoCL's CPU device the inline
        # maths, with the library's exp where the probe finds the inline one differs, so that
        # it replays the forward's exp bit for bit whichever forward build ran.
        defines = defines | {"CLS_POCL_CPU": rt.is_pocl_cpu}
        if rt.is_pocl_cpu and defines["PIX"] > 1 and cfg.precision == "float32":
            pix, batch, chunk, _ = _planned_layout(rt, cfg, tile_size, defines["CHANNELS"])
            fwd = cfg.defines(tile_size) | {"PIX": pix, "BATCH": batch, "CHANNELS": defines["CHANNELS"],
                                            "CCHUNK": chunk, "SAVE_LAST": False, "CLS_POCL_CPU": True}
            if not inline_exp_exact(rt, cfg, fwd):
                defines = defines | {"CLS_INLINE_EXP": 0}
    elif composite_tuned(rt, cfg):
        defines = defines | {"CLS_POCL_CPU": rt.is_pocl_cpu}
        if rt.is_pocl_cpu and defines["PIX"] > 1 and cfg.precision == "float32":
            # the forward's own program holds the probe (no extra build); the backward, which
            # follows a forward, finds the answer cached, else builds a forward-like program
            fwd = defines if stage == "composite" else cfg.defines(tile_size) | {
                "PIX": defines["PIX"], "BATCH": defines["BATCH"], "CHANNELS": defines["CHANNELS"],
                "CCHUNK": defines["CCHUNK"], "SAVE_LAST": False, "CLS_POCL_CPU": True}
            if not inline_exp_exact(rt, cfg, fwd):
                defines = defines | {"CLS_INLINE_EXP": 0}
    else:  # the same kernel source, built without the CPU-specific staging (CLS_TUNED=0)
        defines = defines | {"CLS_TUNED": 0}
    return rt.kernel(stage, name, defines, cfg.fast_math)


def composite(rt: Runtime, cfg: RenderConfig, means2d: DeviceArray, conics: DeviceArray,
              opacities: DeviceArray, extents: DeviceArray, feats: DeviceArray,
              offsets: DeviceArray, keys: DeviceArray,
              width: int, height: int, tile_size: int, save_last: bool,
              events: list | None = None, counts: DeviceArray | None = None,
              ) -> tuple[DeviceArray, DeviceArray, DeviceArray | None]:
    """Front-to-back compositing of every tile, one launch per chunk of channels.

    means2d [C,N,2], conics [C,N,3], opacities [C,N], extents [C,N,2], feats [C,N,CH] ->
    (out_feats [C,H,W,CH], out_T [C,H,W], last [C,H,W] int32 or None).
    ``counts``: zeroed int32 [C * tiles * group, 4] (group = tile_size^2 / pix, pix from
    :func:`composite_layout`): the kernel built with its sample counters (``CLS_COUNT``,
    kernels/composite.cl; the bench's counted flops) adds each work-item's counts of samples
    tested, past the extent test, past the sigma bound and past the alpha test. None
    (production): no counters are compiled in.
    """
    C = means2d.tensor.shape[0]
    CH = feats.tensor.shape[-1]
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    pix, batch, chunk, _ = _planned_layout(rt, cfg, tile_size, CH)
    out = rt.empty((C, height, width, CH), cfg.dtype)
    T = rt.empty((C, height, width), cfg.dtype)
    last = rt.empty((C, height, width), torch.int32) if save_last else None
    defines = cfg.defines(tile_size) | {"PIX": pix, "BATCH": batch, "CHANNELS": CH,
                                         "CCHUNK": chunk, "SAVE_LAST": save_last}
    group = tile_size * tile_size // pix
    if counts is not None:
        n_items = C * tiles_x * tiles_y * group
        if tuple(counts.tensor.shape) != (n_items, 4) or counts.tensor.dtype != torch.int32:
            raise ValueError(f"counts: expected int32 [{n_items}, 4], got {counts.tensor.dtype} "
                             f"{list(counts.tensor.shape)}")
        defines["CLS_COUNT"] = 1
    k = _composite_kernel(rt, cfg, "composite", defines, group, tile_size)
    for ch0 in range(0, CH, chunk):
        args = [np.int32(width), np.int32(height), np.int32(tiles_x), np.int32(tiles_x * tiles_y),
                np.int32(ch0), offsets.buffer, keys.buffer, means2d.buffer, conics.buffer,
                opacities.buffer, extents.buffer, feats.buffer, out.buffer, T.buffer]
        if save_last:
            args.append(last.buffer)
        if counts is not None:
            args.append(counts.buffer)
        _record(events, "composite", rt.enqueue(k, C * tiles_x * tiles_y * group, group, *args))
    return out, T, last


# ---- backward ------------------------------------------------------------------------------

def slot_width(channels: int, geom: bool, color: bool, absgrad: bool) -> int:
    """Gradient values stored per intersection (see kernels/composite_bwd.cl)."""
    return (8 if absgrad else 6) * geom + channels * color


def backward_gaussian(rt: Runtime, cfg: RenderConfig) -> bool:
    """Whether the backward of compositing runs ``kernels/composite_bwd_gauss.cl`` (a work-item
    per tile, each Gaussian's sum over the tile's pixels in registers) rather than
    ``composite_bwd.cl`` (a work-item per row segment, sums over items in local memory):
    ``RenderConfig.backward_impl``; None: :data:`BACKWARD_IMPL_CPU` on PoCL's CPU device, where
    it was measured, and "pixel" elsewhere (a work-item per tile would leave a GPU nearly idle;
    Oclgrind, a CPU device, keeps testing the GPU default)."""
    return (cfg.backward_impl or (BACKWARD_IMPL_CPU if rt.is_pocl_cpu else "pixel")) == "gaussian"


#: the default ``backward_impl`` on PoCL's CPU device: the compositing backward 0.63-0.77x the
#: per-pixel one's device time on scenes A, B and 10k-1M Gaussians, both ``packed`` layouts
#: (bench/notes/engine_cpu_speed.md, "Issue 35: the per-Gaussian backward")
BACKWARD_IMPL_CPU = "gaussian"


def gauss_layout(rt: Runtime, cfg: RenderConfig, tile_size: int, channels: int) -> tuple[int, int]:
    """(pixels per segment, channels per launch) of ``kernels/composite_bwd_gauss.cl``: the
    forward's pixels per work-item (so that its exp is the forward's), and as many channels
    (at most :data:`CHANNEL_CHUNK`) as let the per-pixel state (T, B, last, v_T T_final and
    one v_out per channel, plus an int per segment) fit :attr:`Runtime.local_mem`."""
    pix = _planned_layout(rt, cfg, tile_size, channels)[0]
    real = 8 if cfg.precision == "float64" else 4
    per_chunk = lambda ch: tile_size * tile_size * (4 + ch) * real + tile_size * tile_size // pix * 4  # noqa: E731
    chunk = min(channels, CHANNEL_CHUNK)
    while per_chunk(chunk) > rt.local_mem and chunk > 1:
        chunk = -(-chunk // 2)
    if per_chunk(chunk) > rt.local_mem:
        raise ValueError(f"tile_size: {tile_size}x{tile_size} tiles need {per_chunk(chunk)} bytes of "
                         f"local memory for the per-Gaussian backward, over the {rt.local_mem} "
                         "available; use a smaller tile_size or RenderConfig(backward_impl='pixel')")
    return pix, chunk


def isect_offsets(rt: Runtime, rects: DeviceArray, pair_tiles=None) -> DeviceArray:
    """[C*N] first gradient slot of each pair: exclusive prefix of its tile count
    (``pair_tiles``, [C*N] int32 numpy or the projection's ``tiles`` array, where the forward
    counted them: :func:`_intersections`)."""
    if pair_tiles is None:
        r = rects.host().reshape(-1, 4).numpy()  # numpy: a few us against ~40 for torch's ops
        n = (r[:, 2] - r[:, 0]) * (r[:, 3] - r[:, 1])
    elif isinstance(pair_tiles, DeviceArray):
        n = pair_tiles.host().reshape(-1).numpy()
    else:
        n = pair_tiles
    # (int32 sums: their total, the intersection count, was checked below 2^31 - 1)
    if rt.pools and 0 < n.nbytes:  # written in place into a pooled array (the device's memory)
        out = rt.empty(n.shape, torch.int32, zero=False)
        _exclusive_scan(n, out.tensor.numpy())
        return out
    o = np.empty(n.shape, np.int32)
    _exclusive_scan(n, o)
    return rt.from_host(o)


#: pairs from which the slot offsets' scan is torch's, not numpy's: numpy accumulates int32 in int64
#: and casts back (B's 1.95M counts: 4.4 against 0.65 ms, one thread), but costs ~5 us less a call
#: below a few thousand (100 pairs: 2.3 against 7.2 us; 10,000: 31 against 15)
TORCH_SCAN_MIN_PAIRS = 4096


def _exclusive_scan(n: np.ndarray, out: np.ndarray) -> None:
    """``out`` [P] int32 = the exclusive prefix sums of the counts ``n`` [P] (int32)."""
    if n.size == 0:
        return
    out[0] = 0
    if n.size >= TORCH_SCAN_MIN_PAIRS:
        torch.cumsum(torch.from_numpy(np.ascontiguousarray(n[:-1], np.int32)), 0, dtype=torch.int32,
                     out=torch.from_numpy(out[1:]))
    else:
        np.cumsum(n[:-1], out=out[1:])


#: Small calls on PoCL's CPU device: up to this many slot values (intersections x values per
#: slot), the per-Gaussian backward's last work-item sums them itself (FUSED_REDUCE,
#: kernels/composite_bwd_gauss.cl) instead of a reduce launch: one launch and one wake-up of
#: the device's threads fewer (~30-50 us of a tiny call), against one thread summing serially
#: what the reduce spreads over them (32k additions: a few tens of us at most).
FUSED_REDUCE_VALUES = 1 << 15


def composite_bwd_reduced(rt: Runtime, cfg: RenderConfig, fwd: dict, v_out: DeviceArray,
                          v_T: DeviceArray, width: int, height: int, tile_size: int, *,
                          geom: bool, color: bool, absgrad: bool, divide: bool = False,
                          events: list | None = None,
                          alloc: Callable[[tuple, torch.dtype], DeviceArray] | None = None) -> dict:
    """:func:`composite_bwd` then :func:`reduce_slots`: the per-pair gradients by name (as
    :func:`reduce_slots` returns them). Where the per-Gaussian backward runs on PoCL's CPU
    device in one launch, without fast maths, with at most :data:`FUSED_REDUCE_VALUES` slot
    values, that launch sums the slots itself (the same bits: both call kernels/common.h's
    reduce_pair, and without fast maths its additions are not reordered)."""
    C, N = fwd["opacities"].tensor.shape
    CH = fwd["feats"].tensor.shape[-1]
    G = slot_width(CH, geom, color, absgrad)
    fuse = (rt.is_pocl_cpu and not cfg.fast_math and backward_gaussian(rt, cfg)
            and fwd["keys"].tensor.numel() * G <= FUSED_REDUCE_VALUES
            and (not color or CH <= rt.plan(("gauss_layout", cfg, tile_size, CH),
                                            lambda: gauss_layout(rt, cfg, tile_size, CH))[1]))
    if not fuse:
        slots, offs = composite_bwd(rt, cfg, fwd, v_out, v_T, width, height, tile_size, geom=geom,
                                    color=color, absgrad=absgrad, divide=divide, events=events,
                                    alloc=alloc)
        return reduce_slots(rt, cfg, fwd["rects"], offs, slots, CH, geom=geom, color=color,
                            absgrad=absgrad, events=events)
    out, shapes = _reduce_outputs(rt, cfg, C, N, CH, geom, color, absgrad)
    composite_bwd(rt, cfg, fwd, v_out, v_T, width, height, tile_size, geom=geom, color=color,
                  absgrad=absgrad, divide=divide, events=events, alloc=alloc, reduce_into=out)
    return {k: a for k, a in out.items() if shapes[k] is not None}


def composite_bwd(rt: Runtime, cfg: RenderConfig, fwd: dict, v_out: DeviceArray,
                  v_T: DeviceArray, width: int, height: int, tile_size: int, *, geom: bool,
                  color: bool, absgrad: bool, divide: bool = False,
                  events: list | None = None,
                  alloc: Callable[[tuple, torch.dtype], DeviceArray] | None = None,
                  reduce_into: dict | None = None) -> tuple[DeviceArray, DeviceArray]:
    """Per-intersection gradient slots of compositing: ``kernels/composite_bwd_gauss.cl`` (a
    work-item per tile) where :func:`backward_gaussian`, else ``kernels/composite_bwd.cl`` (a
    work-item per row segment); the same slots to rounding, each bitwise reproducible.

    ``fwd`` holds the forward's DeviceArrays: means2d, conics, opacities, extents, feats, rects,
    offsets, keys, out (out_feats), T, last; optionally "pair_tiles" (:func:`isect_offsets`). v_out [C,H,W,CH], v_T [C,H,W]. ``alloc(shape,
    dtype)`` makes the zeroed slots array (default ``rt.empty``; e.g. ``Runtime.scratch``'s).
    ``reduce_into``: :func:`_reduce_outputs`' arrays, which the per-Gaussian kernel's one launch
    fills itself (FUSED_REDUCE; only as :func:`composite_bwd_reduced` decides).
    Returns (slots [M, G], isect_offsets [C*N]).
    """
    C, N = fwd["opacities"].tensor.shape
    CH = fwd["feats"].tensor.shape[-1]
    G = slot_width(CH, geom, color, absgrad)
    M = fwd["keys"].tensor.numel()
    tiles_x, tiles_y = -(-width // tile_size), -(-height // tile_size)
    geom_cols = (8 if absgrad else 6) * geom
    gauss = backward_gaussian(rt, cfg)
    if gauss:
        pix, chunk = rt.plan(("gauss_layout", cfg, tile_size, CH), lambda: gauss_layout(rt, cfg, tile_size, CH))
        batch, waves, group, n_items = 0, 1, 1, C * tiles_x * tiles_y
    else:
        pix, batch, chunk, waves = _planned_layout(rt, cfg, tile_size, CH, geom_grads=geom_cols,
                                                   color_grad=color, backward=True)
        group = tile_size * tile_size // pix
        n_items = C * tiles_x * tiles_y * group
    rt.check_memory(M * G * (8 if cfg.precision == "float64" else 4),
                    f"means, scales: the backward's gradient slots ({M} intersections x {G} values)")
    offs = isect_offsets(rt, fwd["rects"], fwd.get("pair_tiles"))
    slots = (alloc or rt.empty)((M, G), cfg.dtype)
    f = fwd
    # The first launch computes the geometry gradients (and colour chunk 0); each further
    # launch only the colour gradients of its chunk of channels.
    for ch0 in range(0, CH if color else 1, chunk):
        defines = cfg.defines(tile_size) | {
            "PIX": pix, "CHANNELS": CH, "CCHUNK": chunk,
            "GEOM_GRAD": geom and ch0 == 0, "COLOR_GRAD": color, "ABSGRAD": absgrad,
            "BWD_DIVIDE": divide, "SLOT_G": G, "SLOT_COLOR0": geom_cols}
        if not gauss:
            defines |= {"BATCH": batch, "WAVES": waves}
        else:
            defines["FUSED_REDUCE"] = reduce_into is not None
        stage = "composite_bwd_gauss" if gauss else "composite_bwd"
        k = _composite_kernel(rt, cfg, stage, defines, group, tile_size)
        fused = () if reduce_into is None else (
            np.int32(C * N), rt.plan(("fused_reduce_count",), lambda: rt.empty((1,), torch.int32)).buffer,
            *(a.buffer for a in reduce_into.values()))
        _record(events, "composite_bwd", rt.enqueue(
            k, n_items, group, np.int32(width), np.int32(height),
            np.int32(tiles_x), np.int32(tiles_x * tiles_y), np.int32(N), np.int32(ch0),
            f["offsets"].buffer, f["keys"].buffer, f["rects"].buffer, offs.buffer,
            f["means2d"].buffer, f["conics"].buffer, f["opacities"].buffer, f["extents"].buffer,
            f["feats"].buffer, f["out"].buffer, f["T"].buffer, f["last"].buffer, v_out.buffer,
            v_T.buffer, slots.buffer, *fused))
    return slots, offs


def _reduce_outputs(rt: Runtime, cfg: RenderConfig, C: int, N: int, channels: int, geom: bool,
                    color: bool, absgrad: bool) -> tuple[dict, dict]:
    """(arrays, shapes) of the reduce's outputs, in kernels/common.h's REDUCE_OUT_ARGS order:
    v_means2d [C,N,2], v_conics [C,N,3], v_opacities [C,N] (``geom``), absgrad [C,N,2]
    (``absgrad``), v_feats [C,N,CH] (``color``); shape None for those not built in."""
    dt = cfg.dtype
    shapes = {"v_means2d": (C, N, 2) if geom else None, "v_conics": (C, N, 3) if geom else None,
              "v_opacities": (C, N) if geom else None, "absgrad": (C, N, 2) if absgrad else None,
              "v_feats": (C, N, channels) if color else None}
    # The kernel writes every entry of what is built in (no zero fill); the others are
    # never written, and a one-element buffer stands in for each.
    out = {k: rt.empty(sh, dt, zero=False) if sh is not None else
           rt.plan(("reduce_placeholder", k, dt), lambda: rt.empty((1,), dt, zero=False))
           for k, sh in shapes.items()}
    return out, shapes


def reduce_slots(rt: Runtime, cfg: RenderConfig, rects: DeviceArray, offs: DeviceArray,
                 slots: DeviceArray, channels: int, *, geom: bool, color: bool, absgrad: bool,
                 events: list | None = None) -> dict:
    """Sum each pair's slots into those of v_means2d [C,N,2], v_conics [C,N,3], v_opacities
    [C,N] (``geom``), absgrad [C,N,2] (``absgrad``) and v_feats [C,N,CH] (``color``) that are
    built in; returns them by name."""
    C, N = rects.tensor.shape[:2]
    out, shapes = _reduce_outputs(rt, cfg, C, N, channels, geom, color, absgrad)
    defines = {"REAL_DOUBLE": cfg.precision == "float64", "CHANNELS": channels,
               "GEOM_GRAD": geom, "COLOR_GRAD": color, "ABSGRAD": absgrad}
    k = rt.kernel("reduce", "reduce_slots", defines)
    _record(events, "reduce", rt.launch(
        k, C * N, LOCAL_1D, np.int32(C * N), rects.buffer, offs.buffer, slots.buffer,
        *(a.buffer for a in out.values())))
    return {k: a for k, a in out.items() if shapes[k] is not None}


def sh_colors_bwd(rt: Runtime, cfg: RenderConfig, means: DeviceArray, viewmats: DeviceArray,
                  coeffs: DeviceArray, radii: DeviceArray, colors: DeviceArray, v_colors: DeviceArray,
                  sh_degree: int, means_grad: bool, dir_grad: bool = False,
                  events: list | None = None) -> tuple[DeviceArray, DeviceArray, DeviceArray]:
    """(the forward's colors [C,N,3], v_colors [C,N,3]) -> (v_coeffs [N,K,3], v_means [N,3]
    through the view direction, v_dirs [C,N,3] gradient of each unnormalised direction
    mean - camera centre)."""
    N = means.tensor.shape[0]
    C = viewmats.tensor.shape[0]
    # the kernel writes every entry of v_coeffs, and of v_means when it takes that gradient
    v_coeffs = rt.empty(tuple(coeffs.tensor.shape), cfg.dtype, zero=False)
    v_means = rt.empty((N, 3), cfg.dtype, zero=not means_grad)
    v_dirs = rt.empty((C, N, 3) if dir_grad else (0,), cfg.dtype)
    defines = {"REAL_DOUBLE": cfg.precision == "float64", "SH_DEGREE": sh_degree,
               "SH_COEFFS": coeffs.tensor.shape[1], "MEANS_GRAD": means_grad,
               "DIR_GRAD": dir_grad}
    k = rt.kernel("sh_bwd", "sh_colors_bwd", defines, cfg.fast_math)
    _record(events, "sh_bwd", rt.launch(
        k, N, LOCAL_1D, np.int32(C), np.int32(N), means.buffer, viewmats.buffer, coeffs.buffer,
        radii.buffer, colors.buffer, v_colors.buffer, v_coeffs.buffer, v_means.buffer, v_dirs.buffer))
    return v_coeffs, v_means, v_dirs


def project_bwd(rt: Runtime, cfg: RenderConfig, inputs: dict, radii: DeviceArray, grads: dict,
                width: int, height: int, *, eps2d: float, antialiased: bool, viewmat_grad: bool,
                events: list | None = None) -> dict:
    """Screen-space gradients to 3D parameters.

    inputs: means, quats, scales, opacities, viewmats, Ks (DeviceArrays, as in :func:`project`);
    grads: v_means2d [C,N,2], v_conics [C,N,3], v_depths [C,N], v_opacities [C,N].
    Returns v_means [N,3], v_quats [N,4], v_scales [N,3], v_opacities [N] and, with
    ``viewmat_grad``, v_viewmats [C,4,4].
    """
    N = inputs["means"].tensor.shape[0]
    C = inputs["viewmats"].tensor.shape[0]
    dt = cfg.dtype
    # every Gaussian's entries are written by the kernel: no zero fill
    out = {"v_means": rt.empty((N, 3), dt, zero=False), "v_quats": rt.empty((N, 4), dt, zero=False),
           "v_scales": rt.empty((N, 3), dt, zero=False), "v_opacities": rt.empty((N,), dt, zero=False)}
    defines = {"REAL_DOUBLE": cfg.precision == "float64", "ANTIALIASED": antialiased,
               "VIEWMAT_GRAD": viewmat_grad, "CLS_POCL_CPU": rt.is_pocl_cpu}
    k = rt.kernel("project_bwd", "project_bwd", defines, cfg.fast_math)
    args = [np.int32(C), np.int32(N)] + [inputs[n].buffer for n in
                                         ("means", "quats", "scales", "opacities", "viewmats", "Ks")]
    args += [np.int32(width), np.int32(height), _np_real(cfg)(eps2d), radii.buffer]
    args += [grads[n].buffer for n in ("v_means2d", "v_conics", "v_depths", "v_opacities")]
    args += [a.buffer for a in out.values()]
    v_view = rt.empty((C, N, 12), dt) if viewmat_grad else None
    if viewmat_grad:
        args.append(v_view.buffer)
    _record(events, "project_bwd", rt.launch(k, N, LOCAL_1D, *args))
    if viewmat_grad:
        vv = torch.zeros((C, 4, 4), dtype=dt)
        vv[:, :3, :] = v_view.host().sum(1).reshape(C, 3, 4)
        out["v_viewmats"] = vv
    return out
