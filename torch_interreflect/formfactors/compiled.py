"""The compiled CPU loops' runtime: loading numba's modules and launching their parallel loops.

:func:`loops` gives the numba module of a stage (``"quadrature"``: the fused contour sums and their adjoints;
``"pairs"``: culling, classification and blocker tests of facet pairs; ``"visibility"``: rays and visible
fractions of the fixed-grid visibility estimate; ``"shadows"``: the shadow edges of the visibility gradient;
``"moments"``: the Galerkin moments on a polynomial basis; ``"contacts"``: the contacts of facet pairs), or
None when numba is missing or disabled
(``TI_DISABLE_NUMBA=1``): callers then use their torch path. :func:`launch` runs one loop with
:func:`~torch_interreflect._threads.work_threads` threads (torch's count, or the caller's inside
:func:`~torch_interreflect._threads.compiled_work`).

numba's on-disk cache (``cache=True``) checks only the file that defines a kernel, not the files of the functions it
inlines: after an edit of :mod:`._numba_contour` alone (a ``git pull`` into the editable install of the README's
commands) the moments' kernel kept running the old inner integral, silently. :func:`refresh_cache` drops the cached
kernels beside these modules whenever any of their sources changed, before the first is imported.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import os
import threading
from collections.abc import Callable
from functools import cache
from pathlib import Path
from types import ModuleType

import numpy as np
import torch

from .._threads import work_threads

__all__ = ["dealt", "launch", "loops", "refresh_cache"]

_MODULES = {"quadrature": "._numba_kernels", "pairs": "._numba_pairs", "visibility": "._numba_visibility",
            "shadows": "._numba_shadows", "moments": "._numba_moments", "contacts": "._numba_contacts"}

#: The file beside numba's cached kernels that records the digest of the sources they were compiled from.
_STAMP = "ti_numba_sources.sha256"

#: One compiled launch at a time (numba's workqueue threading layer does not allow concurrent launches).
_LAUNCH = threading.Lock()


def refresh_cache(source_dir: Path, cache_dir: Path) -> bool:
    """Drop numba's cached kernels of the ``_numba_*.py`` modules in ``source_dir`` (files ``_numba_*.nbi`` and
    ``_numba_*.nbc`` in ``cache_dir``) when the digest of those sources differs from the one recorded there, then
    record it. A folder that cannot be written is left alone (numba does not cache there either). Kernels cached
    elsewhere (``NUMBA_CACHE_DIR``, or numba's per-user folder for a read-only install) are not checked: an upgrade
    there replaces every file, so numba's own check sees each kernel's file change.

    Returns:
        Whether cached kernels were dropped (or a stale record replaced).
    """
    digest = hashlib.sha256()
    for src in sorted(source_dir.glob("_numba_*.py")):
        digest.update(src.name.encode())
        digest.update(src.read_bytes())
    stamp = cache_dir / _STAMP
    try:
        if stamp.read_text() == digest.hexdigest():
            return False
    except OSError:
        pass  # no record yet: kernels cached before it are of unknown sources
    if not cache_dir.is_dir():
        return False
    for old in list(cache_dir.glob("_numba_*.nbi")) + list(cache_dir.glob("_numba_*.nbc")):
        with contextlib.suppress(OSError):  # another process dropped it first, or a read-only cache
            old.unlink()
    with contextlib.suppress(OSError):
        tmp = cache_dir / f"{_STAMP}.{os.getpid()}"
        tmp.write_text(digest.hexdigest())
        os.replace(tmp, stamp)
    return True


@cache
def _fresh_cache() -> None:
    here = Path(__file__).resolve().parent
    refresh_cache(here, here / "__pycache__")


@cache
def loops(stage: str = "quadrature") -> ModuleType | None:
    """The numba module of ``stage`` (``"quadrature"``, ``"pairs"``, ``"visibility"``, ``"shadows"``, ``"moments"``
    or ``"contacts"``), or None
    when numba is missing or disabled (``TI_DISABLE_NUMBA=1``)."""
    if stage not in _MODULES:
        raise ValueError(f"stage must be one of {sorted(_MODULES)}; got {stage!r}")
    if os.environ.get("TI_DISABLE_NUMBA", "") not in ("", "0"):
        return None
    try:
        import numba

        if "NUMBA_THREADING_LAYER" not in os.environ:
            # numba's default picks GNU OpenMP here, which is not fork-safe: a process that forks after a fused
            # kernel (a DataLoader's workers, multiprocessing) was killed ("fork() called from a process already
            # using GNU OpenMP"), and it shares the OpenMP runtime (and thread count) with torch. The workqueue
            # layer is fork-safe and separate; its one limit, no concurrent launches from two threads, is kept by
            # the lock in launch.
            numba.config.THREADING_LAYER = "workqueue"
        _fresh_cache()
        return importlib.import_module(_MODULES[stage], __package__)
    except ImportError:  # pragma: no cover - numba is a dependency; a broken install falls back to torch
        return None


def _launch_threads() -> int:
    """Threads of a compiled launch: :func:`~torch_interreflect._threads.work_threads`, at most numba's pool."""
    import numba

    return max(1, min(work_threads(), numba.config.NUMBA_NUM_THREADS))


def launch(kernel: Callable[..., object], *args: object) -> object:
    """Call a compiled kernel with :func:`~torch_interreflect._threads.work_threads` threads (torch's count outside
    :func:`~torch_interreflect._threads.compiled_work`), leaving torch's thread count as it was.

    numba's OpenMP threading layer shares the OpenMP runtime with torch: setting numba's threads (or launching a
    parallel region) changes what ``torch.get_num_threads()`` returns. Left alone, a user's (or a test worker's)
    ``torch.set_num_threads(1)`` silently became 2 after the first form factors, which also matters for
    correctness (batched LU on torch 2.13 CPU gives invalid pivots with 2 threads).
    """
    import numba

    prev = torch.get_num_threads()
    with _LAUNCH:
        try:
            numba.set_num_threads(_launch_threads())
            return kernel(*args)
        finally:
            torch.set_num_threads(prev)


def dealt(items: np.ndarray) -> np.ndarray:
    """``items`` dealt to the threads of :func:`launch` in turn. A ``prange`` gives each thread one contiguous block
    of iterations, and neighbouring items cost alike (the moments' pairs: a facet's pairs come together, touching
    and occluded ones in runs), so one thread could get most of the work; in this order each block holds every
    ``T``-th item. On the Cornell box cut to 0.2 m (122 pieces, tol 1e-4, 2 threads) the moments took 105 ms
    (median of 10) against 127 ms in index order; the same bits.

    Shape:
        - items: ``[N]`` in, ``[N]`` out (a permutation)
    """
    T = _launch_threads()
    if T == 1 or items.size <= T:
        return items
    return np.concatenate([items[k::T] for k in range(T)])
