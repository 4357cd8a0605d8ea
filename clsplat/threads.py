"""CPU runtime settings shared by torch and PoCL (OpenMP's idle workers, torch's allocator),
applied once at import.

On a CPU OpenCL device torch's intra-op threads and PoCL's worker threads take turns on the
same cores. torch's OpenMP runtime (libgomp) by default keeps each idle worker spinning for
``GOMP_SPINCOUNT`` = 300,000 iterations (about 3 ms) after every parallel region, so the cores
PoCL's workers need next are busy doing nothing, and under load from other processes the
spinners also delay the workers that hold real work: two torch threads made a loaded step
4.9-7.4x slower than one (bench/RESULTS.md, "Issue 21"). Sleeping at once
(``OMP_WAIT_POLICY=PASSIVE``) removes that collapse but makes every parallel region wake its
workers through the kernel, and on a quiet machine two threads then gained nothing (a
DrivingForward ``small`` step 1.00x, PGT 1.17x the time of one thread). A short spin keeps
back-to-back regions cheap and still frees the core within half a millisecond:
``GOMP_SPINCOUNT=50000`` gave 0.67x (DrivingForward) and 0.84x (PGT), 10,000 0.86x and 0.79x
(same sitting, quiet machine). Intel's runtime gets the nearest setting, ``KMP_BLOCKTIME=1``
(ms; not measured here: torch's Linux wheels use libgomp). PoCL's workers already sleep on a
condition variable when idle.

torch's CPU allocator also gets ``THP_MEM_ALLOC_ENABLE=1``: it page-aligns allocations of 2 MB
and more and lets the kernel back them with transparent huge pages, so the first touch of a fresh
gradient array faults in 2 MB pages instead of 4 kB ones. A render's backward writes such arrays every
call (the SH coefficients' gradient alone is 192 MB at 1M Gaussians), and the faults were a third
of its time there: with it, the 1M-Gaussian backward's wall time 0.78x (300-320 -> 232-259 ms),
PGT ``small`` steps 0.975x, AutoSplat ``demo`` steps unchanged (bench/notes/engine_peers.md; where
the kernel's huge-page policy is ``never`` the variable changes only the alignment).

The runtimes read these variables when they load, so :func:`apply_thread_defaults` runs
from ``clsplat/__init__.py`` before anything imports torch or pyopencl: **import clsplat
before torch** (every ``clsplat`` command and ``python -m clsplat...`` entry point does). A
value the user has set is never overridden (a user's ``OMP_WAIT_POLICY`` leaves the spin count
to it), and the variables are inherited by child processes started after the import. Opt out
with ``CLSPLAT_THREAD_DEFAULTS=0``.
"""
from __future__ import annotations

import os
import sys
import time

__all__ = ["THREAD_DEFAULTS", "OPT_OUT_ENV", "MAX_SHORT_SPIN", "apply_thread_defaults",
           "thread_defaults_active", "busy_cores", "default_torch_threads"]

#: what :func:`apply_thread_defaults` sets where unset (see the module docstring for the numbers)
THREAD_DEFAULTS = {"GOMP_SPINCOUNT": "50000", "KMP_BLOCKTIME": "1", "THP_MEM_ALLOC_ENABLE": "1"}
OPT_OUT_ENV = "CLSPLAT_THREAD_DEFAULTS"
#: the longest libgomp spin (iterations, ~1e5 per ms) counted as "idle workers let go of the
#: core soon", under which extra torch threads are given to idle cores
MAX_SHORT_SPIN = 100_000


def _opted_out(environ) -> bool:
    return environ.get(OPT_OUT_ENV, "1").strip().lower() in ("0", "off", "false", "no")


def apply_thread_defaults(environ=None) -> dict[str, str]:
    """Set :data:`THREAD_DEFAULTS` in ``environ`` (default ``os.environ``) where unset (the spin
    count also only where ``OMP_WAIT_POLICY`` is unset), unless ``CLSPLAT_THREAD_DEFAULTS`` is
    0/off/false/no; returns the variables it set."""
    environ = os.environ if environ is None else environ
    if _opted_out(environ):
        return {}
    added = {k: v for k, v in THREAD_DEFAULTS.items() if k not in environ}
    if "OMP_WAIT_POLICY" in environ:
        added.pop("GOMP_SPINCOUNT", None)
    environ.update(added)
    return added


def _short_spin(environ) -> bool:
    """Whether libgomp's idle workers in a process with ``environ`` let go of the core soon:
    a passive wait policy, or a spin count of at most :data:`MAX_SHORT_SPIN`."""
    if environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE" and "GOMP_SPINCOUNT" not in environ:
        return True
    spin = environ.get("GOMP_SPINCOUNT")
    if spin is None:
        return False
    try:
        return int(spin.strip()) <= MAX_SHORT_SPIN
    except ValueError:  # libgomp's "infinite" or a suffixed count: treat as long
        return False


def thread_defaults_active() -> bool:
    """True when torch's idle OpenMP workers let go of the core soon in this process (see
    :func:`_short_spin`) and that setting was in the environment before torch loaded."""
    return _ACTIVE_AT_IMPORT and _short_spin(os.environ)


#: how long :func:`busy_cores` watches the machine (seconds, once per training command)
BUSY_WINDOW_S = 0.25


def busy_cores(window: float = BUSY_WINDOW_S) -> float:
    """Cores other processes keep busy now: the non-idle share of ``/proc/stat``'s CPU time
    over ``window`` seconds, times the cores (this process sleeps meanwhile, so it counts
    none of its own work). Where ``/proc/stat`` cannot be read: the 1-minute load average,
    which lags by a minute and still counts a run that just ended."""
    def sample() -> tuple[int, int]:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        idle = v[3] + (v[4] if len(v) > 4 else 0)  # idle + iowait
        return sum(v) - idle, sum(v)
    try:
        b0, t0 = sample()
        time.sleep(window)
        b1, t1 = sample()
    except (OSError, ValueError, IndexError):
        try:
            return os.getloadavg()[0]
        except (OSError, AttributeError):
            return 0.0
    cores = os.cpu_count() or 1
    return cores * (b1 - b0) / (t1 - t0) if t1 > t0 else 0.0


def default_torch_threads(cores: int | None = None, load: float | None = None,
                          active: bool | None = None) -> int:
    """torch's intra-op threads for training on a CPU OpenCL device: when idle OpenMP
    workers let go of the core soon (``active``, default :func:`thread_defaults_active`), the
    cores other processes leave idle now (``cores`` minus ``load``, the busy cores, rounded, at
    least 1; they default to this process's cores and :func:`busy_cores`); else 1.

    Measured (bench/RESULTS.md, "Issue 21"): with long-spinning OpenMP workers two torch
    threads made a loaded DrivingForward step 4-5x slower than one; with workers that let go
    of the core that collapse is gone, yet on a loaded machine one thread stays the faster
    (every parallel region waits for a descheduled worker), so extra threads go only to idle
    cores. The busy cores are measured over a quarter second, not read from the load average:
    in a sitting of runs the 1-minute average still held the previous run (0.55 at rest gave
    one thread on an idle machine).
    """
    if not (thread_defaults_active() if active is None else active):
        return 1
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if load is None:
        load = busy_cores()
    return max(1, min(cores, cores - int(round(load))))


# torch's libgomp reads the environment when it loads: if torch was imported before
# clsplat, the defaults set now reach child processes but not this process's OpenMP runtime.
_ACTIVE_AT_IMPORT = "torch" not in sys.modules or _short_spin(os.environ)
apply_thread_defaults()
