"""Private numerical cores behind :func:`torch_interreflect.solve.solve`.

Everything here works on *columns*: a system ``(I − F R) x = b`` (or its transpose ``(I − R Fᵀ) x = b``) where
``b`` and the reflectance ``r`` are ``[F, N]`` tensors whose ``N`` columns are the flattened batch and
wavelength dimensions. Nothing here is differentiable; the autograd Function in ``solve.py`` calls it for the
forward solve and for the adjoint solve.

Pieces:

- :class:`SolvePlan`: what depends only on the form-factor matrix (connected components of its nonzero
  pattern, isolated facets, row sums, reciprocity). Computed once per matrix and cached in
  ``FormFactors.info``.
- :func:`solve_columns`: splits the system into components, drops facets that do not reflect, and calls one of
  the three cores: batched LU (``dense``), conjugate gradients on the symmetric form (``cg``) or the Neumann
  iteration (``neumann``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .errors import SingularSystemError, ValueRangeError

# Largest amount of memory the dense method spends on LU factors at once (bytes). Larger batches of distinct
# reflectance columns are factored in chunks, and the factors are not kept for the backward pass.
LU_CHUNK_BYTES = 256 * 2**20

# Relative tolerance on reciprocity ``A_i F_ij = A_j F_ji`` (relative to ``max A_i F_ij``) below which the
# symmetric form used by conjugate gradients is valid.
RECIPROCITY_RTOL = 1e-4

_PLAN_KEY = "_solve_plan"


# ----------------------------------------------------------------------------------------------- the plan
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


# ---------------------------------------------------------------------------------------------- statistics
@dataclass
class Stats:
    """What the cores report back (filled in place)."""

    iterations: int = 0
    converged: bool = True
    residual: float = 0.0  # largest relative residual of the iterated system when the method stopped
    distinct_columns: int = 0
    blocks: int = 0
    skipped: int = 0


# ------------------------------------------------------------------------------------------- the driver
def solve_columns(
    matrix: Tensor,
    plan: SolvePlan,
    areas: Tensor,
    r: Tensor,
    b: Tensor,
    *,
    transpose: bool,
    method: str,
    tol: float,
    max_iter: int,
    factors: list[Tensor] | None = None,
    keep_factors: bool = False,
    stats: Stats | None = None,
) -> tuple[Tensor, list[Tensor]]:
    """Solve ``(I − F R) x = b`` (``transpose=False``) or ``(I − R Fᵀ) x = b`` column by column.

    Args:
        matrix: ``F`` (detached), dense ``[F, F]`` or sparse CSR.
        plan: :func:`get_plan` of the matrix.
        areas: ``[F]`` facet areas (same dtype as ``b``).
        r: ``[F, N]`` reflectance columns; ``b``: ``[F, N]`` right-hand sides.
        method: ``"dense"``, ``"cg"`` or ``"neumann"``.
        factors: dense LU factors returned by an earlier call with the same ``r`` (reused for the adjoint).
        keep_factors: return the dense LU factors (3 tensors per block; empty tensors where not kept).

    Returns:
        ``x`` ``[F, N]`` and the list of kept factors.
    """
    stats = stats if stats is not None else Stats()
    x = b.clone()
    out_factors: list[Tensor] = []
    fpos = 0
    delta = math.sqrt(torch.finfo(b.dtype).eps)
    stats.skipped = plan.isolated
    empty = b.new_empty(0)
    for comp in plan.components:
        idx = comp.index
        rc = r if idx is None else r.index_select(0, idx)
        bc = b if idx is None else b.index_select(0, idx)
        refl = (rc != 0).any(1)
        if not bool(refl.any()):
            stats.skipped += comp.size
            continue
        all_one = (rc == 1).all(0)
        if bool(all_one.any()) and comp.row_min >= 1 - delta:
            col = int(torch.nonzero(all_one)[0])
            raise SingularSystemError(
                "the interreflection system (I - F R) E = E0 is singular: reflectance is 1 on every facet of a "
                f"closed group of {comp.size} facets (row sums of F >= {comp.row_min:.6g}) in column {col} "
                "(batch x wavelength); light never leaves it. Use reflectance < 1 or an open scene."
            )
        fc = _block(matrix, comp)
        sub_areas = areas if idx is None else areas.index_select(0, idx)
        reduce = not plan.is_sparse and not bool(refl.all())
        if reduce:
            a = torch.nonzero(refl).squeeze(1)
            z = torch.nonzero(~refl).squeeze(1)
            faa = fc.index_select(0, a).index_select(1, a)
            fza = fc.index_select(0, z).index_select(1, a)
            ra, ba, bz = rc.index_select(0, a), bc.index_select(0, a), bc.index_select(0, z)
            if transpose:
                ba = ba + ra * (fza.mT @ bz)
            stats.skipped += int(z.numel())
            fc, rc_s, bc_s, ar = faa, ra, ba, sub_areas.index_select(0, a)
        else:
            rc_s, bc_s, ar = rc, bc, sub_areas
        stats.blocks += 1
        if method == "dense":
            given = None
            if factors is not None:
                given = factors[fpos : fpos + 3]
                fpos += 3
            xs, kept = _dense(fc, rc_s, bc_s, transpose, given, keep_factors, stats)
            if keep_factors:
                out_factors.extend(kept if kept else [empty, empty, empty])
        elif method == "cg":
            xs = _cg_block(fc, ar, rc_s, bc_s, transpose, tol, max_iter, stats)
        elif method == "neumann":
            xs = _neumann_block(fc, ar, rc_s, bc_s, transpose, tol, max_iter, stats)
        else:  # pragma: no cover - validated by the caller
            raise ValueError(f"unknown method {method!r}")
        if reduce:
            xc = torch.empty_like(bc)
            xc[a] = xs
            xc[z] = bz if transpose else bz + fza @ (ra * xs)
        else:
            xc = xs
        if idx is None:
            x = xc
        else:
            x[idx] = xc
    return x, out_factors


def _block(matrix: Tensor, comp: Component) -> Tensor:
    """The component's sub-matrix of ``F`` (dense or CSR)."""
    if comp.index is None:
        return matrix
    if matrix.layout == torch.strided:
        return matrix.index_select(0, comp.index).index_select(1, comp.index)
    vals = matrix.values().index_select(0, comp.pos)
    return torch.sparse_csr_tensor(comp.crow, comp.col, vals, (comp.size, comp.size), check_invariants=False)


