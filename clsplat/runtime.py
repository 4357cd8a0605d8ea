"""OpenCL runtime: device choice, specialised program builds, and host/device arrays.

This module owns the only global mutable state of clsplat: the runtime cache (one context and
queue per device) and, inside each runtime, the program and kernel caches, the render
plans (:meth:`Runtime.plan`: per shape and config, bounded) and the plans' arrays (the array
pool and the kept input arrays, below: per shape, bounded, handed out only when free).

* Device choice: an argument, else ``CLSPLAT_DEVICE``, else the first GPU, else PoCL's CPU.
  A device is named by ``"P:D"`` (platform and device indices), or by a case-insensitive
  substring of ``"<platform> <device> <type>"`` such as ``"pocl"``, ``"nvidia"`` or ``"gpu"``.
* Programs are ``kernels/common.h`` + one stage file, specialised with ``-D`` options and
  cached by (source hash, options, device). Kernel objects are created once per program.
* :class:`DeviceArray` pairs a torch CPU tensor with an OpenCL buffer. On devices that share
  host memory (``CL_DEVICE_HOST_UNIFIED_MEMORY``, e.g. PoCL's CPU device) the buffer is
  created over the tensor's memory (``USE_HOST_PTR``) and read back by mapping it, which
  copies nothing there; elsewhere data are written at creation and read back with
  ``enqueue_copy``. The host never touches a buffer's memory outside map/unmap or
  read/write commands, as the OpenCL spec requires, except on PoCL's CPU device, which
  computes in the host memory itself (:attr:`Runtime.computes_in_host_memory`): there a
  finished queue is all a read-back needs. ``CLSPLAT_HOST_MEMORY=copy`` forces the
  copy path (what discrete GPUs take) on any device, ``=share`` forces zero-copy.
* Scratch memory: :meth:`Runtime.scratch` hands out zeroed intermediate arrays over host memory
  the runtime keeps from one block to the next (the backward's gradient slots, 100+ MB at 1M
  Gaussians, whose fresh pages cost more to fault in than the kernels take to fill them).
* The array pool (the render plan's arrays, kept per shape): on a device that computes in host
  memory, :meth:`Runtime.empty` hands out small arrays (:data:`POOL_ARRAY_BYTES`) again once
  nothing but the pool holds them (no tensor, view, numpy array, saved tensor or queued
  command: :func:`_unheld`), so a small render makes no buffer per call; a fresh one cost the
  calling thread ~12 us (the tensor, the buffer, PoCL's first use and release of it).
  :meth:`Runtime.array` of a pooled array's own memory returns that array. Bounded by
  :data:`POOL_BYTES` and :data:`POOL_SHAPES`, least recently used shapes dropped first.
* Device limits: launches respect the kernel's own ``CL_KERNEL_WORK_GROUP_SIZE`` and every
  kernel is sized for :data:`LOCAL_MEM_BUDGET` (48 KiB, what GPUs offer) of local memory,
  not for a CPU runtime's larger figure.
"""
from __future__ import annotations

import hashlib
import math
import os
import sys
import threading
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import resources
from typing import Callable, Iterable, Iterator, Mapping

import numpy as np
import pyopencl as cl
import pyopencl.array as cl_array
import torch

from .memory import available_host_memory, fmt_bytes, host_allowance

__all__ = [
    "BuildError", "DeviceError", "Runtime", "DeviceArray", "get_runtime", "list_devices",
    "describe_devices", "read_back", "LOCAL_MEM_BUDGET", "INT32_MAX", "available_host_memory",
    "PLAN_CACHE_SIZE", "POOL_ARRAY_BYTES", "POOL_PER_SHAPE", "POOL_BYTES", "POOL_SHAPES",
    "KEEP_INPUTS", "STAGE_COPY_BYTES", "BUILD_RETRIES",
]

_BASE_OPTIONS = ("-cl-std=CL1.2", "-cl-denorms-are-zero")
_DEVICE_ENV = "CLSPLAT_DEVICE"
_HOST_MEMORY_ENV = "CLSPLAT_HOST_MEMORY"
LOCAL_MEM_BUDGET = 48 * 1024  # bytes of local memory a kernel may use: a GPU's, not PoCL's
INT32_MAX = 2**31 - 1
#: values in the one-time check of the device's prefix scan (Runtime.checked_scan_int32): several
#: of pyopencl's work-group intervals, so the carries between them are checked too
SCAN_SELF_TEST = 4099
_RW = cl.mem_flags.READ_WRITE
_RW_HOST_PTR = cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR
HOST_CHECK_BYTES = 16 << 20  # allocations from this size on are checked against free host memory
#: entries of a runtime's render-plan cache (:meth:`Runtime.plan`): a few per shape and config
#: (two compositing kernels, two layouts, a stage's scratch), for a handful of shapes in use
PLAN_CACHE_SIZE = 64
#: the array pool (:meth:`Runtime.empty`): arrays up to this size are kept and handed out again
#: once free; larger renders' arrays are made per call as before (their kernels outweigh it)
POOL_ARRAY_BYTES = 1 << 20
#: arrays of one shape and dtype kept at most: a call uses up to 5 of one shape ([C, N]: depths,
#: opacities, their gradients in and out), and a training loop holds the last call's outputs
#: while it makes the next call, and a step may render a few views of one shape
POOL_PER_SHAPE = 8
#: bytes the pool of a runtime keeps at most (least recently used shapes dropped first)
POOL_BYTES = 32 << 20
#: shapes the pool keeps at most (a tiny call uses ~20; the intersection arrays change shape
#: with every call whose intersection count differs, and would otherwise fill it with
#: thousands of small buffers)
POOL_SHAPES = 64
#: an incoming gradient ready to use (contiguous, of the right dtype) is copied into a pooled
#: array up to this size (a copy that costs less than the ~12 us of a new buffer); larger ones
#: get an array over their own memory, as before
STAGE_COPY_BYTES = 64 << 10
#: input arrays kept at most (:meth:`Runtime.array` with ``keep``): a render's six projection
#: inputs and its colours, for a couple of scenes in turn
KEEP_INPUTS = 16
#: builds of a program that failed on PoCL made again before the failure counts (Runtime.program:
#: PoCL's kernel cache races between processes); each retry found the finished cache entry
BUILD_RETRIES = 2
_MISSING = object()


