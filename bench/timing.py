"""Timing helpers shared by the benchmark reports: device milliseconds of an OpenCL event and
the median/min/max/spread summary of repeated measurements."""
from __future__ import annotations

import numpy as np

__all__ = ["event_ms", "summarise"]


def event_ms(ev) -> float:
    """Device milliseconds of an event. pyopencl's scan kernels return the output Array, whose
    ``events`` hold the launches still pending on it (their sum is used)."""
    if hasattr(ev, "events"):
        return sum(event_ms(e) for e in ev.events)
    return (ev.profile.end - ev.profile.start) * 1e-6


def summarise(values: list[float]) -> dict:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {"median": 0.0, "min": 0.0, "max": 0.0, "spread_pct": 0.0}
    med = float(np.median(a))
    return {"median": med, "min": float(a.min()), "max": float(a.max()),
            "spread_pct": float(100 * (a.max() - a.min()) / med) if med > 0 else 0.0}
