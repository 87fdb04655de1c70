"""Rendering and writing samples, in this process or in worker processes, one index at a time.

:func:`~.generator.generate` hands the indices it has to render to :func:`render_indices`, which yields
``(index, warning)`` as each sample is written. With ``workers > 1`` this process and ``workers − 1`` ``spawn``-ed
processes render at once, each on ``threads`` torch threads, so a single ``interreflect generate`` uses every core;
the bytes of each sample are the same as in one process (a sample depends only on its index and the configuration).

A worker costs a start-up of ~3 s (importing torch, colour-science and the compiled kernels), about 20 samples at
64 × 64: :func:`auto_workers` starts one per :data:`MIN_SAMPLES_PER_WORKER` samples to render, up to the usable cores.
"""

from __future__ import annotations

import collections
import multiprocessing
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path

import torch

from ..errors import AccuracyWarning, collect_warnings
from .config import GeneratorConfig
from .sample import render_sample
from .storage import write_sample

__all__ = ["MIN_SAMPLES_PER_WORKER", "QUEUED_PER_WORKER", "auto_workers", "render_indices", "usable_cores"]

#: Samples to render per extra worker process that ``workers="auto"`` starts (a worker's start-up ≈ 20 samples).
MIN_SAMPLES_PER_WORKER = 32

#: Samples handed to each worker process ahead of time (the rest wait in this process, which renders too).
QUEUED_PER_WORKER = 3


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the platform has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def auto_workers(todo: int) -> int:
    """Worker processes for ``todo`` samples: one per :data:`MIN_SAMPLES_PER_WORKER`, at least 1, at most the cores.

    Example:
        >>> from torch_interreflect.training.workers import auto_workers
        >>> auto_workers(10)
        1
    """
    return max(1, min(usable_cores(), todo // MIN_SAMPLES_PER_WORKER))


def _render_and_write(out: Path, config: GeneratorConfig, index: int) -> tuple[int, str | None]:
    """Render sample ``index``, write it; return the index and the first ``AccuracyWarning`` of its solves."""
    with collect_warnings(AccuracyWarning) as got:  # reported once, at the end of the run
        sample = render_sample(config, index)
    write_sample(out, sample)
    return index, (got[0] if got else None)


def _start_worker(threads: int | None) -> None:
    if threads is not None:
        torch.set_num_threads(int(threads))


def render_indices(
    out: Path, config: GeneratorConfig, indices: Sequence[int], *, workers: int = 1, threads: int | None = 1
) -> Iterator[tuple[int, str | None]]:
    """Render and write the samples ``indices`` of ``config`` into ``out``, yielding ``(index, warning)`` as each
    is written (in index order with one worker, in order of completion with more).

    Args:
        out: Output folder (exists).
        config: The generator configuration.
        indices: Sample indices to render.
        workers: Processes rendering at once, this one included (it renders with the caller's torch threads).
        threads: Torch threads in each spawned worker process (``None``: torch's default).

    Raises:
        ValueError: ``workers`` below 1.
        Exception: The first error a sample raised; the samples not yet started are cancelled.
    """
    if int(workers) < 1:
        raise ValueError(f"workers must be at least 1; got {workers}")
    if workers == 1 or len(indices) <= 1:
        for k in indices:
            yield _render_and_write(out, config, k)
        return
    # this process renders too, from the end of the list, while workers - 1 spawned processes start (~3 s) and
    # take indices from the front, a few at a time
    ctx = multiprocessing.get_context("spawn")  # fork after torch / OpenMP / numba threads have started can hang
    helpers = int(workers) - 1
    queue = collections.deque(indices)
    with ProcessPoolExecutor(helpers, mp_context=ctx, initializer=_start_worker, initargs=(threads,)) as pool:
        pending: set[Future] = set()
        try:
            while queue or pending:
                while queue and len(pending) < QUEUED_PER_WORKER * helpers:
                    pending.add(pool.submit(_render_and_write, out, config, queue.popleft()))
                if queue:
                    yield _render_and_write(out, config, queue.pop())
                    done = {f for f in pending if f.done()}
                else:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                pending -= done
                for f in sorted(done, key=lambda f: f.result()[0]):
                    yield f.result()
        finally:
            for f in pending:
                f.cancel()
