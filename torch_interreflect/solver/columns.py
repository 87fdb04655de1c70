"""The column driver: every system is solved on *columns*.

A system ``(I − F R) x = b`` (or its transpose ``(I − R Fᵀ) x = b``) where ``b`` and the reflectance ``r`` are
``[F, N]`` tensors whose ``N`` columns are the flattened batch and wavelength dimensions. Nothing here is
differentiable; the autograd Function in :mod:`.functions` calls :func:`solve_columns` for the forward solve and
for the adjoint solve. :func:`solve_columns` splits the system into the components of the :class:`SolvePlan`,
drops facets that do not reflect, and calls one of the cores (:mod:`.dense`, :mod:`.krylov`). The helpers
:func:`broadcast_facet_shapes`, :func:`to_columns` and :func:`from_columns` go between ``[..., F, L]`` and columns.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .._checks import as_real_tensor, broadcast_shapes, check_nonnegative, check_reflectance, check_same_device
from ..errors import ShapeError, SingularSystemError
from .dense import dense_solve
from .krylov import cg_block, error_tolerance, neumann_block
from .plan import Component, SolvePlan, Stats

__all__ = ["broadcast_facet_shapes", "check_closed_r1", "component_block", "finish_output", "from_columns",
           "prepare_inputs", "promote_dtypes", "solve_columns", "to_columns"]


# ----------------------------------------------------------------------------------------------- the plan


# ---------------------------------------------------------------------------------------------- statistics


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
        tol: Requested relative error: iterative methods stop each column at the relative residual
            :func:`~.krylov.error_tolerance` (``tol · (1 − r_max ρ)``), so that the error bound is ``tol``.
        factors: dense factors returned by an earlier call with the same ``r`` (reused for the adjoint).
        keep_factors: return the dense factors (3 tensors per block: Cholesky or LU factors, pivots (empty for
            Cholesky), distinct-column index; empty tensors where not kept).

    Returns:
        ``x`` ``[F, N]`` and the list of kept factors.
    """
    stats = stats if stats is not None else Stats()
    x = b.clone()
    out_factors: list[Tensor] = []
    fpos = 0
    closed_tol = max(plan.kernel_tol, math.sqrt(torch.finfo(b.dtype).eps))
    exact = plan.reciprocity_error <= 16 * torch.finfo(b.dtype).eps
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
        check_closed_r1(rc, comp, closed_tol)
        fc = component_block(matrix, comp)
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
            xs, kept = dense_solve(fc, ar, rc_s, bc_s, transpose, given, keep_factors, stats,
                                   reciprocal=plan.reciprocal, exact=exact)
            if keep_factors:
                out_factors.extend(kept if kept else [empty, empty, empty])
        elif method == "cg":
            xs = cg_block(fc, ar, rc_s, bc_s, transpose, error_tolerance(tol, rc_s, plan.max_row_sum), max_iter,
                          stats)
        elif method == "neumann":
            xs = neumann_block(fc, ar, rc_s, bc_s, transpose, error_tolerance(tol, rc_s, plan.max_row_sum),
                               max_iter, stats)
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


def check_closed_r1(r: Tensor, comp: Component, closed_tol: float) -> None:
    """Raise when a column has reflectance 1 on every facet of a component that is closed within the kernel's
    accuracy: its area-weighted mean leakage ``Σ A_i (1 − Σ_j F_ij) / Σ A_i`` bounds the smallest eigenvalue of
    ``I − G`` from above, so a leakage within ``closed_tol`` means a singular system up to the kernel's error."""
    all_one = (r == 1).all(0)
    if bool(all_one.any()) and comp.leak <= closed_tol:
        col = int(torch.nonzero(all_one)[0])
        raise SingularSystemError(
            "the interreflection system (I - F R) E = E0 is singular: reflectance is 1 on every facet of a "
            f"closed group of {comp.size} facets in column {col} (batch x wavelength): the group leaks "
            f"{comp.leak:.3g} of its light (area-weighted 1 - row sum of F, smallest row sum {comp.row_min:.9g}), "
            f"within the form factors' closure accuracy {closed_tol:.3g}, so light never leaves it as far as the "
            "kernel can tell. Use reflectance < 1 or an open scene."
        )


def component_block(matrix: Tensor, comp: Component) -> Tensor:
    """The component's sub-matrix of ``F`` (dense or CSR)."""
    if comp.index is None:
        return matrix
    if matrix.layout == torch.strided:
        return matrix.index_select(0, comp.index).index_select(1, comp.index)
    vals = matrix.values().index_select(0, comp.pos)
    return torch.sparse_csr_tensor(comp.crow, comp.col, vals, (comp.size, comp.size), check_invariants=False)


