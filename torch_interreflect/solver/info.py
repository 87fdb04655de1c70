"""What :func:`~torch_interreflect.solve` reports (:class:`SolveInfo`), and its convergence warning."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ..errors import AccuracyWarning, ConvergenceWarning
from .krylov import error_tolerance
from .plan import SolvePlan, Stats

__all__ = ["Solution", "SolveInfo", "error_report", "make_info", "relative_bound_estimate", "solver_error",
           "warn_if_inaccurate",
           "warn_if_not_converged"]


@dataclass
class SolveInfo:
    """What :func:`solve` did (``return_info=True``).

    Attributes:
        method: Method used (``"dense"``, ``"cg"``, ``"neumann"``, or ``"series"`` for a finite ``bounces``).
        iterations: Iterations of the iterative method (largest over components); 0 for ``dense``;
            ``bounces − 1`` for the n-bounce series.
        residual: Largest relative residual over columns, ``‖A^{1/2}(E0 − (I − F R) E)‖ / ‖A^{1/2} E0‖``,
            recomputed from the returned ``E`` (for a finite ``bounces``: the first term left out).
        error_bound: Largest over columns of
            ``(‖A^{1/2} residual‖ + ε_F r_max ‖A^{1/2} E‖) / (1 − r_max ρ)`` with ``ρ = max row sum of F``
            (``inf`` if ``r_max ρ ≥ 1``) and ``ε_F`` the closure error of the form factors
            (``extra["kernel_closure_error"]``: how far the rows of a closed group of facets miss 1, or exceed it):
            the solver's error plus the kernel's, as amplified by the system; in W·m⁻¹·nm⁻¹ (area-weighted norm).
        relative_error_bound: The same divided by ``‖A^{1/2} E‖`` (per column, largest): the relative error of
            ``E`` that :func:`solve` compares with ``tol`` (it warns when the bound is above it).
        converged: Whether the iterative method reached ``tol`` (always True for ``dense`` and the series).
        num_components: Independent groups of facets solved separately.
        facets_skipped: Facets outside every solve: isolated facets (no exchange) plus, per component,
            facets with reflectance 0 in every column (dense method only; CG gives them w = 0 anyway).
        num_columns: Right-hand sides solved (batch × wavelength).
        distinct_columns: Distinct reflectance columns factored (``dense``); 0 otherwise.
    """

    method: str
    iterations: int
    residual: float
    error_bound: float
    relative_error_bound: float
    converged: bool
    num_components: int
    facets_skipped: int
    num_columns: int
    distinct_columns: int = 0
    extra: dict[str, Any] = field(default_factory=dict)


class Solution(NamedTuple):
    """What :func:`~torch_interreflect.solver.solve_with_info` returns: the irradiance and the report."""

    E: Tensor
    info: SolveInfo


def relative_bound_estimate(residual: float, closure_error: float, rmax: float, rho: float) -> float:
    """A-priori relative error bound ``(residual + ε_F r_max) / (1 − r_max ρ)`` (``inf`` when ``r_max ρ ≥ 1``)."""
    gap = 1 - rmax * rho
    return math.inf if gap <= 0 else (residual + closure_error * rmax) / gap


def solver_error(method: str, stats: Stats, r: Tensor, tol: float, rho: float, n: int) -> float:
    """A-priori relative residual of the solve, scaled so that :func:`relative_bound_estimate` divides it by
    ``1 − r_max ρ``: ``n·eps`` for ``dense``; for a converged iterative solve the per-column targets of
    :func:`~.krylov.error_tolerance` (at most ``tol/2`` after division); otherwise the residual reached."""
    eps = torch.finfo(r.dtype).eps
    if method == "dense":
        return n * eps
    if not stats.converged or r.numel() == 0:
        return stats.residual
    gap = (1 - r.amax(0) * rho).clamp_min(1e-12)
    gap_all = float(gap.min())
    return float((error_tolerance(tol, r, rho) / gap).max()) * gap_all


#: The form factors' closure error amplified more than this many times by ``1/(1 − r_max ρ)`` is worth a warning.
KERNEL_AMPLIFICATION = 10.0


def warn_if_inaccurate(
    bound: float, tol: float, dtype: torch.dtype, closure_error: float, rmax: float, rho: float, what: str,
    stacklevel: int = 2,
) -> None:
    """:class:`AccuracyWarning` when the relative error bound is above ``max(tol, sqrt(eps))`` (a float32 solve
    cannot promise better than ~3e-4 near r = 1; it warns above that), for the solver's own part of the bound, or
    for the form factors' part when the system amplifies their closure error more than :data:`KERNEL_AMPLIFICATION`
    times (the kernel's own error, passed through a well-conditioned system, is the kernel's business: its
    tolerance is what the user chose when building it; r near 1 in a closed scene is the solver's)."""
    floor = max(tol, math.sqrt(torch.finfo(dtype).eps))
    gap = 1 - rmax * rho
    kernel_part = math.inf if gap <= 0 else closure_error * rmax / gap
    solver_part = bound - kernel_part if math.isfinite(kernel_part) else 0.0
    amplified = gap <= 0 or kernel_part > KERNEL_AMPLIFICATION * closure_error
    if not (solver_part > floor or (kernel_part > floor and amplified)):
        return
    amp = "inf" if gap <= 0 else f"{1 / gap:.3g}"
    w = AccuracyWarning(
        f"{what}: the relative error bound {bound:.3g} is above the requested tol={tol:g}. With reflectance up to "
        f"{rmax:.9g} and form-factor rows summing to at most {rho:.9g}, errors are amplified by "
        f"1/(1 - r_max * rho) = {amp}, and the form factors' closure error {closure_error:.3g} (how far rows of a "
        f"closed scene miss 1) alone contributes {closure_error * rmax / gap if gap > 0 else math.inf:.3g}. "
        "Use reflectance further from 1, more accurate form factors (form_factors(quadrature_tol=...)), or float64."
    )
    w.bound = bound  # type: ignore[attr-defined]
    warnings.warn(w, stacklevel=stacklevel + 1)


def warn_if_not_converged(stats: Stats, what: str) -> None:
    if not stats.converged:
        w = ConvergenceWarning(
            f"{what} did not converge within max_iter={stats.iterations} iterations: relative residual "
            f"{stats.residual:.3g} reached (raise max_iter or tol)"
        )
        w.residual = stats.residual  # type: ignore[attr-defined]
        w.iterations = stats.iterations  # type: ignore[attr-defined]
        warnings.warn(w, stacklevel=3)


def error_report(
    matmul: Callable[[Tensor], Tensor], areas: Tensor, r: Tensor, b: Tensor, x: Tensor, closure_error: float,
    rho: float,
) -> tuple[float, float, float]:
    """Largest relative residual, error bound and relative error bound over the columns (see :class:`SolveInfo`)."""
    with torch.no_grad():
        r, b, x = r.detach(), b.detach(), x.detach()
        res = b - x + matmul(r * x)
        sa = areas.sqrt()[:, None]
        rn = (sa * res).norm(dim=0)
        bn = (sa * b).norm(dim=0)
        rel = torch.where(bn > 0, rn / torch.where(bn > 0, bn, 1), rn)
        rmax = r.amax(0) if r.shape[0] else torch.zeros_like(rn)
        denom = 1 - rmax * rho
        num = rn + closure_error * rmax * (sa * x).norm(dim=0)
        bound = torch.where(denom > 0, num / denom.clamp_min(1e-300), torch.full_like(rn, math.inf))
        bound = torch.where(num == 0, torch.zeros_like(bound), bound)
        xn = (sa * x).norm(dim=0)
        relb = torch.where(xn > 0, bound / torch.where(xn > 0, xn, 1), bound)
    if rn.numel() == 0:
        return 0.0, 0.0, 0.0
    return float(rel.max()), float(bound.max()), float(relb.max())


def make_info(
    method: str,
    iterations: int,
    converged: bool,
    plan: SolvePlan,
    matrix: Tensor,
    areas: Tensor,
    r_cols: Tensor,
    b_cols: Tensor,
    x: Tensor,
    stats: Stats,
) -> SolveInfo:
    m = matrix.detach()
    rel, bound, relb = error_report(m.__matmul__, areas, r_cols, b_cols, x, plan.closure_error, plan.max_row_sum)
    return SolveInfo(
        method=method,
        iterations=int(iterations),
        residual=rel,
        error_bound=bound,
        relative_error_bound=relb,
        converged=bool(converged),
        num_components=len(plan.components),
        facets_skipped=stats.skipped if method != "series" else 0,
        num_columns=int(b_cols.shape[1]),
        distinct_columns=stats.distinct_columns,
        extra={"blocks_solved": stats.blocks, "reciprocity_error": plan.reciprocity_error,
               "kernel_closure_error": plan.closure_error, "kernel_tol": plan.kernel_tol},
    )
