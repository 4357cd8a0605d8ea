"""Host memory available now, and the check every large host allocation passes first.

Loaders (``.ply`` vertices, decoded images) and the engine's device arrays size their buffers
from numbers a file or an argument gives; :func:`check_host_memory` refuses a size that cannot
fit with a ValueError naming what asked for it, before the allocator is asked and fails (or
the kernel's OOM killer steps in).
"""
from __future__ import annotations

import os

__all__ = ["available_host_memory", "check_host_memory"]


def available_host_memory() -> int:
    """Bytes of host memory available now (Linux ``MemAvailable``; elsewhere the physical
    total). Every device array is backed by a host tensor, so allocations are checked against
    it before they are made, never left to fail in the allocator."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def check_host_memory(nbytes: int, what: str) -> None:
    """ValueError naming ``what`` if ``nbytes`` exceed the host memory available now."""
    host = available_host_memory()
    if nbytes > host:
        raise ValueError(f"{what} needs {nbytes >> 20} MiB, more than the {host >> 20} MiB of host memory "
                         "available now")
