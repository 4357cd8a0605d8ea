"""Memory this process may still allocate, and the check every large host allocation passes first.

Loaders (``.ply`` vertices, decoded images) and the engine's device arrays size their buffers
from numbers a file or an argument gives; :func:`check_host_memory` refuses a size that cannot
fit with a ValueError naming what asked for it, before the allocator is asked and fails (or
the kernel's OOM killer steps in).

What may be allocated (:func:`host_allowance`) is the smaller of the host memory available
now (Linux ``MemAvailable``) and, where the process runs under an address-space limit
(``RLIMIT_AS``, e.g. ``ulimit -v``), that limit less the address space already in use
(``VmSize``): under such a limit allocations fail long before the machine runs short.
"""
from __future__ import annotations

import os

try:
    import resource
except ImportError:  # not on Windows
    resource = None  # type: ignore[assignment]

__all__ = ["available_host_memory", "address_space_in_use", "host_allowance", "check_host_memory",
           "fmt_bytes"]


def _proc_kib(path: str, key: str) -> int | None:
    """The ``key: N kB`` line of a Linux ``/proc`` file, in bytes; None where there is none."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(key):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def available_host_memory() -> int:
    """Bytes of host memory available now (Linux ``MemAvailable``; elsewhere the physical
    total). Every device array is backed by a host tensor, so allocations are checked against
    it before they are made, never left to fail in the allocator."""
    available = _proc_kib("/proc/meminfo", "MemAvailable:")
    if available is not None:
        return available
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def address_space_in_use() -> int:
    """Bytes of virtual address space this process has mapped (Linux ``VmSize``; 0 elsewhere)."""
    return _proc_kib("/proc/self/status", "VmSize:") or 0


def _address_space_limit() -> int | None:
    """The soft ``RLIMIT_AS`` in bytes, or None where there is none."""
    if resource is None:
        return None
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    return None if soft == resource.RLIM_INFINITY else int(soft)


def fmt_bytes(n: int) -> str:
    """``n`` bytes for a message: GiB with one decimal from 1 GiB on, else MiB."""
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n >> 20} MiB"


def host_allowance() -> tuple[int, str]:
    """(bytes this process may allocate now, what bounds them, for a message).

    The host memory available now, or less under an address-space limit (``RLIMIT_AS``):
    the limit less the address space in use."""
    avail = available_host_memory()
    limit = _address_space_limit()
    if limit is not None:
        used = address_space_in_use()
        left = max(0, limit - used)
        if left < avail:
            return left, (f"the process's address-space limit (RLIMIT_AS {fmt_bytes(limit)}, "
                          f"{fmt_bytes(used)} of it in use)")
    return avail, f"the host memory available now ({fmt_bytes(avail)})"


def check_host_memory(nbytes: int, what: str) -> None:
    """ValueError naming ``what`` if ``nbytes`` exceed what this process may allocate now."""
    allowed, why = host_allowance()
    if nbytes > allowed:
        raise ValueError(f"{what} needs {nbytes >> 20} MiB, more than the {allowed >> 20} MiB that "
                         f"can be allocated ({why})")
