"""Krylov column solvers: conjugate gradients on the symmetric positive definite form (DESIGN.md §1) and the
Neumann iteration, on a stored matrix or on an operator (a ``matmul`` callable)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from .._threads import SMALL_VECTOR_ELEMENTS, caller_threads, small_work_threads, torch_threads
from ..errors import SingularSystemError
from .plan import Stats

__all__ = ["bounce_series", "cg", "cg_block", "column_tolerance", "error_tolerance", "neumann_block", "operator_cg",
           "operator_neumann"]



def error_tolerance(tol: float, r: Tensor, rho: float) -> Tensor:
    """Per-column relative residual that makes the solver's error bound ``residual / (1 − r_max ρ)`` at most
    ``tol / 2`` (the other half of the budget is left to rounding and to the form factors' own error).

    ``tol · (1 − r_max ρ) / 2`` per column (``r_max`` its largest reflectance, ``ρ`` the largest row sum of ``F``),
    but never tighter than the ``16 eps / (1 − r_max ρ)`` that rounding allows, and never looser than ``tol``.
    """
    eps = torch.finfo(r.dtype).eps
    gap = (1 - (r.amax(0) if r.shape[0] else torch.zeros(r.shape[1], dtype=r.dtype, device=r.device)) * rho)
    gap = gap.clamp_min(1e-12)
    return torch.minimum(torch.maximum(0.5 * tol * gap, 16 * eps / gap), torch.full_like(gap, tol))


def cg_block(
    f: Tensor, areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float | Tensor, max_iter: int,
    stats: Stats,
) -> Tensor:
    """CG for ``F`` dense or CSR (reciprocal: ``A F`` symmetric): :func:`operator_cg` with ``F``'s own product, so
    ``G = A^{1/2} F A^{-1/2}`` is applied as ``sa * (F @ (v / sa))`` and never formed. Forming it took two passes
    over ``F`` and a copy of it per solve: at 4,656 unknowns (the open room's 776 leaves on the quadratic basis) one
    solve took 170 ms with it against 31 ms without, on one thread (117 against 31 ms on two)."""
    return operator_cg(f.__matmul__, areas, r, b, transpose, tol, max_iter, stats)


def operator_cg(
    apply_f: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float | Tensor,
    max_iter: int, stats: Stats,
) -> Tensor:
    """:func:`cg_block` for an ``F`` given only as a product ``apply_f(x) = F @ x`` (``[F, N] -> [F, N]``).

    ``F`` must be exactly reciprocal (``A F`` symmetric); ``G = A^{1/2} F A^{-1/2}`` is applied as
    ``sa * apply_f(v / sa)``. On the CPU, small systems (:data:`~torch_interreflect._threads.SMALL_VECTOR_ELEMENTS`)
    run everything but ``apply_f`` on one thread (the scaling around the product included).
    """
    threads = small_work_threads(b.device, b.numel(), SMALL_VECTOR_ELEMENTS)
    if threads:  # the threads are settled here: the iteration itself (_cg) must not wrap the scaling again
        with torch_threads(1):
            return _operator_cg(_at_threads(apply_f, threads), areas, r, b, transpose, tol, max_iter, stats, _cg)
    with caller_threads():
        return _operator_cg(apply_f, areas, r, b, transpose, tol, max_iter, stats, _cg)


def _operator_cg(apply_f: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool,
                 tol: float | Tensor, max_iter: int, stats: Stats, cg: Callable[..., Tensor]) -> Tensor:
    sa = areas.sqrt()[:, None]

    def g(v: Tensor) -> Tensor:
        return sa * apply_f(v / sa)

    s = r.sqrt()
    if not transpose:
        u0 = sa * b
        w = cg(g, s, s * u0, tol, max_iter, stats)
        return (u0 + g(s * w)) / sa
    v0 = b / sa
    y = cg(g, s, s * g(v0), tol, max_iter, stats)
    return sa * (v0 + s * y)


def operator_neumann(
    apply_f: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool, tol: float | Tensor,
    max_iter: int, stats: Stats,
) -> Tensor:
    """:func:`neumann_block` for an ``F`` given only as a product (reciprocal: ``Fᵀ x = A F (x / A)``)."""
    a = areas[:, None]
    op = (lambda x: a * apply_f(x / a)) if transpose else apply_f
    return neumann_block(op, areas, r, b, transpose, tol, max_iter, stats)


def column_tolerance(tol: float | Tensor, n: int, like: Tensor) -> Tensor:
    """``tol`` as one relative tolerance per column ``[n]``."""
    return torch.as_tensor(tol, dtype=like.dtype, device=like.device).expand(n)


def cg(g: Tensor | Callable[[Tensor], Tensor], s: Tensor, rhs: Tensor, tol: float | Tensor, max_iter: int,
        stats: Stats) -> Tensor:
    """Conjugate gradients on ``(I − S G S) w = rhs`` for all columns at once, one GEMM/SpMM per iteration.

    ``g`` is a matrix or a product callable; ``tol`` the relative residual to reach, one number or one per column.
    Converged columns are frozen (their step 0) and, once they are :data:`COMPACT_FRACTION` of the working set,
    written out and dropped from it (so later products are narrower). On the
    CPU, small systems (at most :data:`~torch_interreflect._threads.SMALL_VECTOR_ELEMENTS` in ``rhs``) run the
    vector operations on one thread and the products on the caller's.
    """
    gmul = g if callable(g) else g.__matmul__
    threads = small_work_threads(rhs.device, rhs.numel(), SMALL_VECTOR_ELEMENTS)
    if not threads:
        with caller_threads():
            return _cg(gmul, s, rhs, tol, max_iter, stats)
    with torch_threads(1):
        return _cg(_at_threads(gmul, threads), s, rhs, tol, max_iter, stats)


def _at_threads(fn: Callable[[Tensor], Tensor], threads: int) -> Callable[[Tensor], Tensor]:
    """``fn`` run with ``threads`` torch threads (the products, inside a one-thread iteration)."""

    def call(v: Tensor) -> Tensor:
        with torch_threads(threads):
            return fn(v)

    return call


#: Converged columns stay in the working set, frozen (their step 0), until they are this fraction of it; then they
#: are written out and dropped at once. Dropping each batch as it converged took 4 column gathers of every vector
#: each time: on 100 reflectance draws of the Cornell box's 50 pieces (quadratic basis, 300 unknowns; the two CG
#: solves of ``solve_moments_sky``) the median went from 12.3 to 11.0 ms in float32 and from 21.4 to 17.8 ms in
#: float64 at 0.5 (0.75 and 1 measured alike, within noise; below 0.5 the gathers come back).
COMPACT_FRACTION = 0.5


def _cg(gmul: Callable[[Tensor], Tensor], s: Tensor, rhs: Tensor, tol: float | Tensor, max_iter: int,
        stats: Stats) -> Tensor:
    x = torch.zeros_like(rhs)
    bnorm2 = (rhs * rhs).sum(0)
    active = torch.nonzero(bnorm2 > 0).squeeze(1)
    if active.numel() == 0:
        return x
    tols = column_tolerance(tol, rhs.shape[1], rhs)
    thresh = tols[active].square() * bnorm2[active]
    bn2 = bnorm2[active]
    sa = s[:, active]
    failed = False
    res = rhs[:, active].clone()
    p = res.clone()
    xa = torch.zeros_like(res)
    rr = torch.linalg.vecdot(res, res, dim=0)
    frozen = torch.zeros_like(rr, dtype=torch.bool)
    it = 0
    worst = 0.0
    while True:
        done = (rr <= thresh) | frozen
        if it >= max_iter:
            failed = failed or not bool(done.all())
            done = torch.ones_like(done)
        new = done & ~frozen
        if bool(new.any()):  # frozen from here: res and rr stay as they are now
            worst = max(worst, float((rr[new] / bn2[new]).max().sqrt()))
            frozen = done
            n_done = int(frozen.sum())
            if n_done == frozen.numel():
                x[:, active] = xa
                break
            # (a column whose residual is not finite, float32 overflow, leaves at once: frozen, its p would spread NaN)
            if n_done >= COMPACT_FRACTION * frozen.numel() or not bool(rr[new].isfinite().all()):
                x[:, active[frozen]] = xa[:, frozen]
                keep = ~frozen
                active, thresh, bn2, rr, frozen = active[keep], thresh[keep], bn2[keep], rr[keep], frozen[keep]
                sa, res, p, xa = sa[:, keep], res[:, keep], p[:, keep], xa[:, keep]
        ap = torch.addcmul(p, sa, gmul(sa * p), value=-1)
        pap = torch.linalg.vecdot(p, ap, dim=0)
        if bool(((pap <= 0) & ~frozen).any()):
            raise SingularSystemError(
                "the interreflection system is singular or indefinite (conjugate-gradient breakdown, "
                f"p·Ap = {float(pap[~frozen].min()):.3g}): reflectance 1 in a closed scene, or form-factor rows "
                "summing to more than 1?"
            )
        alpha = (rr / pap).masked_fill_(frozen, 0.0)
        xa.addcmul_(p, alpha)
        res.addcmul_(ap, alpha, value=-1)
        rr_new = torch.linalg.vecdot(res, res, dim=0)
        p.mul_((rr_new / rr).masked_fill_(frozen, 0.0)).add_(res)
        rr = rr_new
        it += 1
    stats.iterations = max(stats.iterations, it)
    stats.residual = max(stats.residual, worst)
    if failed:
        stats.converged = False
    return x


def neumann_block(
    f: Tensor | Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, transpose: bool,
    tol: float | Tensor, max_iter: int, stats: Stats,
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
    thresh = column_tolerance(tol, b.shape[1], b)[active].square() * bnorm2[active]
    bn2 = bnorm2[active]
    failed = False
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
            failed = failed or not bool((d2 <= thresh).all())
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
    if failed:
        stats.converged = False
    return x


def bounce_series(matmul: Callable[[Tensor], Tensor], r: Tensor, b: Tensor, bounces: int) -> Tensor:
    """The paper's n-bounce model on columns: ``x = Σ_{k < n} (F R)^k b`` by ``n − 1`` products ``x ← b + F (r x)``.

    Differentiable by autograd through the products (memory grows with ``bounces``).

    Shape:
        - r, b, output: ``[F, N]``
    """
    x = b
    for _ in range(bounces - 1):
        x = b + matmul(r * x)
    return x
