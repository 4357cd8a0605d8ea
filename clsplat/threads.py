"""CPU thread settings shared by torch's OpenMP runtime and PoCL, applied once at import.

On a CPU OpenCL device torch's intra-op threads and PoCL's worker threads take turns on the
same cores. torch's OpenMP runtime (libgomp) by default keeps each worker spinning for a
while after every parallel region (``GOMP_SPINCOUNT``, 300,000 iterations: milliseconds), so
the cores PoCL's workers need next are busy doing nothing; under load from other processes
the spinning workers also delay the ones that hold real work (bench/RESULTS.md, "issue 21").
With ``OMP_WAIT_POLICY=PASSIVE`` idle OpenMP workers sleep at once (libgomp, and Intel's
runtime through ``KMP_BLOCKTIME=0``), and PoCL's workers already sleep on a condition
variable when idle, so both runtimes can use every core.

The runtimes read these variables when they load, so :func:`apply_thread_defaults` runs
from ``clsplat/__init__.py`` before anything imports torch or pyopencl: **import clsplat
before torch** (every ``clsplat`` command and ``python -m clsplat...`` entry point does). A
value the user has set is never overridden, and the variables are inherited by child
processes started after the import. Opt out with ``CLSPLAT_THREAD_DEFAULTS=0``.
"""
from __future__ import annotations

import os
import sys

__all__ = ["THREAD_DEFAULTS", "OPT_OUT_ENV", "apply_thread_defaults", "thread_defaults_active",
           "default_torch_threads"]

#: what :func:`apply_thread_defaults` sets where unset
THREAD_DEFAULTS = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}
OPT_OUT_ENV = "CLSPLAT_THREAD_DEFAULTS"


def _opted_out(environ) -> bool:
    return environ.get(OPT_OUT_ENV, "1").strip().lower() in ("0", "off", "false", "no")


def apply_thread_defaults(environ=None) -> dict[str, str]:
    """Set :data:`THREAD_DEFAULTS` in ``environ`` (default ``os.environ``) where unset,
    unless ``CLSPLAT_THREAD_DEFAULTS`` is 0/off/false/no; returns the variables it set."""
    environ = os.environ if environ is None else environ
    if _opted_out(environ):
        return {}
    added = {k: v for k, v in THREAD_DEFAULTS.items() if k not in environ}
    environ.update(added)
    return added


def thread_defaults_active() -> bool:
    """True when torch's OpenMP workers sleep when idle in this process: the wait policy is
    passive now and was either set before clsplat was imported or set by that import before
    torch loaded."""
    return _ACTIVE_AT_IMPORT and os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE"


def default_torch_threads(cores: int | None = None, load: float | None = None,
                          active: bool | None = None) -> int:
    """torch's intra-op threads for training on a CPU OpenCL device: when idle OpenMP
    workers sleep (``active``, default :func:`thread_defaults_active`), the cores other
    processes leave idle now (``cores`` minus the 1-minute ``load`` average, rounded, at
    least 1; both default to this machine's); else 1.

    Measured (bench/RESULTS.md, "issue 21"): with spinning OpenMP workers two torch threads
    made a loaded DrivingForward step 4-5x slower than one; with sleeping workers that
    collapse is gone, yet on a loaded machine one thread stays the faster (every parallel
    region waits for a descheduled worker), so extra threads go only to idle cores.
    """
    if not (thread_defaults_active() if active is None else active):
        return 1
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if load is None:
        try:
            load = os.getloadavg()[0]
        except (OSError, AttributeError):
            load = 0.0
    return max(1, min(cores, cores - int(round(load))))


# torch's libgomp reads the environment when it loads: if torch was imported before
# clsplat, the defaults set now reach child processes but not this process's OpenMP runtime.
_ACTIVE_AT_IMPORT = ("torch" not in sys.modules
                     or os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE")
apply_thread_defaults()