# ----------------------------------------------------------------------------------------------- dense LU


# ------------------------------------------------------------------------------------ conjugate gradients


# ------------------------------------------------------------------------------------------------- Neumann


def broadcast_facet_shapes(n: int, reflectance: Tensor, e0: Tensor) -> tuple[Tensor, Tensor, torch.Size]:
    """Bring reflectance and E0 to ``[..., F, L]`` form and broadcast them."""
    if reflectance.ndim == 0 or (reflectance.shape[-1] != n and (reflectance.ndim < 2 or reflectance.shape[-2] != n)):
        raise ShapeError(
            f"reflectance must have shape [..., F] (grey) or [..., F, L] with F = {n} facets; got "
            f"{list(reflectance.shape)}"
        )
    grey = reflectance.ndim < 2 or reflectance.shape[-2] != n
    r = reflectance.unsqueeze(-1) if grey else reflectance
    if e0.ndim == 1 and e0.shape[0] == n:
        e = e0.unsqueeze(-1)
    elif e0.ndim >= 2 and e0.shape[-2] == n:
        e = e0
    else:
        raise ShapeError(f"E0 must have shape [..., F, L] (or [F]) with F = {n} facets; got {list(e0.shape)}")
    try:
        shape = broadcast_shapes(r.shape, e.shape)
    except ShapeError as exc:
        raise ShapeError(
            f"reflectance {list(r.shape)} (as [..., F, L]) and E0 {list(e.shape)} do not broadcast: "
            f"wavelength counts L = {r.shape[-1]} vs {e.shape[-1]}, batch dims {list(r.shape[:-2])} vs "
            f"{list(e.shape[:-2])}"
        ) from exc
    return r, e, shape


def promote_dtypes(base: torch.dtype, *tensors: Tensor) -> tuple[torch.dtype, torch.dtype]:
    """``(compute dtype, output dtype)``: the promotion of ``base`` (the form factors') with the floating inputs;
    half precision (float16, bfloat16) is computed in float32 and returned in its own dtype."""
    if not base.is_floating_point:
        raise TypeError(f"form factors must be floating point; got {base}")
    dtype = base
    for t in tensors:
        if t.dtype.is_floating_point:
            dtype = torch.promote_types(dtype, t.dtype)
    compute = torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
    return compute, dtype


def prepare_inputs(
    n: int, device: torch.device, reflectance: Any, E0: Any, base: torch.dtype
) -> tuple[Tensor, Tensor, torch.Size, torch.dtype, bool]:
    """Validate and broadcast the inputs of a solve: ``(r, e0, shape, output dtype, drop_wavelength)``.

    ``r``, ``e0`` are ``[..., F, L]`` in the compute dtype (:func:`promote_dtypes`); ``drop_wavelength`` is True when
    both inputs are ``[F]`` vectors (the output is then ``[F]``: shape in = shape out).
    """
    reflectance = as_real_tensor(reflectance, "reflectance")
    E0 = as_real_tensor(E0, "E0")
    check_same_device(device, "the form factors", reflectance=reflectance, E0=E0)
    compute, out_dtype = promote_dtypes(base, reflectance, E0)
    r, e0, shape = broadcast_facet_shapes(n, reflectance.to(compute), E0.to(compute))
    check_reflectance(r)
    check_nonnegative(e0, "E0", -2)
    return r, e0, shape, out_dtype, reflectance.ndim == 1 and E0.ndim == 1


def finish_output(x: Tensor, shape: torch.Size, out_dtype: torch.dtype, drop_wavelength: bool) -> Tensor:
    """Columns ``[F, N]`` → the output shape and dtype."""
    E = from_columns(x, shape)
    if drop_wavelength:
        E = E.squeeze(-1)
    return E if E.dtype == out_dtype else E.to(out_dtype)


def to_columns(t: Tensor, shape: torch.Size) -> Tensor:
    """``[..., F, L]`` (broadcast to ``shape``) → ``[F, N]``; differentiable (expand sums the gradient)."""
    n = shape[-2]
    return t.expand(shape).movedim(-2, 0).reshape(n, -1)


def from_columns(x: Tensor, shape: torch.Size) -> Tensor:
    n = shape[-2]
    return x.reshape(n, *shape[:-2], shape[-1]).movedim(0, -2)
