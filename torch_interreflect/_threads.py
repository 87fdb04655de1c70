"""Threads of the compiled loops and of the ray casts, apart from torch's own (internal, shared by every stage).

Inside :func:`compiled_work`, torch runs its glue (indexing, sorting, small reductions between the compiled loops) on
one thread while the compiled loops and Embree's ray casts keep the caller's thread count (:func:`work_threads`).
Torch's OpenMP workers otherwise spin on a core for a while after each of its parallel regions, which is the core the
next compiled loop wants: on the 1,024-facet Cornell box (no occlusion, 2 cores, best of 15) 2 threads took 0.66–0.76
of 1 thread's time, and 0.58 with the glue on one thread.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext

import torch

__all__ = ["SMALL_VECTOR_ELEMENTS", "caller_threads", "compiled_work", "small_work_threads", "torch_threads",
           "work_threads"]

#: Iterations whose vectors hold at most this many elements run their vector operations on one thread (the products
#: keep the caller's threads): waking torch's OpenMP workers for each of them cost more than the work. One CG
#: iteration's vector operations on ``[336, 100]`` columns (2 cores): 54 µs on one thread against 413 µs on two
#: with ``OMP_WAIT_POLICY=PASSIVE`` and 44 µs with spinning workers; at 130,000 elements 351 / 516 / 129 µs.
SMALL_VECTOR_ELEMENTS = 65536

_state = threading.local()


def work_threads() -> int:
    """Threads for compiled loops and ray casts: the caller's torch thread count when the outermost
    :func:`compiled_work` was entered, or torch's current count outside one."""
    n = getattr(_state, "threads", None)
    return torch.get_num_threads() if n is None else int(n)


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads; the caller's count is restored on exit.

    Example:
        >>> import torch
        >>> from torch_interreflect._threads import torch_threads
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     inside = torch.get_num_threads()
        >>> (inside, torch.get_num_threads() == before)
        (1, True)
    """
    prev = torch.get_num_threads()
    if prev != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(prev)


def small_work_threads(device: torch.device, elements: int, limit: int) -> int:
    """The caller's thread count (:func:`work_threads`: torch's, or the caller's inside :func:`compiled_work`) when
    work of ``elements`` elements on ``device`` is small enough (at most ``limit``, on the CPU, with more than one
    thread) for its element-wise operations to run on one thread; else 0. Work above the limit runs on
    :func:`work_threads` (:func:`caller_threads`).

    Example:
        >>> import torch
        >>> from torch_interreflect._threads import small_work_threads
        >>> small_work_threads(torch.device("cpu"), 10**9, 65536)
        0
    """
    threads = work_threads()
    return threads if device.type == "cpu" and threads > 1 and elements <= limit else 0


def caller_threads() -> AbstractContextManager[None]:
    """Run the block on :func:`work_threads` torch threads: large dense work (a factorisation, a product of a big
    matrix, a copy of one) inside :func:`compiled_work` keeps the caller's threads; outside one, nothing changes.

    Returns:
        A context manager (restores torch's thread count on exit).

    Example:
        >>> import torch
        >>> from torch_interreflect._threads import caller_threads, compiled_work
        >>> before = torch.get_num_threads()
        >>> with compiled_work():
        ...     with caller_threads():
        ...         inside = torch.get_num_threads()
        >>> inside == before == torch.get_num_threads()
        True
    """
    n = work_threads()
    return nullcontext() if n == torch.get_num_threads() else torch_threads(n)


@contextmanager
def compiled_work() -> Iterator[int]:
    """Run the block's torch operations on one thread; compiled loops and ray casts in it use :func:`work_threads`.
    Torch's thread count is restored on exit. Yields the work threads.

    Example:
        >>> import torch
        >>> from torch_interreflect._threads import compiled_work, work_threads
        >>> before = torch.get_num_threads()
        >>> with compiled_work() as n:
        ...     inside = torch.get_num_threads()
        >>> (inside, n == before == torch.get_num_threads() == work_threads())
        (1, True)
    """
    outer = getattr(_state, "threads", None)
    n = torch.get_num_threads() if outer is None else int(outer)
    _state.threads = n
    try:
        with torch_threads(1):
            yield n
    finally:
        _state.threads = outer
