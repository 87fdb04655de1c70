"""The dense column solver: one factorisation per distinct reflectance column, shared by every right-hand side
with that column and by the adjoint solve.

- Reciprocal ``F`` (``A_i F_ij = A_j F_ji``): batched Cholesky of the symmetric positive definite form
  ``H = I − R^{1/2} G R^{1/2}``, ``G = A^{1/2} F A^{-1/2}`` (DESIGN.md §1). The forward system is
  ``H w = R^{1/2} u0``, ``E = A^{-1/2} (u0 + G R^{1/2} w)`` with ``u0 = A^{1/2} E0``; the adjoint uses the same
  ``H`` (``Mᵀ = A^{1/2} (I − R G) A^{-1/2}``). Half the flops of LU, no pivoting, and correct under any thread
  count. ``G`` is symmetrised; when ``F`` is reciprocal only up to :data:`~.plan.RECIPROCITY_RTOL`, a few steps of
  iterative refinement against the stored ``F`` remove the difference (LU if they do not converge).
- Otherwise: batched LU of ``I − F R``, guarded: on torch 2.13 CPU, batched ``lu_factor`` with more than one
  thread returns invalid pivots for batches ≥ 2 of matrices with ≳ 200 rows (oneMKL ``SLASWP`` errors), so batched
  LU runs with one thread and its pivots are validated.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass

import torch
from torch import Tensor

from .._threads import caller_threads, small_work_threads, torch_threads
from ..errors import SingularSystemError
from .plan import Stats

__all__ = ["FACTOR_CHUNK_BYTES", "LU_CHUNK_BYTES", "MAX_REFINE", "SMALL_DENSE_ELEMENTS", "dense_solve", "single_thread"]

#: Largest ``[k, c, c]`` buffer factored at once (bytes).
FACTOR_CHUNK_BYTES = 256 * 2**20
LU_CHUNK_BYTES = FACTOR_CHUNK_BYTES  # former name

#: Dense solves with at most this many elements in ``c² N`` (``c`` unknowns, ``N`` columns) run on one thread on
#: the CPU: their element-wise work costs more in waking torch's workers than it gains. One solve of the Cornell
#: box's 56 pieces under the sky (336 unknowns, two solves on one factorisation, 2 cores): 2.3 ms on two threads
#: against 1.4 ms on one with ``OMP_WAIT_POLICY=PASSIVE`` (the benchmarks' setting), 1.25 against 1.4 ms with
#: workers that spin in a tight loop of solves; right after the form factors (65 pieces, 195 unknowns) 1.9 against
#: 1.5 ms (passive) and 1.6 against 1.7 ms (torch's default).
SMALL_DENSE_ELEMENTS = 1 << 18

#: Iterative-refinement steps allowed when ``F`` is reciprocal only approximately.
MAX_REFINE = 30


@contextmanager
def single_thread(t: Tensor) -> Iterator[None]:
    """Run the body with one intra-op thread when ``t`` is a batched CPU tensor (restored afterwards)."""
    with torch_threads(1) if t.device.type == "cpu" and t.ndim >= 3 and t.shape[0] >= 2 else nullcontext():
        yield


def _singular(what: str) -> SingularSystemError:
    return SingularSystemError(
        f"the interreflection system (I - F R) E = E0 is singular or too ill-conditioned ({what}): reflectance 1 "
        "in a closed group of facets, or form-factor rows summing to more than 1? Use reflectance < 1."
    )


@dataclass
class _Packing:
    """Right-hand-side columns grouped by distinct reflectance column: ``[k, c, width]`` slots."""

    order: Tensor
    sinv: Tensor
    slot: Tensor
    width: int
    k: int

    @staticmethod
    def of(inv: Tensor, k: int) -> _Packing:
        order = torch.argsort(inv, stable=True)
        sinv = inv[order]
        counts = torch.bincount(inv, minlength=k)
        starts = counts.cumsum(0) - counts
        slot = torch.arange(inv.numel(), device=inv.device) - starts[sinv]
        return _Packing(order, sinv, slot, int(counts.max()), k)

    def pack(self, b: Tensor) -> Tensor:
        rhs = b.new_zeros(self.k, b.shape[0], self.width)
        rhs[self.sinv, :, self.slot] = b[:, self.order].T
        return rhs

    def unpack(self, sol: Tensor) -> Tensor:
        x = sol.new_empty(sol.shape[1], self.order.numel())
        x[:, self.order] = sol[self.sinv, :, self.slot].T
        return x


def _factor_chunks(c: int, k: int, itemsize: int) -> int:
    return max(1, FACTOR_CHUNK_BYTES // max(c * c * itemsize, 1)) if k else 1


def _cholesky(gs: Tensor, s_uniq: Tensor) -> Tensor | None:
    """Cholesky factors ``[k, c, c]`` of ``H_k = I − s_k s_kᵀ ∘ G`` (``None`` if one is not positive definite)."""
    k, c = int(s_uniq.shape[1]), int(gs.shape[0])
    chunk = _factor_chunks(c, k, gs.element_size())
    out = []
    for k0 in range(0, k, chunk):
        s = s_uniq[:, k0 : k0 + chunk].T  # [kc, c]
        m = gs.unsqueeze(0) * s.unsqueeze(1)  # built in place: one [kc, c, c] buffer
        m.mul_(s.unsqueeze(2)).neg_().diagonal(dim1=-2, dim2=-1).add_(1)
        lower, info = torch.linalg.cholesky_ex(m)
        if bool((info > 0).any()):
            return None
        out.append(lower)
    return torch.cat(out) if len(out) > 1 else out[0]


def _lu(f: Tensor, uniq: Tensor) -> tuple[Tensor, Tensor]:
    """Guarded batched LU of ``I − F diag(r_k)``: one thread for batches on the CPU, pivots validated."""
    k, c = int(uniq.shape[1]), int(f.shape[0])
    chunk = _factor_chunks(c, k, f.element_size())
    lus, pivs = [], []
    for k0 in range(0, k, chunk):
        m = f.unsqueeze(0) * uniq[:, k0 : k0 + chunk].T.unsqueeze(1)
        m.neg_().diagonal(dim1=-2, dim2=-1).add_(1)
        with single_thread(m):
            lu, piv, info = torch.linalg.lu_factor_ex(m)
        if bool(((piv < 1) | (piv > c)).any()):  # never seen with one thread; factor one matrix at a time
            parts = [torch.linalg.lu_factor_ex(m[i]) for i in range(m.shape[0])]
            lu, piv, info = (torch.stack([p[j] for p in parts]) for j in range(3))
            if bool(((piv < 1) | (piv > c)).any()):
                raise RuntimeError(f"torch.linalg.lu_factor_ex returned invalid pivots for {c}x{c} matrices")
        if bool((info > 0).any()):
            raise _singular("zero pivot in the LU factorisation")
        lus.append(lu)
        pivs.append(piv)
    return (torch.cat(lus), torch.cat(pivs)) if len(lus) > 1 else (lus[0], pivs[0])


def _lu_apply(lu: Tensor, piv: Tensor, pk: _Packing, b: Tensor, transpose: bool) -> Tensor:
    rhs = pk.pack(b)
    with single_thread(lu):
        sol = torch.linalg.lu_solve(lu, piv, rhs, adjoint=transpose)
    return pk.unpack(sol)


def _spd_apply(lower: Tensor, pk: _Packing, gs: Tensor, sa: Tensor, s: Tensor, b: Tensor, transpose: bool) -> Tensor:
    """``(I − F R)⁻¹ b`` (or ``(I − R Fᵀ)⁻¹ b``) through the Cholesky factors of the symmetric form."""
    if not transpose:
        u0 = sa * b
        w = pk.unpack(torch.cholesky_solve(pk.pack(s * u0), lower))
        return (u0 + gs @ (s * w)) / sa
    v0 = b / sa
    y = pk.unpack(torch.cholesky_solve(pk.pack(s * (gs @ v0)), lower))
    return sa * (v0 + s * y)


def _refine(
    solve: Callable[[Tensor], Tensor], f: Tensor, r: Tensor, b: Tensor, x: Tensor, transpose: bool
) -> Tensor | None:
    """Iterative refinement of ``x`` against the stored ``F``; ``None`` if it does not converge."""
    eps = torch.finfo(b.dtype).eps
    prev = math.inf
    for _ in range(MAX_REFINE):
        res = b - x + (r * (f.mT @ x) if transpose else f @ (r * x))
        dx = solve(res)
        x = x + dx
        xn = x.norm(dim=0)
        rel = float(torch.where(xn > 0, dx.norm(dim=0) / torch.where(xn > 0, xn, 1), dx.norm(dim=0)).max())
        if rel <= 4 * eps:
            return x
        if rel > 0.5 * prev:
            return x if rel <= math.sqrt(eps) * 1e-3 else None
        prev = rel
    return None


def _spd_solve(
    f: Tensor, areas: Tensor, r: Tensor, b: Tensor, transpose: bool, factor: Tensor | None, uniq: Tensor | None,
    pk: _Packing, exact: bool,
) -> tuple[Tensor | None, Tensor | None]:
    """Solve through the Cholesky factors of the symmetric form (factored here unless given); ``(None, None)``
    when a matrix is not positive definite or the refinement does not converge."""
    sa = areas.sqrt()[:, None]
    g = sa * f / sa.T
    gs = 0.5 * (g + g.mT)
    if factor is None and uniq is not None:
        factor = _cholesky(gs, uniq.sqrt())
    if factor is None:
        return None, None
    s = r.sqrt()
    lower = factor

    def spd(rhs: Tensor) -> Tensor:
        return _spd_apply(lower, pk, gs, sa, s, rhs, transpose)

    x: Tensor | None = spd(b)
    if not exact and x is not None:
        x = _refine(spd, f, r, b, x, transpose)
    return (x, factor) if x is not None else (None, None)


def dense_solve(
    f: Tensor,
    areas: Tensor,
    r: Tensor,
    b: Tensor,
    transpose: bool,
    given: list[Tensor] | None,
    keep: bool,
    stats: Stats,
    *,
    reciprocal: bool = True,
    exact: bool = True,
) -> tuple[Tensor, list[Tensor]]:
    """Solve one component densely: Cholesky of the symmetric form when ``reciprocal``, guarded LU otherwise.
    Small systems on the CPU (``c² N`` at most :data:`SMALL_DENSE_ELEMENTS`) run on one thread.

    Args:
        f: The component's ``[c, c]`` block of ``F`` (dense or CSR).
        areas: ``[c]`` facet areas.
        r, b: ``[c, N]`` reflectance and right-hand-side columns.
        transpose: Solve ``(I − R Fᵀ) x = b`` instead of ``(I − F R) x = b``.
        given: Factors kept by an earlier call with the same ``r`` (``[factor, pivots or empty, inverse]``).
        keep: Return the factors for reuse (the adjoint solve).
        reciprocal: ``F`` is reciprocal (within :data:`~.plan.RECIPROCITY_RTOL`): Cholesky of the symmetric form.
        exact: ``F`` is reciprocal to rounding; otherwise the Cholesky solution is refined against ``F``.

    Returns:
        ``x`` ``[c, N]`` and the kept factors (empty list when not kept).
    """
    small = small_work_threads(f.device, f.shape[0] ** 2 * max(int(r.shape[1]), 1), SMALL_DENSE_ELEMENTS)
    with torch_threads(1) if small else caller_threads():
        if f.layout != torch.strided:
            f = f.to_dense()
        if given is not None and given[0].numel():
            factor, piv, inv = given
            uniq, k = None, int(factor.shape[0])
        else:
            factor = piv = None
            uniq, inv = torch.unique(r, dim=1, return_inverse=True)
            k = int(uniq.shape[1])
        stats.distinct_columns += k
        pk = _Packing.of(inv, k)
        keep = keep and k <= _factor_chunks(int(f.shape[0]), k, f.element_size())
        x = None
        if reciprocal and (piv is None or piv.numel() == 0):
            x, factor = _spd_solve(f, areas, r, b, transpose, factor, uniq, pk, exact)
            piv = b.new_empty(0, dtype=torch.int32)
        if x is None:  # not reciprocal, not positive definite (rows summing to more than 1), or refinement failed
            if piv is None or piv.numel() == 0 or factor is None:
                factor, piv = _lu(f, torch.unique(r, dim=1) if uniq is None else uniq)
            x = _lu_apply(factor, piv, pk, b, transpose)
        if not bool(torch.isfinite(x).all()):
            raise _singular("non-finite result of the dense solve")
        return x, ([factor, piv, inv] if keep and factor is not None else [])
