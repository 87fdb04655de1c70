"""Wall times of the benchmarks: the fastest of a few runs (the machine may be shared; the minimum is the least
disturbed run)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

__all__ = ["best_time", "timed"]


def timed(fn: Callable[[], Any], budget: float = 6.0, reps: int = 3) -> tuple[Any, float]:
    """Run ``fn`` up to ``reps`` times while the runs so far took less than ``budget`` seconds.

    Returns:
        ``(the last result, the fastest time in seconds)``.
    """
    best = math.inf
    spent = 0.0
    out = None
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best = min(best, dt)
        spent += dt
        if spent >= budget:
            break
    return out, best


def best_time(fn: Callable[[], Any], reps: int) -> float:
    """The fastest of ``reps`` runs of ``fn`` in seconds (``inf`` for ``reps <= 0``)."""
    return timed(fn, budget=math.inf, reps=max(reps, 0))[1] if reps > 0 else math.inf