# ----------------------------------------------------------------------------------------------- dense LU
def _dense(
    f: Tensor,
    r: Tensor,
    b: Tensor,
    transpose: bool,
    given: list[Tensor] | None,
    keep: bool,
    stats: Stats,
) -> tuple[Tensor, list[Tensor]]:
    """Batched LU: one ``[c, c]`` factorisation per distinct reflectance column, all RHS sharing it at once."""
    if f.layout != torch.strided:
        f = f.to_dense()
    c, n = b.shape
    if given is not None and given[0].numel():
        lu_all, piv_all, inv = given
        uniq = None
        k = int(lu_all.shape[0])
    else:
        lu_all = piv_all = None
        uniq, inv = torch.unique(r, dim=1, return_inverse=True)
        k = int(uniq.shape[1])
    stats.distinct_columns += k
    # pack the right-hand sides by distinct column: rhs[k, :, slot]
    order = torch.argsort(inv, stable=True)
    sinv = inv[order]
    counts = torch.bincount(inv, minlength=k)
    starts = counts.cumsum(0) - counts
    slot = torch.arange(n, device=b.device) - starts[sinv]
    width = int(counts.max())
    rhs = b.new_zeros(k, c, width)
    rhs[sinv, :, slot] = b[:, order].T
    bytes_one = c * c * b.element_size()
    chunk = max(1, LU_CHUNK_BYTES // max(bytes_one, 1))
    keep = keep and k <= chunk
    sols = []
    lus, pivs = [], []
    for k0 in range(0, k, chunk):
        k1 = min(k, k0 + chunk)
        if lu_all is not None and piv_all is not None:
            lu, piv = lu_all[k0:k1], piv_all[k0:k1]
        else:
            m = f.unsqueeze(0) * uniq[:, k0:k1].T.unsqueeze(1)  # built in place: one [k, c, c] buffer
            m.neg_().diagonal(dim1=-2, dim2=-1).add_(1)
            lu, piv, info = torch.linalg.lu_factor_ex(m)
            del m
            if bool((info > 0).any()):
                raise SingularSystemError(
                    "the interreflection system (I - F R) E = E0 is singular (zero pivot in the LU "
                    "factorisation): reflectance 1 in a closed group of facets?"
                )
            if keep:
                lus.append(lu)
                pivs.append(piv)
        sols.append(torch.linalg.lu_solve(lu, piv, rhs[k0:k1], adjoint=transpose))
    sol = torch.cat(sols) if len(sols) > 1 else sols[0]
    x = torch.empty_like(b)
    x[:, order] = sol[sinv, :, slot].T
    if not bool(torch.isfinite(x).all()):
        raise SingularSystemError(
            "the interreflection system (I - F R) E = E0 is singular or too ill-conditioned for the LU "
            "solve (non-finite result)"
        )
    kept: list[Tensor] = []
    if keep and lus:
        kept = [
            torch.cat(lus) if len(lus) > 1 else lus[0],
            torch.cat(pivs) if len(pivs) > 1 else pivs[0],
            inv,
        ]
    return x, kept


# ------------------------------------------------------------------------------------ conjugate gradients
def symmetric_operator(f: Tensor, sqrt_areas: Tensor) -> Tensor:
    """``G = A^{1/2} F A^{-1/2}`` (symmetric when ``F`` is reciprocal), dense or CSR like ``f``."""
    if f.layout == torch.strided:
        return sqrt_areas[:, None] * f / sqrt_areas[None, :]
    csr = f.to_sparse_csr()
    crow, col, vals = csr.crow_indices(), csr.col_indices(), csr.values()
    rows = torch.repeat_interleave(torch.arange(f.shape[0], device=f.device), crow.diff())
    vals = vals * sqrt_areas[rows] / sqrt_areas[col]
    return torch.sparse_csr_tensor(crow, col, vals, tuple(f.shape), check_invariants=False)


def _cg_block(
    f: Tensor, areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float, max_iter: int, stats: Stats
) -> Tensor:
    sa = areas.sqrt()
    g = symmetric_operator(f, sa)
    sa = sa[:, None]
    s = r.sqrt()
    if not transpose:
        u0 = sa * b
        w = _cg(g, s, s * u0, tol, max_iter, stats)
        return (u0 + g @ (s * w)) / sa
    v0 = b / sa
    y = _cg(g, s, s * (g @ v0), tol, max_iter, stats)
    return sa * (v0 + s * y)


def operator_cg(
    apply_f: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float,
    max_iter: int, stats: Stats,
) -> Tensor:
    """:func:`_cg_block` for an ``F`` given only as a product ``apply_f(x) = F @ x`` (``[F, N] -> [F, N]``).

    ``F`` must be exactly reciprocal (``A F`` symmetric); ``G = A^{1/2} F A^{-1/2}`` is applied as
    ``sa * apply_f(v / sa)``.
    """
    sa = areas.sqrt()[:, None]

    def g(v: Tensor) -> Tensor:
        return sa * apply_f(v / sa)

    s = r.sqrt()
    if not transpose:
        u0 = sa * b
        w = _cg(g, s, s * u0, tol, max_iter, stats)
        return (u0 + g(s * w)) / sa
    v0 = b / sa
    y = _cg(g, s, s * g(v0), tol, max_iter, stats)
    return sa * (v0 + s * y)


def operator_neumann(
    apply_f: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float,
    max_iter: int, stats: Stats,
) -> Tensor:
    """:func:`_neumann_block` for an ``F`` given only as a product (reciprocal: ``Fᵀ x = A F (x / A)``)."""
    a = areas[:, None]
    op = (lambda x: a * apply_f(x / a)) if transpose else apply_f
    return _neumann_block(op, areas, r, b, transpose, tol, max_iter, stats)


def _cg(g: Tensor | Callable[[Tensor], Tensor], s: Tensor, rhs: Tensor, tol: float, max_iter: int,
        stats: Stats) -> Tensor:
    """Conjugate gradients on ``(I − S G S) w = rhs`` for all columns at once, one GEMM/SpMM per iteration.

    ``g`` is a matrix or a product callable. Converged columns are written out and dropped from the working set
    (so later products are narrower).
    """
    gmul = g if callable(g) else g.__matmul__
    x = torch.zeros_like(rhs)
    bnorm2 = (rhs * rhs).sum(0)
    active = torch.nonzero(bnorm2 > 0).squeeze(1)
    if active.numel() == 0:
        return x
    thresh = (tol * tol) * bnorm2[active]
    bn2 = bnorm2[active]
    sa = s[:, active]
    res = rhs[:, active].clone()
    p = res.clone()
    xa = torch.zeros_like(res)
    rr = torch.linalg.vecdot(res, res, dim=0)
    it = 0
    worst = 0.0
    while True:
        done = rr <= thresh
        if it >= max_iter:
            done = torch.ones_like(done)
        if bool(done.any()):
            x[:, active[done]] = xa[:, done]
            worst = max(worst, float((rr[done] / bn2[done]).max().sqrt()))
            keep = ~done
            if not bool(keep.any()):
                break
            active, thresh, bn2, rr = active[keep], thresh[keep], bn2[keep], rr[keep]
            sa, res, p, xa = sa[:, keep], res[:, keep], p[:, keep], xa[:, keep]
        ap = torch.addcmul(p, sa, gmul(sa * p), value=-1)
        pap = torch.linalg.vecdot(p, ap, dim=0)
        if bool((pap <= 0).any()):
            raise SingularSystemError(
                "the interreflection system is singular or indefinite (conjugate-gradient breakdown, "
                f"p·Ap = {float(pap.min()):.3g}): reflectance 1 in a closed scene, or form-factor rows "
                "summing to more than 1?"
            )
        alpha = rr / pap
        xa.addcmul_(p, alpha)
        res.addcmul_(ap, alpha, value=-1)
        rr_new = torch.linalg.vecdot(res, res, dim=0)
        p.mul_(rr_new / rr).add_(res)
        rr = rr_new
        it += 1
    stats.iterations = max(stats.iterations, it)
    stats.residual = max(stats.residual, worst)
    if worst > tol:
        stats.converged = False
    return x


# ------------------------------------------------------------------------------------------------- Neumann
def _neumann_block(
    f: Tensor | Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float,
    max_iter: int, stats: Stats,
) -> Tensor:
    """``x ← b + F R x`` (or ``b + R Fᵀ x``) until ``‖x_{k+1} − x_k‖ ≤ tol ‖b‖`` per column (area-weighted).

    ``f`` is a matrix, or a callable that applies ``F`` (``Fᵀ`` when ``transpose``) to ``[F, N]`` columns.
    """
    weight = areas.sqrt()[:, None]
    op = f if callable(f) else None
    if transpose:
        weight = 1 / weight
        if op is None:
            ft = f.mT if f.layout == torch.strided else f.t().to_sparse_csr()
    dense = op is None and f.layout == torch.strided
    w2 = weight * weight
    x = b.clone()
    bnorm2 = torch.linalg.vecdot(b, b * w2, dim=0)
    active = torch.nonzero(bnorm2 > 0).squeeze(1)
    if active.numel() == 0:
        return x
    thresh = (tol * tol) * bnorm2[active]
    bn2 = bnorm2[active]
    ra, ba, xa = r[:, active], b[:, active], x[:, active]
    it = 0
    worst = 0.0
    d2 = bn2
    while True:
        if it < max_iter:
            if op is not None:
                y = torch.addcmul(ba, ra, op(xa)) if transpose else ba + op(ra * xa)
            elif transpose:
                y = torch.addcmul(ba, ra, ft @ xa)
            elif dense:
                y = torch.addmm(ba, f, ra * xa)
            else:
                y = ba + f @ (ra * xa)
            d = y - xa
            d2 = torch.linalg.vecdot(d, d * w2, dim=0)
            xa = y
            it += 1
            done = d2 <= thresh
        else:
            done = torch.ones(active.numel(), dtype=torch.bool, device=b.device)
        if bool(done.any()):
            x[:, active[done]] = xa[:, done]
            worst = max(worst, float((d2[done] / bn2[done]).max().sqrt()))
            keep = ~done
            if not bool(keep.any()):
                break
            active, thresh, bn2 = active[keep], thresh[keep], bn2[keep]
            ra, ba, xa, d2 = ra[:, keep], ba[:, keep], xa[:, keep], d2[keep]
    stats.iterations = max(stats.iterations, it)
    stats.residual = max(stats.residual, worst)
    if worst > tol:
        stats.converged = False
    return x
