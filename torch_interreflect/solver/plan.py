"""What depends only on the form-factor matrix, computed once per matrix and cached: connected components of
its nonzero pattern, isolated facets, row sums, reciprocity (:class:`SolvePlan`); and the :class:`Stats` that
the column solvers report back."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import ValueRangeError

__all__ = ["RECIPROCITY_RTOL", "Component", "SolvePlan", "Stats", "get_plan"]



RECIPROCITY_RTOL = 1e-4


_PLAN_KEY = "_solve_plan"


@dataclass
class Component:
    """A connected group of facets that exchange light (in the nonzero pattern of ``F``)."""

    index: Tensor | None  # global facet indices [c] (long), None when the component is every facet
    size: int
    row_min: float  # smallest row sum of F in the component (closure test for the singular case)
    pos: Tensor | None = None  # sparse only: positions of the component's stored entries in values()
    crow: Tensor | None = None  # sparse only: local CSR structure
    col: Tensor | None = None


@dataclass
class SolvePlan:
    """What the solver needs to know about a form-factor matrix, independent of reflectance and light."""

    key: tuple[Any, ...]
    num_facets: int
    is_sparse: bool
    nnz: int
    components: list[Component]
    isolated: int  # facets with a zero row and a zero column: E = E0 there, no solve
    row_sums: Tensor
    max_row_sum: float
    reciprocal: bool
    reciprocity_error: float
    worst_pair: tuple[int, int]
    extra: dict[str, Any] = field(default_factory=dict)


def _matrix_key(matrix: Tensor, areas: Tensor) -> tuple[Any, ...]:
    if matrix.layout == torch.strided:
        ptr = matrix.data_ptr()
        ver = matrix._version
    else:
        ptr = matrix.values().data_ptr()
        ver = (matrix._version, matrix.values()._version)
    return (
        id(matrix),
        ptr,
        ver,
        tuple(matrix.shape),
        matrix.dtype,
        str(matrix.device),
        id(areas),
        areas.data_ptr(),
        areas._version,
    )


def get_plan(form_factors: Any) -> SolvePlan:
    """The :class:`SolvePlan` of ``form_factors``, cached in ``form_factors.info`` (recomputed on change)."""
    matrix, areas = form_factors.matrix, form_factors.areas
    key = _matrix_key(matrix, areas)
    cached = form_factors.info.get(_PLAN_KEY)
    if isinstance(cached, SolvePlan) and cached.key == key:
        return cached
    plan = _make_plan(matrix.detach(), areas.detach(), key)
    form_factors.info[_PLAN_KEY] = plan
    return plan


def _check_matrix_values(values: Tensor, dense: Tensor | None) -> None:
    if values.numel() == 0:
        return
    bad = ~torch.isfinite(values)
    if bool(bad.any()):
        where = ""
        if dense is not None:
            i, j = (int(t) for t in torch.nonzero(~torch.isfinite(dense))[0])
            where = f" at F[{i}, {j}]"
        raise ValueRangeError(
            f"form factors must be finite; got {int(bad.sum())} non-finite entries (first: "
            f"{float(values[bad][0])}{where})"
        )
    vmin = float(values.min())
    if vmin < -1e-7:
        raise ValueRangeError(f"form factors must be nonnegative; got min {vmin:.3g}")


def _make_plan(matrix: Tensor, areas: Tensor, key: tuple[Any, ...]) -> SolvePlan:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = int(matrix.shape[0])
    sparse = matrix.layout != torch.strided
    if not bool(torch.isfinite(areas).all()) or (n and float(areas.min()) <= 0):
        raise ValueRangeError(f"facet areas must be finite and positive; got min {float(areas.min()):.3g}")
    if sparse:
        csr = matrix.to_sparse_csr()
        crow, col, vals = csr.crow_indices(), csr.col_indices(), csr.values()
        _check_matrix_values(vals, None)
        rows = torch.repeat_interleave(torch.arange(n, device=matrix.device), crow.diff())
        nz = vals != 0
        r_np, c_np = rows[nz].cpu().numpy(), col[nz].cpu().numpy()
        pattern = sp.csr_matrix((np.ones(r_np.size, dtype=np.int8), (r_np, c_np)), shape=(n, n))
        row_sums = torch.zeros(n, dtype=vals.dtype, device=vals.device).index_add_(0, rows, vals)
        w = sp.csr_matrix(((areas[rows] * vals).cpu().numpy(), (rows.cpu().numpy(), col.cpu().numpy())), shape=(n, n))
        diff = abs(w - w.T).tocoo()
        wmax = float(abs(w).max()) if w.nnz else 0.0
        if diff.nnz:
            k = int(np.argmax(diff.data))
            err, worst = float(diff.data[k]), (int(diff.row[k]), int(diff.col[k]))
        else:
            err, worst = 0.0, (0, 0)
        nnz = int(vals.numel())
    else:
        _check_matrix_values(matrix.reshape(-1), matrix)
        nzm = matrix != 0
        row_sums = matrix.sum(1)
        wmat = areas[:, None] * matrix
        d = (wmat - wmat.T).abs()
        wmax = float(wmat.abs().max()) if n else 0.0
        flat = int(d.argmax()) if n else 0
        err, worst = (float(d.reshape(-1)[flat]), (flat // n, flat % n)) if n else (0.0, (0, 0))
        pattern = None
        nnz = int(nzm.sum())
        rows = crow = col = None
        # fast path: one breadth-first search over the dense pattern usually covers all non-isolated facets
        sym = nzm | nzm.T
        deg = sym.sum(1)
        nonisolated = deg > 0
        labels = None
        if bool(nonisolated.any()):
            seen = torch.zeros(n, dtype=torch.bool, device=matrix.device)
            seen[int(torch.nonzero(nonisolated)[0])] = True
            for _ in range(4):
                nxt = seen | (sym[seen].any(0))
                if bool((nxt == seen).all()):
                    break
                seen = nxt
            if bool((seen == nonisolated).all()):
                labels = np.where(nonisolated.cpu().numpy(), 0, -1)
        if labels is None:
            pattern = sp.csr_matrix(nzm.cpu().numpy())
    rel_err = err / wmax if wmax > 0 else 0.0

    if pattern is not None:
        _, labels = connected_components(pattern, directed=True, connection="weak")
        diag_nz = pattern.diagonal() != 0
        counts = np.bincount(labels, minlength=int(labels.max()) + 1 if n else 0)
        trivial = (counts[labels] == 1) & ~diag_nz
        labels = np.where(trivial, -1, labels)
    isolated = int((labels < 0).sum())
    comps: list[Component] = []
    uniq = np.unique(labels[labels >= 0])
    rs_cpu = row_sums.cpu()
    for lab in uniq:
        members = np.nonzero(labels == lab)[0]
        whole = members.size == n
        index = None if whole else torch.as_tensor(members, dtype=torch.long, device=matrix.device)
        comp = Component(index=index, size=int(members.size), row_min=float(rs_cpu[members].min()))
        if sparse and not whole:
            local = torch.full((n,), -1, dtype=torch.long, device=matrix.device)
            local[index] = torch.arange(members.size, device=matrix.device)
            pos = torch.nonzero(local[rows] >= 0).squeeze(1)
            lrow = local[rows[pos]]
            comp.pos = pos
            comp.col = local[col[pos]]
            comp.crow = torch.cat(
                [
                    torch.zeros(1, dtype=torch.long, device=matrix.device),
                    torch.bincount(lrow, minlength=members.size).cumsum(0),
                ]
            )
        comps.append(comp)
    extra: dict[str, Any] = {}
    if sparse:
        extra["rows"] = rows
    return SolvePlan(
        key=key,
        num_facets=n,
        is_sparse=sparse,
        nnz=nnz,
        components=comps,
        isolated=isolated,
        row_sums=row_sums,
        max_row_sum=float(row_sums.max()) if n else 0.0,
        reciprocal=rel_err <= RECIPROCITY_RTOL,
        reciprocity_error=rel_err,
        worst_pair=worst,
        extra=extra,
    )


@dataclass
class Stats:
    """What the cores report back (filled in place)."""

    iterations: int = 0
    converged: bool = True
    residual: float = 0.0  # largest relative residual of the iterated system when the method stopped
    distinct_columns: int = 0
    blocks: int = 0
    skipped: int = 0
