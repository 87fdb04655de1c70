"""Thread counts of the compiled loops and the ray casting, and a quiet torch while they run.

torch's intra-op pool is GNU OpenMP, whose workers keep spinning on their cores for a while after every parallel
region (``OMP_WAIT_POLICY`` is read once, when torch loads). numba's and Embree's threads, launched right after a
torch operation on a large tensor, then share the cores with those spinning workers: on 2 cores a compiled loop ran
up to 1.3× slower than alone. :func:`serial_torch` runs torch single-threaded inside a block (its workers stay
asleep; what torch still does there is small), while :func:`loop_threads` keeps giving the compiled loops and the
ray casting the caller's thread count.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["loop_threads", "serial_torch"]

_STATE = threading.local()


def loop_threads() -> int:
    """Threads for compiled loops and ray casting: the caller's ``torch.get_num_threads()`` (as it was when the
    enclosing :func:`serial_torch` began)."""
    n = getattr(_STATE, "threads", None)
    return n if n is not None else torch.get_num_threads()


@contextmanager
def serial_torch() -> Iterator[int]:
    """Run torch on one thread inside the block; :func:`loop_threads` keeps the caller's count. Yields it."""
    outer = getattr(_STATE, "threads", None)
    threads = loop_threads()
    before = torch.get_num_threads()
    _STATE.threads = threads
    torch.set_num_threads(1)
    try:
        yield threads
    finally:
        torch.set_num_threads(before)
        _STATE.threads = outer
