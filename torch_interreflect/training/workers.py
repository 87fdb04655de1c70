"""Rendering and writing samples, in this process or in worker processes, one index at a time.

:func:`~.generator.generate` hands the indices it has to render to :func:`render_indices`, which yields
``(index, warning)`` as each sample is written. With ``workers > 1`` this process and up to ``workers − 1``
``spawn``-ed processes render at once, each on ``threads`` torch threads, so a single ``interreflect generate`` uses
every core; the bytes of each sample are the same as in one process (a sample depends only on its index and the
configuration).

A worker costs a start-up of ~3 s (importing torch, colour-science and the compiled kernels), about 20 samples at
64 × 64: :func:`auto_workers` starts one per :data:`MIN_SAMPLES_PER_WORKER` samples to render, up to the usable cores.
Workers exit when this process dies (killed included), and the warnings they raise are raised again here, under this
process's filters.
"""

from __future__ import annotations

import collections
import math
import multiprocessing
import os
import threading
import warnings
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import torch

from .._checks import check_count
from ..errors import AccuracyWarning, ValueRangeError, collect_warnings
from .config import GeneratorConfig
from .sample import render_sample
from .storage import write_sample

__all__ = [
    "CGROUP_QUOTA", "MIN_SAMPLES_PER_WORKER", "QUEUED_PER_WORKER", "auto_workers", "check_workers", "cpu_quota",
    "processes", "render_indices", "usable_cores",
]

#: Samples to render per extra worker process that ``workers="auto"`` starts (a worker's start-up ≈ 20 samples).
MIN_SAMPLES_PER_WORKER = 32

#: Samples handed to each worker process ahead of time (the rest wait in this process, which renders too).
QUEUED_PER_WORKER = 3


#: Linux's files of a container's CPU quota: cgroup v2 (``"quota period"`` or ``"max period"``), then cgroup v1 (the
#: quota and the period in microseconds, ``-1``: none).
CGROUP_QUOTA = (Path("/sys/fs/cgroup/cpu.max"),
                (Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us"), Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us")))


def cpu_quota(files: tuple[Path, tuple[Path, Path]] | None = None) -> int | None:
    """Whole cores a container's CPU quota allows (rounded up), or ``None`` without a quota (or off Linux).
    ``files``: where to read it (:data:`CGROUP_QUOTA` by default).

    Example:
        >>> from torch_interreflect.training.workers import cpu_quota
        >>> q = cpu_quota()
        >>> q is None or q >= 1
        True
    """
    v2, (quota_v1, period_v1) = CGROUP_QUOTA if files is None else files
    try:
        quota, period = v2.read_text().split()[:2]
    except (OSError, ValueError):
        try:
            quota, period = quota_v1.read_text().strip(), period_v1.read_text().strip()
        except OSError:
            return None
    try:
        q, p = float(quota), float(period)
    except ValueError:  # "max": no quota
        return None
    return max(1, math.ceil(q / p)) if q > 0 and p > 0 else None


