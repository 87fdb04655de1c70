"""What :func:`~torch_interreflect.solve` reports (:class:`SolveInfo`), and its convergence warning."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from ..errors import ConvergenceWarning
from .plan import SolvePlan, Stats

__all__ = ["SolveInfo", "make_info", "warn_if_not_converged"]



@dataclass
class SolveInfo:
    """What :func:`solve` did (``return_info=True``).

    Attributes:
        method: Method used (``"dense"``, ``"cg"``, ``"neumann"``, or ``"series"`` for a finite ``bounces``).
        iterations: Iterations of the iterative method (largest over components); 0 for ``dense``;
            ``bounces − 1`` for the n-bounce series.
        residual: Largest relative residual over columns, ``‖A^{1/2}(E0 − (I − F R) E)‖ / ‖A^{1/2} E0‖``,
            recomputed from the returned ``E`` (for a finite ``bounces``: the first term left out).
        error_bound: Largest over columns of ``‖A^{1/2}(E − E*)‖ ≤ ‖A^{1/2} residual‖ / (1 − r_max ρ)`` with
            ``ρ = max row sum of F`` (``inf`` if ``r_max ρ ≥ 1``); in W·m⁻¹·nm⁻¹ (area-weighted norm).
        relative_error_bound: The same divided by ``‖A^{1/2} E0‖`` (per column, largest).
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


def warn_if_not_converged(stats: Stats, what: str) -> None:
    if not stats.converged:
        w = ConvergenceWarning(
            f"{what} did not converge within max_iter={stats.iterations} iterations: relative residual "
            f"{stats.residual:.3g} reached (raise max_iter or tol)"
        )
        w.residual = stats.residual  # type: ignore[attr-defined]
        w.iterations = stats.iterations  # type: ignore[attr-defined]
        warnings.warn(w, stacklevel=3)


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
    with torch.no_grad():
        m, r, b, x = matrix.detach(), r_cols.detach(), b_cols.detach(), x.detach()
        res = b - x + m @ (r * x)
        sa = areas.sqrt()[:, None]
        rn = (sa * res).norm(dim=0)
        bn = (sa * b).norm(dim=0)
        rel = torch.where(bn > 0, rn / torch.where(bn > 0, bn, 1), rn)
        rmax = r.amax(0) if r.shape[0] else torch.zeros_like(rn)
        denom = 1 - rmax * plan.max_row_sum
        bound = torch.where(denom > 0, rn / denom.clamp_min(1e-300), torch.full_like(rn, math.inf))
        bound = torch.where(rn == 0, torch.zeros_like(bound), bound)
        relb = torch.where(bn > 0, bound / torch.where(bn > 0, bn, 1), bound)
    empty = rn.numel() == 0
    return SolveInfo(
        method=method,
        iterations=int(iterations),
        residual=0.0 if empty else float(rel.max()),
        error_bound=0.0 if empty else float(bound.max()),
        relative_error_bound=0.0 if empty else float(relb.max()),
        converged=bool(converged),
        num_components=len(plan.components),
        facets_skipped=stats.skipped if method != "series" else 0,
        num_columns=int(b.shape[1]),
        distinct_columns=stats.distinct_columns,
        extra={"blocks_solved": stats.blocks, "reciprocity_error": plan.reciprocity_error},
    )