class DeviceError(ValueError):
    """The requested OpenCL device does not exist or lacks a feature clsplat needs."""


class BuildError(RuntimeError):
    """An OpenCL program failed to build; carries the compiler log and the options used."""

    def __init__(self, stage: str, options: Iterable[str], log: str, device: str) -> None:
        self.stage, self.options, self.log, self.device = stage, list(options), log, device
        super().__init__(
            f"building kernels/{stage}.cl for {device} failed\n"
            f"options: {' '.join(self.options)}\ncompiler log:\n{log}")


def _kernel_source(name: str) -> str:
    return resources.files("clsplat.kernels").joinpath(name).read_text()


def list_devices() -> list[tuple[int, int, cl.Device]]:
    """Every OpenCL device as (platform index, device index, device)."""
    out = []
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # no ICD at all
        return out
    for pi, p in enumerate(platforms):
        try:
            devs = p.get_devices()
        except cl.Error:
            continue
        out.extend((pi, di, d) for di, d in enumerate(devs))
    return out


def _label(d: cl.Device) -> str:
    return f"{d.platform.name} ({d.platform.vendor}) {d.name} {cl.device_type.to_string(d.type)}"


def _choose(spec: str | None) -> cl.Device:
    devices = list_devices()
    if not devices:
        raise DeviceError("device: no OpenCL platform found; install pocl-binary-distribution")
    if spec is None or spec == "":
        gpus = [d for _, _, d in devices if d.type & cl.device_type.GPU]
        if gpus:
            return gpus[0]
        pocl = [d for _, _, d in devices if "portable" in d.platform.name.lower()]
        return (pocl or [devices[0][2]])[0]
    if ":" in spec and all(part.isdigit() for part in spec.split(":", 1)):
        pi, di = (int(x) for x in spec.split(":", 1))
        for p, i, d in devices:
            if (p, i) == (pi, di):
                return d
    else:
        for _, _, d in devices:
            if spec.lower() in _label(d).lower():
                return d
    known = "; ".join(f"{p}:{i} {_label(d)}" for p, i, d in devices)
    raise DeviceError(f"device: no OpenCL device matches {spec!r}; available: {known}")


