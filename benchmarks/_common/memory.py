"""Memory readings of the benchmarks (Linux ``/proc``; ``getrusage`` or NaN elsewhere).

``VmRSS`` is the resident set now, ``VmHWM`` its high-water mark since exec or since :func:`reset_peak`.
"""

from __future__ import annotations

import math
import resource
from pathlib import Path

__all__ = ["mem_available", "peak_rss_mb", "peak_since", "reset_peak", "status_mb"]


def status_mb(field: str) -> float:
    """A field of ``/proc/self/status`` (``VmRSS``, ``VmHWM``, …) in MiB; NaN where there is none."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return math.nan


def peak_rss_mb() -> float:
    """The process's peak resident set in MiB (``VmHWM``, else ``getrusage``)."""
    v = status_mb("VmHWM")
    return v if math.isfinite(v) else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def reset_peak() -> float:
    """Reset the high-water mark (``clear_refs`` 5) and return the current resident set in MiB (the base of
    :func:`peak_since`); where it cannot be reset, the peak so far."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        v = status_mb("VmRSS")
        if math.isfinite(v):
            return v
    except OSError:
        pass
    return peak_rss_mb()


def peak_since(base: float) -> float:
    """Growth of the high-water mark in MiB since :func:`reset_peak` returned ``base``."""
    return max(0.0, peak_rss_mb() - base)


def mem_available() -> float:
    """``MemAvailable`` of ``/proc/meminfo`` in bytes (``inf`` where unknown)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return math.inf
