"""The method planner of ``method="auto"``: a cost model of the dense and CG solvers (:data:`AUTO_COST`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .plan import SolvePlan

__all__ = ["AUTO_COST", "DEFAULT_MAX_ITER", "DENSE_MAX_FACETS", "METHODS", "choose_method", "distinct_columns",
           "estimate_cg_iterations"]



METHODS = ("auto", "dense", "cg", "neumann")


#: Default iteration limits (finite, generous): CG needs ~``0.5·sqrt((1+r)/(1−r))·ln(2/tol)`` iterations
#: (≈ 330 at r = 0.999, tol = 1e-6), the Neumann series ``ln(tol)/ln(r)`` (≈ 14 000 at r = 0.999).
DEFAULT_MAX_ITER = {"cg": 10_000, "neumann": 100_000}


#: Cost model used by ``method="auto"``: seconds ≈ flops / rate + overheads, with rates measured on the
#: development machine (2 shared CPU cores, torch 2.13, float64, uncontended; float32 roughly doubles every
#: rate, so the crossover barely moves):
#:
#: - GEMM ``[F, F] @ [F, N]``: 15 / 46 / 84 GFLOP/s at N = 1 / 31 / 248 (F = 1024) → ``gemm_peak·N/(N + gemm_half)``,
#:   at least ``gemm_min``; 2048³ GEMM: 89 GFLOP/s (float32: 139).
#: - batched ``lu_factor`` ``[K, F, F]``: 7 / 31 / 41–56 GFLOP/s at F = 64 / 256 / 1024 (counting (2/3)F³)
#:   → ``lu_peak·F/(F + lu_half)``, plus ``lu_each`` seconds per matrix.
#: - CG: ``iter_overhead`` seconds of Python per iteration plus ~8 elementwise passes over ``[F, N]``
#:   (``elem_rate`` elements/s); iterations = ``cg_iter_factor`` × the bound ``0.5·sqrt(κ)·ln(2/tol)``
#:   (measured on the closed box room of benchmarks/solver.py at r_max = 0.9: 10 iterations, bound 32).
#: - SpMM (sparse ``F``): ``spmm_rate`` flop/s counting 2·nnz·N.
#:
#: Measured crossover (``OMP_NUM_THREADS=1 python benchmarks/solver.py --calibrate``: float64, r_max = 0.9,
#: closed box room, forward time, dense vs cg): with every column distinct (K = N) CG wins from F ≈ 16 for
#: N = 248 (F = 40: 8.1 vs 1.9 ms; F = 144: 93 vs 6.6 ms) and from F ≈ 64 for N = 31 (1.5 vs 1.1 ms); with one
#: grey column (K = 1) dense wins for N ≥ 31 up to at least F = 576 (N = 248: 37 vs 142 ms) and CG wins for
#: N = 1 from F ≈ 256 (2.2 vs 1.0 ms). The model picks the faster method in 28 of the 30 calibration cases
#: (the two misses within 2×).
AUTO_COST: dict[str, float] = {
    "gemm_peak": 9.6e10,
    "gemm_half": 35.0,
    "gemm_min": 1.5e10,
    "lu_peak": 5.5e10,
    "lu_half": 100.0,
    "lu_each": 1e-5,
    "elem_rate": 1.2e8,  # [F, N] entries per second for the ~8 elementwise passes of one CG iteration
    "iter_overhead": 6e-5,
    "call_overhead": 2e-4,
    "cg_iter_factor": 0.35,
    "spmm_rate": 1.5e9,
}


#: Largest component the dense method factors when ``F`` is not reciprocal (CG unavailable) in ``auto``.
DENSE_MAX_FACETS = 4096


def estimate_cg_iterations(rho: float, tol: float, size: int) -> int:
    """CG iterations to reach the relative error ``tol`` (residual ``tol·(1 − ρ)``) at ``ρ = r_max·max row sum``."""
    if rho >= 1:
        return size
    kappa = (1 + rho) / (1 - rho)
    return max(1, min(size, math.ceil(0.5 * math.sqrt(kappa) * math.log(2 / (tol * (1 - rho))))))


def distinct_columns(r_cols: Tensor) -> int:
    """How many distinct columns ``r_cols [F, N]`` holds (the dense method's factorisations), counted on one fixed
    projection per column: two different columns that project alike would be counted once, a slip of the cost model
    only. ``torch.unique(dim=1)`` took 0.2-0.45 ms on 100 columns of 300 rows, the projection 0.04 ms."""
    n = int(r_cols.shape[1])
    if n <= 1:
        return n
    w = torch.linspace(1.0, 2.0, r_cols.shape[0], dtype=torch.float64, device=r_cols.device).sqrt()
    return int(torch.unique(w @ r_cols.detach().to(torch.float64)).numel())


def choose_method(plan: SolvePlan, r_cols: Tensor, tol: float) -> str:
    """Pick ``dense`` or ``cg`` by the cost model :data:`AUTO_COST` (``neumann`` only when ``F`` is not
    reciprocal and a component is too large for ``dense``).

    dense ≈ Σ_components K·((2/3)c³/lu_rate(c) + lu_each) + 2c²N/gemm_rate(N) (K distinct reflectance columns,
    N columns); cg ≈ Σ_components k·(2c²N/gemm_rate(N) + c·N/elem_rate + iter_overhead), k the iteration
    estimate for ``ρ = r_max·max row sum``.
    """
    sizes = [c.size for c in plan.components]
    if not sizes:
        return "dense"
    if not plan.reciprocal:
        return "dense" if max(sizes) <= DENSE_MAX_FACETS else "neumann"
    if plan.is_sparse and max(sizes) > DENSE_MAX_FACETS:
        return "cg"
    cost = AUTO_COST
    n = int(r_cols.shape[1])
    k_cols = distinct_columns(r_cols)
    rho = float(r_cols.detach().max()) * plan.max_row_sum
    gemm_rate = max(cost["gemm_min"], cost["gemm_peak"] * n / (n + cost["gemm_half"]))
    t_dense = t_cg = 0.0
    for c in sizes:
        lu_rate = cost["lu_peak"] * c / (c + cost["lu_half"])
        t_dense += k_cols * ((2 / 3) * c**3 / lu_rate + cost["lu_each"]) + 2 * c * c * n / gemm_rate
        t_dense += cost["call_overhead"]
        k = max(1.0, cost["cg_iter_factor"] * estimate_cg_iterations(rho, tol, c))
        if plan.is_sparse:
            prod = 2 * plan.nnz * (c / max(plan.num_facets, 1)) * n / cost["spmm_rate"]
        else:
            prod = 2 * c * c * n / gemm_rate
        t_cg += (k + 2) * (prod + c * n / cost["elem_rate"] + cost["iter_overhead"]) + cost["call_overhead"]
    return "dense" if t_dense <= t_cg else "cg"