@dataclass
class Runtime:
    """One OpenCL device with its context, profiling queue and program cache."""

    device: cl.Device
    context: cl.Context = field(init=False)
    queue: cl.CommandQueue = field(init=False)
    _programs: dict = field(default_factory=dict, init=False, repr=False)
    _kernels: dict = field(default_factory=dict, init=False, repr=False)
    _scans: dict = field(default_factory=dict, init=False, repr=False)
    _group_limits: dict = field(default_factory=dict, init=False, repr=False)
    # kernel.int_ptr -> the argument types whose scalar dtypes were declared to pyopencl (enqueue)
    _arg_dtypes: dict = field(default_factory=dict, init=False, repr=False)
    # (stage, kernel name, sorted defines, fast_math) -> kernel: the per-launch look-up, which
    # neither reads nor hashes the sources (they are package data, fixed for the process).
    _kernel_index: dict = field(default_factory=dict, init=False, repr=False)
    _sources: dict = field(default_factory=dict, init=False, repr=False)
    _limits: tuple = field(default=(), init=False, repr=False)  # (max alloc, global mem) bytes
    _in_host_memory: bool | None = field(default=None, init=False, repr=False)
    _shares: bool | None = field(default=None, init=False, repr=False)  # shares_host_memory, cached
    _device_only: bool | None = field(default=None, init=False, repr=False)  # device_only_arrays, cached
    _pools_device: bool | None = field(default=None, init=False, repr=False)  # pools' device part, cached
    # whether the tuned compositing kernels' inline exp is this device's library exp bit for
    # bit (clsplat.stages.inline_exp_exact; None until probed)
    inline_exp_exact: bool | None = field(default=None, init=False, repr=False)
    # Commands that may write device memory, counted: an array read back (or created) after
    # the last of them needs no wait on the queue to be read again.
    launches: int = field(default=0, init=False, repr=False)
    # Buffers that queued commands may still touch. A released pyopencl Buffer drops its host
    # memory at once, even while a kernel is queued on it, so every buffer a command uses is
    # held here from its enqueue until the next finish().
    _in_flight: list = field(default_factory=list, init=False, repr=False)
    _finished_at: int = field(default=-1, init=False, repr=False)  # ``launches`` at the last finish()
    # Host memory kept for :meth:`scratch`: at most one block (the largest handed back), taken
    # by one scratch block at a time (a concurrent one allocates its own).
    _scratch_mem: torch.Tensor | None = field(default=None, init=False, repr=False)
    _scratch_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)
    # The render plans (:meth:`plan`): what a call works out from its shape and config alone,
    # least recently used first, at most PLAN_CACHE_SIZE entries.
    _plans: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)
    _plan_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)
    plan_builds: int = field(default=0, init=False, repr=False)  # entries built (misses), for tests
    plan_hits: int = field(default=0, init=False, repr=False)
    # The array pool (:meth:`empty`): (shape, dtype) -> arrays, least recently used shape
    # first; data_ptr -> pooled array (for :meth:`array`); the bytes kept; 0 turns it off.
    _pool: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)
    _pool_ptrs: dict = field(default_factory=dict, init=False, repr=False)
    _pool_bytes: int = field(default=0, init=False, repr=False)
    _pool_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)
    pool_limit: int = field(default=POOL_BYTES, init=False, repr=False)
    pool_reuses: int = field(default=0, init=False, repr=False)  # arrays handed out again, for tests
    # (data_ptr, shape, dtype) -> the kept array of an input (:meth:`array` with ``keep``)
    _kept: OrderedDict = field(default_factory=OrderedDict, init=False, repr=False)

    def __post_init__(self) -> None:
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(
            self.context, properties=cl.command_queue_properties.PROFILING_ENABLE)

    # -- facts the drivers specialise on -------------------------------------------------
    @property
    def name(self) -> str:
        return _label(self.device)

    @property
    def has_fp64(self) -> bool:
        return "cl_khr_fp64" in self.device.extensions

    @property
    def shares_host_memory(self) -> bool:
        """True where buffers are created over the tensors' own memory (zero-copy): devices
        with unified host memory, unless ``CLSPLAT_HOST_MEMORY`` says ``copy`` (or ``share``).
        Decided once per runtime, when first asked (every array asks: the environment is not
        read per array)."""
        if self._shares is None:
            mode = os.environ.get(_HOST_MEMORY_ENV, "auto").lower()
            if mode not in ("auto", "copy", "share"):
                raise DeviceError(f"{_HOST_MEMORY_ENV}: expected 'auto', 'copy' or 'share', got {mode!r}")
            if mode != "auto":
                self._shares = mode == "share"
            else:
                try:
                    self._shares = bool(self.device.host_unified_memory)
                except cl.Error:  # the query is deprecated in OpenCL 2.0: fall back to the type
                    self._shares = bool(self.device.type & cl.device_type.CPU)
        return self._shares

    @property
    def computes_in_host_memory(self) -> bool:
        """Whether zero-copy buffers are used in place, with no map needed to hand data over.

        PoCL's CPU device computes on a ``USE_HOST_PTR`` buffer's host memory itself, so there
        a zero-copy array skips the map and unmap at creation (whose contents the spec defines
        then anyway) and on read-back (the finished queue suffices). Each map cost ~0.2 ms of
        the calling thread on PoCL, most of the fixed cost of a small render. Elsewhere
        (Oclgrind's checker tracks host writes, GPUs keep copies) arrays are mapped."""
        if self._in_host_memory is None:
            pocl = "portable computing language" in self.device.platform.name.lower()
            self._in_host_memory = pocl and self.is_cpu
        return self._in_host_memory

    @property
    def device_only_arrays(self) -> bool:
        """Whether intermediates live on the device alone where it does not share host memory
        (:meth:`DeviceArray.on_device`). Not on Oclgrind, whose uninitialised-value checker
        counts neither a fill command as a write nor, once a released buffer's memory is
        reused, another live buffer's written values (bench/experiments/oclgrind_reuse_uninit.py):
        there every array is uploaded from the host, as before."""
        if self._device_only is None:  # (asked by every intermediate: worked out once)
            self._device_only = "oclgrind" not in self.device.platform.name.lower()
        return self._device_only

    @property
    def pools(self) -> bool:
        """Whether the array pool is on (:meth:`empty`, see the module docstring): where the
        device computes in the zero-copy arrays' host memory itself (PoCL's CPU device; not
        with ``CLSPLAT_HOST_MEMORY=copy``), so that a pooled array zeroed or written on the
        host, or an input changed in place, needs no transfer; and :attr:`pool_limit` > 0.
        (Asked ~50 times a small call: the device's part is worked out once.)"""
        on = self._pools_device
        if on is None:
            on = self._pools_device = self.computes_in_host_memory and self.shares_host_memory
        return on and self.pool_limit > 0

    @property
    def is_pocl_cpu(self) -> bool:
        """PoCL's CPU device (whose kernel compiler is clang on the host: kernels may use clang
        builtins there, e.g. the compositing kernels' prefetches)."""
        return self.computes_in_host_memory

    @property
    def max_alloc(self) -> int:
        """``CL_DEVICE_MAX_MEM_ALLOC_SIZE`` in bytes (queried once)."""
        if not self._limits:
            self._limits = (int(self.device.max_mem_alloc_size), int(self.device.global_mem_size))
        return self._limits[0]

    @property
    def is_cpu(self) -> bool:
        return bool(self.device.type & cl.device_type.CPU)

    @property
    def max_group(self) -> int:
        return int(self.device.max_work_group_size)

    @property
    def local_mem(self) -> int:
        """Local memory a kernel may use: the device's, capped at :data:`LOCAL_MEM_BUDGET`."""
        return min(int(self.device.local_mem_size), LOCAL_MEM_BUDGET)

    def kernel_group_limit(self, kernel: cl.Kernel) -> int:
        """``CL_KERNEL_WORK_GROUP_SIZE``: the largest group this kernel runs with here."""
        return int(kernel.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self.device))

    def check_group(self, kernel: cl.Kernel, stage: str, group: int, hint: str = "") -> None:
        """Refuse a launch whose work-group exceeds the kernel's own limit or whose static
        local memory exceeds the device's, before enqueueing it."""
        limit = self.kernel_group_limit(kernel)
        if group > limit:
            raise ValueError(f"{stage}: work-groups of {group} items exceed this kernel's "
                             f"CL_KERNEL_WORK_GROUP_SIZE of {limit} on {self.name}{hint}")
        lmem = int(kernel.get_work_group_info(cl.kernel_work_group_info.LOCAL_MEM_SIZE, self.device))
        if lmem > int(self.device.local_mem_size):
            raise ValueError(f"{stage}: the kernel needs {lmem} bytes of local memory, the device "
                             f"has {self.device.local_mem_size}{hint}")

    def check_group_once(self, kernel: cl.Kernel, stage: str, group: int, hint: str = "") -> None:
        """:meth:`check_group` the first time a kernel is checked (or after ``_group_limits``
        was emptied); later, ``group`` against the kernel's limit kept there (a dict look-up:
        the limits and the kernel's local memory are fixed for the process)."""
        limit = self._group_limits.get(kernel.int_ptr)
        if limit is None or group > limit:
            self.check_group(kernel, stage, group, hint)
            self._group_limits[kernel.int_ptr] = self.kernel_group_limit(kernel)

    # -- programs -----------------------------------------------------------------------
    def program(self, stage: str, defines: Mapping[str, object], fast_math: bool = False) -> cl.Program:
        """Build (or fetch) ``kernels/<stage>.cl`` specialised by ``defines``."""
        source = self._sources.get(stage)
        if source is None:
            source = self._sources[stage] = (_kernel_source("common.h") + f'\n#line 1 "{stage}.cl"\n'
                                             + _kernel_source(f"{stage}.cl"))
        options = list(_BASE_OPTIONS) + [f"-D{k}={_define(v)}" for k, v in sorted(defines.items())]
        if fast_math:
            options.append("-cl-fast-relaxed-math")
        key = (hashlib.sha256(source.encode()).hexdigest(), tuple(options))
        prog = self._programs.get(key)
        if prog is None:
            # PoCL 3.0's on-disk kernel cache is not safe across processes: two processes building
            # the same program at once can each fail with an empty log (pocl/pocl#1480; reproduced
            # here: 1-2 failures in 900 builds of six processes, every one gone when built again).
            # A failure on PoCL is therefore built again before it counts; a real compile error
            # fails every time and is reported with its log, a few builds later.
            retries = BUILD_RETRIES if "portable computing language" in self.device.platform.name.lower() else 0
            for attempt in range(retries + 1):
                try:
                    prog = cl.Program(self.context, source).build(options=options)
                    break
                except (cl.RuntimeError, cl.LogicError) as exc:
                    if attempt == retries:   # pyopencl puts the device's build log into the message
                        raise BuildError(stage, options, str(exc), self.name) from None
            self._programs[key] = prog
        return prog

    def kernel(self, stage: str, name: str, defines: Mapping[str, object],
               fast_math: bool = False) -> cl.Kernel:
        """A kernel object of a specialised program, created once.

        Looked up first by ``defines`` in the order given (a call site builds them in one
        order: a hash of the items, ~3 us less per launch than sorting them), else by the
        sorted items, under which the kernel is made once whatever the order."""
        given = (stage, name, tuple(defines.items()), fast_math)
        k = self._kernel_index.get(given)
        if k is not None:
            return k
        index = (stage, name, tuple(sorted(defines.items())), fast_math)
        k = self._kernel_index.get(index)
        if k is not None:
            self._kernel_index[given] = k
            return k
        prog = self.program(stage, defines, fast_math)
        key = (id(prog), name)
        k = self._kernels.get(key)
        if k is None:
            try:
                k = self._kernels[key] = getattr(prog, name)
            except (AttributeError, cl.Error) as exc:  # built, yet the device made no kernel
                raise BuildError(stage, [f"-D{d}={_define(v)}" for d, v in sorted(defines.items())],
                                 f"no kernel {name!r} in the built program: {exc}", self.name) from None
        self._kernel_index[index] = self._kernel_index[given] = k
        return k

    def exclusive_scan_int32(self):
        """pyopencl's exclusive prefix sum over int32 (``scan(src, dst) -> cl.Event``),
        built once per runtime."""
        if "int32" not in self._scans:
            from pyopencl.scan import GenericScanKernel
            self._scans["int32"] = GenericScanKernel(
                self.context, np.int32, arguments="__global const int *src, __global int *dst",
                input_expr="src[i]", scan_expr="a+b", neutral="0",
                output_statement="dst[i] = prev_item;")
        return self._scans["int32"]

    def checked_scan_int32(self):
        """:meth:`exclusive_scan_int32`, checked against a host prefix sum the first time it is
        used: every sort stage indexes memory with the scan's output, so an OpenCL
        implementation that miscomputes it (a driver bug; Oclgrind's uninitialised-value
        checker) is refused before it sends an out-of-range offset into a kernel. RuntimeError
        naming ``CLSPLAT_HOST_SCAN=1`` (the host's scan) when the check fails."""
        scan = self.exclusive_scan_int32()
        if self._scans.get("checked") is not scan:
            x = np.random.default_rng(0).integers(0, 1000, SCAN_SELF_TEST).astype(np.int32)
            a, b = cl_array.to_device(self.queue, x), cl_array.empty(self.queue, x.shape, np.int32)
            scan(a, b, queue=self.queue)
            got, want = b.get(), (np.cumsum(x) - x).astype(np.int32)
            if not np.array_equal(got, want):
                bad = int(np.argmax(got != want))
                raise RuntimeError(
                    f"scan: the device's prefix scan returned inconsistent sums in a self-test of {x.size} "
                    f"values (first wrong at {bad}: {int(got[bad])}, expected {int(want[bad])}); the OpenCL "
                    "implementation miscomputes pyopencl's scan, refusing to index memory with it "
                    "(CLSPLAT_HOST_SCAN=1 scans on the host)")
            self._scans["checked"] = scan
        return scan

    # -- launches -----------------------------------------------------------------------
    def enqueue(self, kernel: cl.Kernel, global_size: int, local_size: int, *args) -> cl.Event:
        """Enqueue ``kernel`` and hold its buffer arguments until the next :meth:`finish`.

        The numpy scalars among ``args`` are declared to pyopencl once per kernel and
        signature (``set_scalar_arg_dtypes``), so its invoker packs them with ``struct``
        (the same bytes): its generic path spent ~9 us of the calling thread per scalar
        (the project kernel's 10 scalars: 95 of its 145 us), the declared path ~0.2."""
        sig = tuple(map(type, args))  # the argument types decide the dtypes
        key = kernel.int_ptr
        if self._arg_dtypes.get(key) != sig:
            kernel.set_scalar_arg_dtypes([np.dtype(t) if issubclass(t, np.generic) else None
                                          for t in sig])
            self._arg_dtypes[key] = sig
        self._in_flight.append(args)  # (its buffers, until the next finish)
        self.launches += 1
        return kernel(self.queue, (global_size,), (local_size,), *args)

    def launch(self, kernel: cl.Kernel, n_items: int, local: int, *args) -> cl.Event:
        """Enqueue over ``n_items`` work-items padded up to a multiple of ``local``, which is
        first lowered to a power of two the kernel allows (``CL_KERNEL_WORK_GROUP_SIZE``)."""
        if n_items > INT32_MAX:
            raise ValueError(f"{kernel.function_name}: {n_items} work-items exceed the int32 index range")
        limit = self._group_limits.get(kernel.int_ptr)
        if limit is None:
            limit = self._group_limits[kernel.int_ptr] = self.kernel_group_limit(kernel)
        while local > limit and local > 1:
            local //= 2
        return self.enqueue(kernel, max(local, -(-n_items // local) * local), local, *args)

    def hold(self, *args) -> None:
        """Keep the buffers among ``args`` alive until the queue has finished with them."""
        self._in_flight.extend(a for a in args if isinstance(a, cl.MemoryObjectHolder))

    def finish(self) -> None:
        """Wait for every queued command, then let go of the arrays they used."""
        self.queue.finish()
        self._in_flight.clear()
        self._finished_at = self.launches

    def plan(self, key: tuple, build: Callable[[], object]) -> object:
        """The render plan's entry for ``key``, built by ``build()`` on first use.

        ``key`` names a stage and everything its entry depends on (shapes, the config, the
        defines; never data values), e.g. the compositing kernel checked against the device's
        limits for one tile size and channel count, or a stage's transient buffers for one
        size. The cache is bounded (:data:`PLAN_CACHE_SIZE` entries, least recently used
        dropped first); an entry whose ``build`` raises is not kept, so a refused request is
        refused again with its one-line error."""
        with self._plan_lock:
            entry = self._plans.get(key, _MISSING)
            if entry is not _MISSING:
                self._plans.move_to_end(key)
                self.plan_hits += 1
                return entry
        entry = build()
        with self._plan_lock:
            self._plans[key] = entry
            self._plans.move_to_end(key)
            while len(self._plans) > PLAN_CACHE_SIZE:
                self._plans.popitem(last=False)
            self.plan_builds += 1
        return entry

    def allowance(self) -> tuple[int, str]:
        """(bytes a render may still allocate here, what bounds them, for a message).

        Every device array is backed by a host tensor, so the host's allowance
        (:func:`clsplat.memory.host_allowance`: available memory, or the process's
        ``RLIMIT_AS`` less what is in use) bounds every device; a device with memory of its
        own (a GPU: no shared host memory) is bounded by its global memory too."""
        allowed, why = host_allowance()
        if not self.shares_host_memory:
            dev = int(self.device.global_mem_size)
            if dev < allowed:
                return dev, f"the device's global memory ({fmt_bytes(dev)}, {self.device.name})"
        return allowed, why

    def check_memory(self, nbytes: int, what: str) -> None:
        """Refuse an allocation of ``nbytes`` for ``what`` (a message naming the argument to
        blame) that exceeds the device's allocation limit, its global memory or what the
        process may allocate now (:meth:`allowance`)."""
        max_alloc = self.max_alloc  # (fills self._limits)
        if nbytes < HOST_CHECK_BYTES and nbytes <= max_alloc and nbytes <= self._limits[1]:
            return  # small: reading /proc per allocation cost more than the render
        if nbytes > max_alloc:
            raise ValueError(f"{what} needs {nbytes >> 20} MiB, over the device allocation limit of "
                             f"{max_alloc >> 20} MiB ({self.device.name})")
        allowed, why = self.allowance()
        allowed = min(allowed, self._limits[1])
        if nbytes > allowed:
            raise ValueError(f"{what} needs {nbytes >> 20} MiB, over the {allowed >> 20} MiB that can "
                             f"be allocated ({why})")

    def array(self, tensor: torch.Tensor, read_only: bool = False,
              keep: bool = False) -> "DeviceArray":
        """``tensor`` on the device; ``read_only``: no command will write it, so reading it
        back never waits (the tensor is the data). A contiguous tensor over a pooled array's
        own memory (e.g. a projection output read back, passed to the next stage) gets that
        array: its buffer is over the same memory (the pool is on where the device computes
        in host memory only). ``keep``: an input the kernels only read, likely passed again
        (a parameter): its array is kept for the next call over the same memory
        (:data:`KEEP_INPUTS` at most, each dropped once nothing but the runtime holds its
        memory; there, kernels read the host memory itself, so the values are always the
        tensor's)."""
        if self._pool_ptrs and tensor.numel() and self.pools:
            a = self._pool_ptrs.get(tensor.data_ptr())
            if (a is not None and a.tensor.shape == tensor.shape and a.tensor.dtype == tensor.dtype
                    and tensor.is_contiguous() and not _moved(a)):
                if read_only:
                    a.read_only = True  # (until empty() hands it out again)
                return a
            if keep and not read_only and tensor.is_contiguous():
                return self._kept_array(tensor)
        # (an array holds the data, never the caller's autograd graph: callers need not detach)
        return DeviceArray(self, tensor.detach() if tensor.requires_grad else tensor, read_only)

    def _kept_array(self, t: torch.Tensor) -> "DeviceArray":
        """:meth:`array` with ``keep`` (pool on, ``t`` contiguous and not empty)."""
        key = (t.data_ptr(), t.shape, t.dtype)
        with self._pool_lock:
            a = self._kept.get(key)
            if a is not None and not _moved(a):
                self._kept.move_to_end(key)
                return a
            if a is not None:  # its memory moved under the buffer (see _moved): make it again
                del self._kept[key]
            if t.untyped_storage().nbytes() > POOL_ARRAY_BYTES:
                return DeviceArray(self, t)
            # Drop, oldest first, kept arrays whose memory nothing else holds any more (the
            # inputs of former calls): up to the first still held (parameters, used by every
            # call, stay at the recent end), and the oldest beyond KEEP_INPUTS.
            while self._kept:
                k = next(iter(self._kept))
                b = self._kept[k]
                if not (len(self._kept) >= KEEP_INPUTS or _is_free(b)):
                    break
                del self._kept[k]
            b = None
            a = DeviceArray(self, t.detach())  # (the storage, not the caller's autograd graph)
            self._kept[key] = a
            h = _holders(a)
            # free: the runtime's own references, one use of the implementation, and of the
            # storage the tensor's, the buffer's numpy view's and _holders' look-up
            a._pool_free, a._pool_refs = (h[0], 1, 3, h[3]), _array_refs(a)
            a._pool_ptr = a.tensor.data_ptr()
            return a

    def empty(self, shape, dtype: torch.dtype, zero: bool = True) -> "DeviceArray":
        """A new array ``shape`` of ``dtype``, zeroed unless ``zero`` is False (then every entry
        a command reads must be written first). Small arrays come from the pool (see the module
        docstring) where the device computes in host memory."""
        shape = tuple(map(int, shape))
        nbytes = math.prod(shape) * dtype.itemsize
        # (the pool is on only on PoCL's CPU device, whose allocation limit is a quarter of the
        # host's memory at least: no pooled size needs the check below)
        if 0 < nbytes <= POOL_ARRAY_BYTES and self.pools:
            return self._pooled(shape, dtype, nbytes, zero)
        if nbytes >= HOST_CHECK_BYTES or nbytes > self.max_alloc:  # the message only when needed
            self.check_memory(nbytes, f"an intermediate array {list(shape)} {dtype}")
        if nbytes and not self.shares_host_memory and self.device_only_arrays:
            return DeviceArray.on_device(self, shape, dtype, zero)  # the copying path (GPUs)
        t = torch.zeros(shape, dtype=dtype) if zero else torch.empty(shape, dtype=dtype)
        return DeviceArray(self, t)

    def from_host(self, values: np.ndarray) -> "DeviceArray":
        """A device array holding ``values`` (a numpy array the device only reads): a pooled
        array written in place where the pool is on, else one over a tensor of the values."""
        nbytes = values.nbytes
        if 0 < nbytes <= POOL_ARRAY_BYTES and self.pools:
            a = self._pooled(values.shape, torch.from_numpy(values[:0]).dtype, nbytes, zero=False)
            np.copyto(a.tensor.numpy(), values, casting="no")
            return a
        return DeviceArray(self, torch.from_numpy(np.ascontiguousarray(values)))

    def staged(self, g: torch.Tensor | None, shape: tuple, dtype: torch.dtype) -> "DeviceArray":
        """An incoming gradient ``g`` (None: zeros) as a contiguous ``dtype`` array ``shape``
        on the device, for kernels to read. Where the pool is on: a pooled array's own memory
        (e.g. a kernel's output) as it is; else copied into a pooled array where a copy is due
        anyway (``contiguous().to(dtype)`` makes one) or costs less than a new buffer (up to
        :data:`STAGE_COPY_BYTES`). Otherwise an array over ``g`` (or that copy), as before.
        None: zeros; up to :data:`POOL_ARRAY_BYTES`, one read-only array per shape kept in the
        render plan (no command writes a staged gradient: the kernels only read them), not
        zeroed again every call."""
        if g is None:
            shape = tuple(shape)
            if math.prod(shape) * dtype.itemsize > POOL_ARRAY_BYTES:
                return self.empty(shape, dtype)
            return self.plan(("staged_zeros", shape, dtype), lambda: DeviceArray(
                self, torch.zeros(shape, dtype=dtype), read_only=True))
        ready = g.dtype == dtype and g.is_contiguous()
        if ready:
            a = self._pool_ptrs.get(g.data_ptr()) if self._pool_ptrs and g.numel() and self.pools else None
            if a is not None and a.tensor.shape == g.shape and a.tensor.dtype == dtype:
                return a  # a pooled array's own memory (e.g. a kernel's output): as it is
        if (tuple(g.shape) == tuple(shape) and self.pools
                and (not ready or g.numel() * dtype.itemsize <= STAGE_COPY_BYTES)):
            a = self.empty(shape, dtype, zero=False)  # (in host memory: written in place)
            a.tensor.copy_(g.detach())
            return a
        return self.array(g.detach().contiguous().to(dtype))

    def _pooled(self, shape: tuple, dtype: torch.dtype, nbytes: int, zero: bool) -> "DeviceArray":
        """A free array of the pool for (shape, dtype), or a new one, kept while the pool has
        room for it (:data:`POOL_PER_SHAPE`, :attr:`pool_limit`)."""
        key = (shape, dtype)
        with self._pool_lock:
            entries = self._pool.get(key)
            if entries is not None:
                self._pool.move_to_end(key)
                # (an array whose memory moved is never free, _is_free: the list is cleared of
                # such arrays below, before a new array takes a place in it)
                for i in range(len(entries)):  # (no enumerate: its tuple would hold ``a``)
                    a = entries[i]
                    if _is_free(a):
                        a.synced_at, a.read_only = self.launches, False
                        if zero:
                            a.tensor.zero_()
                        self.pool_reuses += 1
                        if i + 1 < len(entries):  # the held ones last: the next scan finds the
                            entries.append(entries.pop(i))  # free ones first
                        return a
                self._forget_moved(entries)  # (none free: make room of the moved ones first)
            else:
                entries = self._pool[key] = []
            a = DeviceArray(self, torch.zeros(shape, dtype=dtype) if zero else
                            torch.empty(shape, dtype=dtype))
            if len(entries) < POOL_PER_SHAPE:
                entries.append(a)
                self._pool_ptrs[a.tensor.data_ptr()] = a
                self._pool_bytes += nbytes
                # what holds a pooled array that nothing outside holds: the same references
                # as at every later check (entries, _pool_ptrs, the name ``a``)
                a._pool_free, a._pool_refs = _holders(a), _array_refs(a)
                a._pool_ptr = a.tensor.data_ptr()
                while ((self._pool_bytes > self.pool_limit or len(self._pool) > POOL_SHAPES)
                       and len(self._pool) > 1):
                    self._drop_pool_shape(next(iter(self._pool)))
            return a

    def _forget_moved(self, entries: list) -> None:
        """Drop from ``entries`` (one shape's pooled arrays) those whose memory moved away from
        their buffer (:func:`_moved`): the buffer is over the old memory, so the array can never
        be handed out again; whoever moved it keeps the tensor."""
        for x in [x for x in entries if _moved(x)]:
            entries.remove(x)
            if self._pool_ptrs.get(x._pool_ptr) is x:
                del self._pool_ptrs[x._pool_ptr]
            self._pool_bytes -= x.tensor.numel() * x.tensor.dtype.itemsize

    def _drop_pool_shape(self, key: tuple) -> None:
        """Forget the pooled arrays of ``key`` (their holders keep them; nothing is freed
        under anyone)."""
        for a in self._pool.pop(key):
            if self._pool_ptrs.get(a._pool_ptr) is a:
                del self._pool_ptrs[a._pool_ptr]
            self._pool_bytes -= a.tensor.numel() * a.tensor.dtype.itemsize

    def release_pool(self) -> None:
        """Forget every pooled array (see the module docstring)."""
        with self._pool_lock:
            while self._pool:
                self._drop_pool_shape(next(iter(self._pool)))
            self._kept.clear()


    @contextmanager
    def scratch(self) -> Iterator[Callable[[tuple, torch.dtype], "DeviceArray"]]:
        """``with rt.scratch() as alloc:`` ``alloc(shape, dtype)`` gives a zeroed DeviceArray,
        valid until the block ends, over memory this runtime keeps for the next block.

        A training loop's backward needs the same large intermediate array every step; fresh
        memory of that size comes from the OS with every page faulted in on first touch (90 ms
        for 136 MB here, against 10 ms to zero memory already mapped). The block ends with a
        finished queue, so no command can still use the memory when it is handed out again.
        The runtime keeps the largest block handed back (:meth:`release_scratch` drops it).
        """
        taken: list[torch.Tensor] = []

        def alloc(shape: tuple, dtype: torch.dtype) -> "DeviceArray":
            nbytes = math.prod(int(d) for d in shape) * dtype.itemsize
            if 0 < nbytes <= POOL_ARRAY_BYTES and self.pools:
                return self.empty(shape, dtype)  # small: a pooled array, zeroed
            if nbytes >= HOST_CHECK_BYTES or nbytes > self.max_alloc:
                self.check_memory(nbytes, f"an intermediate array {list(shape)} {dtype}")
            with self._scratch_lock:
                mem = self._scratch_mem
                if mem is not None and mem.numel() >= nbytes:
                    self._scratch_mem = None
                else:
                    mem = None
            if mem is None:
                mem = torch.empty(nbytes, dtype=torch.uint8)
            taken.append(mem)
            t = mem[:nbytes].view(dtype).view(tuple(shape))
            t.zero_()
            return DeviceArray(self, t)

        try:
            yield alloc
        finally:
            if self._finished_at != self.launches:  # a command may still use the memory
                self.finish()
            with self._scratch_lock:
                for mem in taken:
                    if self._scratch_mem is None or mem.numel() > self._scratch_mem.numel():
                        self._scratch_mem = mem

    def release_scratch(self) -> None:
        """Give the memory kept for :meth:`scratch` back."""
        with self._scratch_lock:
            self._scratch_mem = None


def _holders(a: "DeviceArray") -> tuple[int, int, int, int]:
    """What holds a device array's memory: the references to its tensor and its buffer (a
    queued command's hold, :meth:`Runtime.hold`), and the uses of its tensor's implementation
    (autograd's saved tensors, views) and storage (views, numpy arrays, saved outputs). With
    :func:`_array_refs`, what tells a free pooled array from a held one (:func:`_is_free`)."""
    t = a.tensor
    return (sys.getrefcount(t), t._use_count(), torch._C._storage_Use_Count(t.untyped_storage()._cdata),
            sys.getrefcount(a.buffer))


def _array_refs(a: "DeviceArray") -> int:
    """The references to ``a`` (at the depth :func:`_is_free` counts them)."""
    return sys.getrefcount(a)


def _moved(a: "DeviceArray") -> bool:
    """Whether a pooled or kept array's memory moved away from its buffer: ``share_memory_()``
    (which ``torch.multiprocessing`` queues call on every tensor they send), ``resize_()`` or
    ``set_()`` on an alias swap the storage's memory, and the buffer stays over the old one."""
    return a.tensor.data_ptr() != a._pool_ptr


def _is_free(a: "DeviceArray") -> bool:
    """Whether only the pool holds ``a``: the references to it (first: a held array mostly
    fails there, cheaply) and :func:`_holders` are what they were when the pool took it. Called
    with the same references to ``a`` as then (its list, ``_pool_ptrs``, one name)."""
    return sys.getrefcount(a) == a._pool_refs and _holders(a) == a._pool_free and not _moved(a)


def _define(v: object) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return repr(v)
    return str(v)


class DeviceArray:
    """A contiguous torch CPU tensor and the OpenCL buffer that holds its data on the device.

    Zero-copy where the device shares host memory: the buffer is created over the tensor
    (``USE_HOST_PTR``, whose contents the spec defines at creation) and :meth:`host` maps it
    for reading, which brings the tensor up to date and on such devices copies nothing.
    Elsewhere the data are copied in at creation (``COPY_HOST_PTR``) and back by :meth:`host`.
    The tensor must not be read for device results other than through :meth:`host`.
    """

    _pool_free: tuple | None = None  # pooled arrays: _holders() when only the pool holds it
    _pool_refs: int = -1  # its first entry: the references to the array then
    _pool_ptr: int = 0  # pooled and kept arrays: the memory their buffer was made over

    def __init__(self, rt: Runtime, tensor: torch.Tensor, read_only: bool = False) -> None:
        if tensor.device.type != "cpu":
            raise ValueError(f"DeviceArray: tensor must live on the CPU, got {tensor.device}")
        self.rt = rt
        self.tensor = tensor = tensor if tensor.is_contiguous() else tensor.contiguous()
        numel = tensor.numel()
        self.zero_copy = numel > 0 and rt.shares_host_memory
        self.synced_at = rt.launches  # the tensor holds the data as of this many launches
        self.read_only = read_only  # no command writes it: the tensor stays the data
        _check_alloc(rt, tensor)
        if numel == 0:  # OpenCL has no empty buffers; kernels never read it
            self.buffer = cl.Buffer(rt.context, _RW, 16)
        elif self.zero_copy:
            host = tensor.numpy()
            self.buffer = cl.Buffer(rt.context, _RW_HOST_PTR, hostbuf=host)
            if rt.computes_in_host_memory:
                return
            # Hand the tensor's contents to the device through a map for writing and its
            # unmap: free where the memory is shared, and correct where the runtime keeps a
            # copy of its own (or, like Oclgrind's checker, tracks what the host wrote).
            # Non-blocking: the queue is in order, and no queued command can use this buffer.
            mapped, ev = cl.enqueue_map_buffer(rt.queue, self.buffer, cl.map_flags.WRITE, 0,
                                               host.shape, host.dtype, is_blocking=False)
            if mapped.ctypes.data != host.ctypes.data:
                ev.wait()
                np.copyto(mapped, host)
            mapped.base.release(rt.queue)
        else:
            self.buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                                    hostbuf=tensor.numpy())

    @classmethod
    def on_device(cls, rt: Runtime, shape: tuple, dtype: torch.dtype, zero: bool) -> "DeviceArray":
        """A new array ``shape`` of ``dtype`` where the device does not share host memory (the
        copying path: GPUs, ``CLSPLAT_HOST_MEMORY=copy``): its buffer is allocated with no host
        data, zeroed by the device (a fill command) where ``zero``; its tensor is host memory
        that holds nothing until :meth:`host` reads the buffer back. A render's intermediates
        (keys, gradient slots, sort scratch: hundreds of MB for large scenes) then cost neither
        a host memset nor a transfer of zeros or garbage to the device. Where ``zero`` is False
        every entry a command reads must be written first, as on every path."""
        a = cls.__new__(cls)
        a.rt, a.tensor, a.zero_copy, a.read_only = rt, torch.empty(shape, dtype=dtype), False, False
        a.synced_at = -1  # the tensor holds nothing yet: the first read_back copies the buffer
        nbytes = _check_alloc(rt, a.tensor)
        a.buffer = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE, nbytes)
        if zero:
            cl.enqueue_fill_buffer(rt.queue, a.buffer, np.zeros(1, np.uint8), 0, nbytes)
        return a

    def host(self) -> torch.Tensor:
        """The tensor, with every queued command finished and the device's data read back
        (a map and unmap on the zero-copy path, a copy otherwise)."""
        return read_back(self)[0]

    def prefix(self, n: int) -> "DeviceArray":
        """The first ``n`` entries of this 1-D array: a DeviceArray whose tensor is a view of
        this one's and whose buffer is this one's (no new buffer; kernels given it may read
        past ``n``). It holds this array's memory while it lives (a pooled array is not handed
        out again meanwhile: the view and the buffer reference count)."""
        v = DeviceArray.__new__(DeviceArray)
        v.rt, v.tensor, v.buffer = self.rt, self.tensor[:n], self.buffer
        v.zero_copy, v.synced_at, v.read_only = self.zero_copy, self.synced_at, self.read_only
        return v


def _check_alloc(rt: Runtime, tensor: torch.Tensor) -> int:
    """The bytes of a device array over ``tensor``, refused over the device's allocation limit."""
    nbytes = tensor.numel() * tensor.dtype.itemsize
    if nbytes > rt.max_alloc:
        raise ValueError(f"DeviceArray: {list(tensor.shape)} {tensor.dtype} needs {nbytes >> 20} MiB, "
                         f"over the device's {rt.device.max_mem_alloc_size >> 20} MiB allocation limit")
    return nbytes


def read_back(*arrays: DeviceArray) -> list[torch.Tensor]:
    """The tensors of ``arrays`` (one runtime) with every queued command finished and the
    device's data read back, waiting on the queue once for all of them.

    Arrays that no command launched since their creation or last read back can have written
    are returned as they are; on devices that compute in host memory
    (:attr:`Runtime.computes_in_host_memory`) zero-copy arrays need only the finished queue.
    Other zero-copy arrays are mapped for reading without blocking, the queue is finished once, and
    the maps are released (their unmaps stay queued, the buffers held until the next finish);
    on that path nothing is copied unless the runtime kept its own copy. Other arrays are
    read with non-blocking copies before the same single wait.
    """
    live = [a for a in arrays
            if a.tensor.numel() > 0 and not a.read_only and a.synced_at != a.rt.launches]
    if not live:  # nothing launched since these were created or last read back
        return [a.tensor for a in arrays]
    rt = live[0].rt
    maps = []
    in_place = rt.computes_in_host_memory
    for a in live:
        if a.zero_copy and in_place:  # the device wrote the tensor's own memory
            continue
        dst = a.tensor.numpy()
        if a.zero_copy:
            mapped, _ = cl.enqueue_map_buffer(rt.queue, a.buffer, cl.map_flags.READ, 0,
                                              dst.shape, dst.dtype, is_blocking=False)
            maps.append((a, dst, mapped))
        else:
            cl.enqueue_copy(rt.queue, dst, a.buffer, is_blocking=False)
            rt.hold(a.buffer)
    try:
        rt.finish()
        for a, dst, mapped in maps:
            if mapped.ctypes.data != dst.ctypes.data:  # the runtime kept its own copy
                np.copyto(dst, mapped)
    finally:
        for a, _, mapped in maps:
            mapped.base.release(rt.queue)
            rt.hold(a.buffer)
    for a in live:
        a.synced_at = rt.launches
    return [a.tensor for a in arrays]


_RUNTIMES: dict[str, Runtime] = {}


def get_runtime(device: "str | Runtime | None" = None) -> Runtime:
    """The cached runtime for ``device`` (see the module docstring for how it is named)."""
    if isinstance(device, Runtime):
        return device
    if device is not None and not isinstance(device, str):
        raise DeviceError(f"device: expected a string such as 'pocl' or '0:0', got {type(device).__name__}")
    spec = device if device is not None else os.environ.get(_DEVICE_ENV)
    rt = _RUNTIMES.get(spec or "")
    if rt is None:
        rt = _RUNTIMES[spec or ""] = Runtime(_choose(spec))
    return rt


def describe_devices() -> str:
    """A text listing of platforms, devices and the features clsplat uses."""
    lines = []
    devices = list_devices()
    if not devices:
        return "no OpenCL platforms found"
    default = _choose(os.environ.get(_DEVICE_ENV) or None)
    for pi, di, d in devices:
        ext = d.extensions
        feats = {
            "fp64": "cl_khr_fp64" in ext,
            "int64 atomics": "cl_khr_int64_base_atomics" in ext,
            "float atomics": "cl_ext_float_atomics" in ext,
            "subgroups": "cl_khr_subgroups" in ext,
        }
        mark = "*" if d.int_ptr == default.int_ptr else " "
        lines.append(f"{mark} {pi}:{di}  {d.platform.name} | {d.name} | "
                     f"{cl.device_type.to_string(d.type)} | {d.version}")
        lines.append(f"      compute units {d.max_compute_units}, max work-group {d.max_work_group_size}, "
                     f"local mem {d.local_mem_size // 1024} KiB, global mem {d.global_mem_size >> 20} MiB, "
                     f"max alloc {d.max_mem_alloc_size >> 20} MiB")
        lines.append("      " + ", ".join(f"{k}: {'yes' if v else 'no'}" for k, v in feats.items()))
    lines.append(f"(* = default; choose with {_DEVICE_ENV} or device=)")
    return "\n".join(lines)
