"""What depends only on the form-factor matrix, computed once per matrix and cached: connected components of
its nonzero pattern, isolated facets, row sums, reciprocity (:class:`SolvePlan`); and the :class:`Stats` that
the column solvers report back."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..errors import ValueRangeError

__all__ = ["QUADRATURE_DEFAULT_TOL", "RECIPROCITY_RTOL", "Component", "SolvePlan", "Stats", "get_plan",
           "kernel_tolerance", "operator_component"]

RECIPROCITY_RTOL = 1e-4

#: Entry accuracy assumed for a quadrature kernel that did not record its ``tol`` (the default of
#: :func:`~torch_interreflect.formfactors.form_factors`).
QUADRATURE_DEFAULT_TOL = 1e-6


_PLAN_KEY = "_solve_plan"


@dataclass
class Component:
    """A connected group of facets that exchange light (in the nonzero pattern of ``F``)."""

    index: Tensor | None  # global facet indices [c] (long), None when the component is every facet
    size: int
    row_min: float  # smallest row sum of F in the component
    leak: float = 0.0  # area-weighted mean of 1 - row sum: λ_min(I - G) <= leak (singular test for r = 1)
    closure_error: float = 0.0  # closure error of the kernel seen in this component (see _closure)
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
    kernel_tol: float = 0.0  # closure accuracy stated by the kernel (kernel_tolerance); singular test for r = 1
    closure_error: float = 0.0  # closure error the kernel has (largest over components, rounding floor)
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
    plan = _make_plan(matrix.detach(), areas.detach(), key, form_factors.info)
    form_factors.info[_PLAN_KEY] = plan
    return plan


def kernel_tolerance(info: dict[str, Any], dtype: torch.dtype) -> float:
    """The closure (row-sum) accuracy that the producer of the form factors states, or the dtype's floor.

    Read from ``info``: ``closure_tol``, ``tol`` or ``quadrature_tol`` (a relative accuracy per entry bounds the
    row sum's error by the same number), ``estimated_rel_error`` (hierarchical operators), plus
    ``dropped_row_mass`` (:meth:`FormFactors.sparsify`). A quadrature kernel that recorded no tolerance is taken
    at :data:`QUADRATURE_DEFAULT_TOL` (the default of ``form_factors``), a Monte Carlo kernel at
    ``3/sqrt(samples)``; anything else at ``sqrt(eps)`` of its dtype.
    """
    tol = None
    for key in ("closure_tol", "tol", "quadrature_tol", "estimated_rel_error"):
        v = info.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0:
            tol = float(v)
            break
    if tol is None:
        samples = info.get("samples")
        if info.get("method") == "quadrature":
            tol = QUADRATURE_DEFAULT_TOL
        elif info.get("method") == "monte_carlo" and isinstance(samples, int) and samples > 0:
            tol = 3 / math.sqrt(samples)
        else:
            tol = 0.0
    dropped = info.get("dropped_row_mass")
    if isinstance(dropped, (int, float)) and math.isfinite(dropped):
        tol += float(dropped)
    return max(tol, math.sqrt(torch.finfo(dtype).eps))


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


def _check_areas(areas: Tensor, n: int) -> None:
    if not bool(torch.isfinite(areas).all()) or (n and float(areas.min()) <= 0):
        raise ValueRangeError(f"facet areas must be finite and positive; got min {float(areas.min()):.3g}")


@dataclass
class _Structure:
    """What :func:`_sparse_structure` / :func:`_dense_structure` read off the matrix."""

    row_sums: Tensor
    nnz: int
    rel_err: float  # largest |A_i F_ij - A_j F_ji| relative to max |A F|
    worst: tuple[int, int]
    pattern: Any  # scipy CSR pattern for the connected components, or None when labels are known
    labels: np.ndarray | None
    rows: Tensor | None = None  # sparse only: row index of every stored entry
    col: Tensor | None = None


def _sparse_structure(matrix: Tensor, areas: Tensor) -> _Structure:
    import scipy.sparse as sp

    n = int(matrix.shape[0])
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
    rel = err / wmax if wmax > 0 else 0.0
    return _Structure(row_sums, int(vals.numel()), rel, worst, pattern, None, rows, col)


def _dense_labels(nzm: Tensor) -> np.ndarray | None:
    """Fast path: one breadth-first search over the dense pattern usually covers all non-isolated facets
    (label 0; -1 for isolated facets); None when it does not (then scipy finds the components)."""
    sym = nzm | nzm.T
    nonisolated = sym.sum(1) > 0
    if not bool(nonisolated.any()):
        return None
    seen = torch.zeros(nzm.shape[0], dtype=torch.bool, device=nzm.device)
    seen[int(torch.nonzero(nonisolated)[0])] = True
    for _ in range(4):
        nxt = seen | (sym[seen].any(0))
        if bool((nxt == seen).all()):
            break
        seen = nxt
    if bool((seen == nonisolated).all()):
        return np.where(nonisolated.cpu().numpy(), 0, -1)
    return None


def _dense_structure(matrix: Tensor, areas: Tensor) -> _Structure:
    import scipy.sparse as sp

    n = int(matrix.shape[0])
    _check_matrix_values(matrix.reshape(-1), matrix)
    nzm = matrix != 0
    wmat = areas[:, None] * matrix
    d = (wmat - wmat.T).abs()
    wmax = float(wmat.abs().max()) if n else 0.0
    flat = int(d.argmax()) if n else 0
    err, worst = (float(d.reshape(-1)[flat]), (flat // n, flat % n)) if n else (0.0, (0, 0))
    labels = _dense_labels(nzm)
    pattern = sp.csr_matrix(nzm.cpu().numpy()) if labels is None else None
    rel = err / wmax if wmax > 0 else 0.0
    return _Structure(matrix.sum(1), int(nzm.sum()), rel, worst, pattern, labels)


def _component_labels(st: _Structure, n: int) -> np.ndarray:
    """Component label per facet (-1: isolated, i.e. no exchange with any facet nor itself)."""
    if st.labels is not None:
        return st.labels
    from scipy.sparse.csgraph import connected_components

    _, labels = connected_components(st.pattern, directed=True, connection="weak")
    diag_nz = st.pattern.diagonal() != 0
    counts = np.bincount(labels, minlength=int(labels.max()) + 1 if n else 0)
    trivial = (counts[labels] == 1) & ~diag_nz
    return np.where(trivial, -1, labels)


def _closure(rs: np.ndarray, areas: np.ndarray, kernel_tol: float) -> tuple[float, float]:
    """Area-weighted mean leakage ``Σ A_i (1 - s_i) / Σ A_i`` of a component and its closure error: the largest
    ``|1 - s_i|`` when the component is closed within ``kernel_tol`` (its rows should all be 1), else the largest
    excess of a row sum over 1 (no row of an exact kernel exceeds 1)."""
    leak = float((areas * (1 - rs)).sum() / areas.sum())
    if leak <= kernel_tol:
        return leak, float(np.abs(1 - rs).max())
    return leak, float(max((rs - 1).max(), 0.0))


def _components(
    matrix: Tensor, areas: Tensor, st: _Structure, labels: np.ndarray, sparse: bool, kernel_tol: float
) -> list[Component]:
    n = int(matrix.shape[0])
    dev = matrix.device
    comps: list[Component] = []
    rs_np = st.row_sums.detach().cpu().double().numpy()
    a_np = areas.detach().cpu().double().numpy()
    for lab in np.unique(labels[labels >= 0]):
        members = np.nonzero(labels == lab)[0]
        whole = members.size == n
        index = None if whole else torch.as_tensor(members, dtype=torch.long, device=dev)
        leak, closure = _closure(rs_np[members], a_np[members], kernel_tol)
        comp = Component(index=index, size=int(members.size), row_min=float(rs_np[members].min()), leak=leak,
                         closure_error=closure)
        if sparse and not whole and st.rows is not None and st.col is not None:
            local = torch.full((n,), -1, dtype=torch.long, device=dev)
            local[index] = torch.arange(members.size, device=dev)
            pos = torch.nonzero(local[st.rows] >= 0).squeeze(1)
            lrow = local[st.rows[pos]]
            comp.pos = pos
            comp.col = local[st.col[pos]]
            comp.crow = torch.cat(
                [torch.zeros(1, dtype=torch.long, device=dev), torch.bincount(lrow, minlength=members.size).cumsum(0)]
            )
        comps.append(comp)
    return comps


def operator_component(op: Any) -> tuple[Component, float]:
    """The whole operator as one :class:`Component` (leakage and closure error from its row sums), and the closure
    accuracy its producer states (:func:`kernel_tolerance`)."""
    rs = op.row_sums().detach()
    n = int(rs.numel())
    kernel_tol = kernel_tolerance(op.info, op.dtype)
    rs_np, a_np = rs.cpu().double().numpy(), op.areas.detach().cpu().double().numpy()
    leak, closure = _closure(rs_np, a_np, kernel_tol) if n else (1.0, 0.0)
    rounding = math.sqrt(max(n, 1)) * torch.finfo(op.dtype).eps
    comp = Component(index=None, size=n, row_min=float(rs_np.min()) if n else 1.0, leak=leak,
                     closure_error=max(closure, rounding))
    return comp, kernel_tol


def _make_plan(matrix: Tensor, areas: Tensor, key: tuple[Any, ...], info: dict[str, Any]) -> SolvePlan:
    n = int(matrix.shape[0])
    sparse = matrix.layout != torch.strided
    _check_areas(areas, n)
    st = _sparse_structure(matrix, areas) if sparse else _dense_structure(matrix, areas)
    labels = _component_labels(st, n)
    kernel_tol = kernel_tolerance(info, matrix.dtype)
    comps = _components(matrix, areas, st, labels, sparse, kernel_tol)
    rounding = math.sqrt(max(n, 1)) * torch.finfo(matrix.dtype).eps
    return SolvePlan(
        key=key,
        num_facets=n,
        is_sparse=sparse,
        nnz=st.nnz,
        components=comps,
        isolated=int((labels < 0).sum()),
        row_sums=st.row_sums,
        max_row_sum=float(st.row_sums.max()) if n else 0.0,
        reciprocal=st.rel_err <= RECIPROCITY_RTOL,
        reciprocity_error=st.rel_err,
        worst_pair=st.worst,
        kernel_tol=kernel_tol,
        closure_error=max([rounding, *(c.closure_error for c in comps)]),
        extra={"rows": st.rows} if sparse else {},
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