def usable_cores() -> int:
    """CPU cores this process may run on: its affinity mask where the platform has one (a SLURM task's own cores),
    and at most the container's CPU quota (:func:`cpu_quota`; Docker's ``--cpus``, a Kubernetes limit), which the
    mask does not show."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        cores = os.cpu_count() or 1
    quota = cpu_quota()
    return min(cores, quota) if quota is not None else cores


def auto_workers(todo: int, threads: int = 1) -> int:
    """Processes for ``todo`` samples on ``threads`` torch threads each: one per :data:`MIN_SAMPLES_PER_WORKER`
    samples, at least 1, at most the usable cores over ``threads``.

    Example:
        >>> from torch_interreflect.training.workers import auto_workers
        >>> auto_workers(10)
        1
    """
    return max(1, min(usable_cores() // max(1, int(threads)), todo // MIN_SAMPLES_PER_WORKER))


def check_workers(workers: Any, *, allow_auto: bool = True) -> int | str:
    """``workers`` as a positive int, or ``"auto"`` (where allowed).

    Raises:
        ValueRangeError: anything else (a ``ValueError``).
    """
    if allow_auto and workers == "auto":
        return "auto"
    try:
        return int(check_count(workers, "workers"))  # type: ignore[arg-type]
    except ValueRangeError as exc:
        raise ValueRangeError(f"workers must be a positive int{' or ' + repr('auto') if allow_auto else ''}; got "
                              f"{workers!r}") from exc


def processes(workers: int, count: int) -> int:
    """Processes that :func:`render_indices` uses for ``count`` samples: ``workers``, at most one per sample.

    Example:
        >>> from torch_interreflect.training.workers import processes
        >>> processes(4, 2), processes(2, 0)
        (2, 1)
    """
    return max(1, min(int(workers), int(count)))


def _render_and_write(out: Path, config: GeneratorConfig, index: int) -> tuple[int, str | None]:
    """Render sample ``index``, write it; return the index and the first ``AccuracyWarning`` of its solves."""
    with collect_warnings(AccuracyWarning) as got:  # reported once, at the end of the run
        sample = render_sample(config, index)
    write_sample(out, sample)
    return index, (got[0] if got else None)


def _render_in_worker(out: Path, config: GeneratorConfig, index: int) -> tuple[int, str | None, list[tuple]]:
    """:func:`_render_and_write` in a worker process, with the other warnings it raised, to raise again in the
    parent (``(message, category, filename, lineno)``)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        k, accuracy = _render_and_write(out, config, index)
    return k, accuracy, [(str(w.message), w.category, w.filename, w.lineno) for w in caught]


def _exit_with_parent() -> None:
    parent = multiprocessing.parent_process()
    if parent is not None:
        parent.join()  # returns when the parent process has ended, however it ended
        os._exit(1)


def _start_worker(threads: int) -> None:
    torch.set_num_threads(int(threads))
    # a parent killed by a signal runs no shutdown: without this, its workers would wait for work forever
    threading.Thread(target=_exit_with_parent, daemon=True, name="ti-parent-watch").start()


def render_indices(
    out: Path, config: GeneratorConfig, indices: Sequence[int], *, workers: int = 1, threads: int | None = 1
) -> Iterator[tuple[int, str | None]]:
    """Render and write the samples ``indices`` of ``config`` into ``out``, yielding ``(index, warning)`` as each
    is written (in the order of ``indices`` in one process, in order of completion with more).

    Args:
        out: Output folder (exists).
        config: The generator configuration.
        indices: Sample indices to render.
        workers: Processes rendering at once, this one included (it renders with the caller's torch threads, and
            always the last index); at most one per index (:func:`processes`).
        threads: Torch threads in each spawned process (``None``: this process's current count).

    Raises:
        ValueRangeError: ``workers`` not a positive int.
        Exception: The first error a sample raised; the samples not yet started are cancelled.
    """
    n = processes(int(check_workers(workers, allow_auto=False)), len(indices))
    if n == 1:
        for k in indices:
            yield _render_and_write(out, config, k)
        return
    # this process renders too, from the end of the list, while the n - 1 spawned processes start (~3 s) and take
    # indices from the front, a few at a time; the last index always stays here
    ctx = multiprocessing.get_context("spawn")  # fork after torch / OpenMP / numba threads have started can hang
    helpers = n - 1
    queue = collections.deque(indices)
    threads = torch.get_num_threads() if threads is None else int(threads)
    with ProcessPoolExecutor(helpers, mp_context=ctx, initializer=_start_worker, initargs=(threads,)) as pool:
        pending: set[Future] = set()
        try:
            while queue or pending:
                while len(queue) > 1 and len(pending) < QUEUED_PER_WORKER * helpers:
                    pending.add(pool.submit(_render_in_worker, out, config, queue.popleft()))
                if queue:
                    yield _render_and_write(out, config, queue.pop())
                    done = {f for f in pending if f.done()}
                else:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                pending -= done
                for f in sorted(done, key=lambda f: f.result()[0]):
                    k, accuracy, other = f.result()
                    for message, category, filename, lineno in other:
                        warnings.warn_explicit(message, category, filename, lineno)
                    yield k, accuracy
        finally:
            for f in pending:
                f.cancel()
