"""Memory estimates of the dense kernel, checked before allocating (a clear error instead of torch's raw one).

The dense kernel (:func:`~torch_interreflect.form_factors`) and the back-face / shadow tests of
:mod:`torch_interreflect.lights` hold ``[F, F]`` matrices; above some tens of thousands of facets they need more
memory than a machine has. :func:`check_memory` compares an estimate with :func:`available_memory` and raises
:class:`~torch_interreflect.errors.InsufficientMemoryError` naming both and the way out.
"""

from __future__ import annotations

import os

from ..errors import InsufficientMemoryError

__all__ = ["PAIR_BYTES", "available_memory", "check_memory", "dense_kernel_bytes", "format_bytes"]

#: Peak bytes per facet pair that can exchange light in the quadrature (pair lists, orders, classes, the COO
#: triplets of both directions and their filtered copies; measured ~150-190 B, rounded up).
PAIR_BYTES = 200


def available_memory() -> int:
    """Bytes of memory available to this process: ``MemAvailable`` of ``/proc/meminfo``, else the physical memory."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):  # not available on this platform: do not block
        return 1 << 62


def format_bytes(n: float) -> str:
    """``1.5e9`` → ``"1.50 GB"`` (decimal units)."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.2f} {unit}"
    return f"{int(n)} B"


def dense_kernel_bytes(num_facets: int, pairs: int | None = None, dense_output: bool = True,
                       output_itemsize: int = 8) -> int:
    """Peak bytes of :func:`~torch_interreflect.form_factors` for ``num_facets`` facets.

    Args:
        num_facets: ``F``.
        pairs: Facet pairs that can exchange light (``None``: only the ``[F, F]`` facing matrices are counted).
        dense_output: The result is a dense ``[F, F]`` matrix (float64 while assembling, then the output dtype).
        output_itemsize: Bytes per entry of the output dtype.
    """
    F = int(num_facets)
    total = 3 * F * F  # facing matrix, its mutual part and the upper triangle (bool)
    if pairs is not None:
        total += PAIR_BYTES * int(pairs)
    if dense_output:
        total += (8 + output_itemsize) * F * F
    return total


def check_memory(needed: int, what: str, remedy: str, available: int | None = None) -> None:
    """Raise :class:`InsufficientMemoryError` when ``needed`` bytes exceed the available memory.

    Args:
        needed: Estimated peak bytes.
        what: What needs them (e.g. ``"form_factors on 200000 facets"``).
        remedy: What to do instead (named in the message).
        available: Bytes available (default: :func:`available_memory`).
    """
    avail = available_memory() if available is None else int(available)
    if needed > avail:
        raise InsufficientMemoryError(
            f"{what} needs about {format_bytes(needed)} of memory, but this machine has {format_bytes(avail)} "
            f"available; {remedy}"
        )
