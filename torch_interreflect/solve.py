"""Infinite-bounce (and n-bounce) interreflection: solve ``(I − F R) E = E0`` for every batch and wavelength.

:func:`solve` is the public entry point (DESIGN.md §1): it validates its inputs, picks a method, and calls a
custom autograd Function whose backward pass solves the adjoint system with the same method, so memory stays
at a few ``[..., F, L]`` tensors whatever the number of iterations. :func:`radiance` turns irradiance into
radiance ``L = R E / π``.

Methods (all columns, i.e. batch × wavelength, share one form-factor matrix):

- ``"dense"``: batched LU of ``I − F R``, one ``[F, F]`` factorisation per *distinct* reflectance column (a
  grey reflectance needs one for all wavelengths); the factors are reused for the adjoint.
- ``"cg"``: conjugate gradients on the symmetric positive definite form
  ``(I − R^{1/2} G R^{1/2}) w = R^{1/2} A^{1/2} E0`` with ``G = A^{1/2} F A^{-1/2}``; every iteration is one
  GEMM (or SpMM for sparse ``F``) with all still-unconverged columns. Needs reciprocity ``A_i F_ij = A_j F_ji``.
- ``"neumann"``: the Neumann series ``E ← E0 + F R E`` iterated to ``tol``.
- ``"auto"``: a cost model with constants measured on the development machine (see :data:`AUTO_COST`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ._solvers import SolvePlan, Stats, get_plan, solve_columns
from .errors import ConvergenceWarning, ShapeError, ValueRangeError
from .kernel import FormFactors

__all__ = ["AUTO_COST", "SolveInfo", "radiance", "solve"]

_METHODS = ("auto", "dense", "cg", "neumann")

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


# ------------------------------------------------------------------------------------ autograd Functions
@dataclass
class _Config:
    plan: SolvePlan
    areas: Tensor
    method: str
    tol: float
    max_iter: int
    transpose: bool
    keep: bool
    stats: Stats

    def adjoint(self) -> _Config:
        return replace(self, transpose=not self.transpose, keep=False, stats=Stats())


class _InterreflectSolve(torch.autograd.Function):
    """``x = (I − F R)⁻¹ b`` (or ``(I − R Fᵀ)⁻¹ b`` when transposed) for ``[F, N]`` columns.

    Gradients (adjoint method, DESIGN.md §1), with ``γ`` the solution of the transposed system for the
    upstream gradient ``g``:

    - not transposed, ``γ = (I − R Fᵀ)⁻¹ g``: ``∂b = γ``, ``∂r = (Fᵀ γ) ⊙ x``, ``∂F = γ (r ⊙ x)ᵀ``;
    - transposed, ``γ = (I − F R)⁻¹ g``: ``∂b = γ``, ``∂r = γ ⊙ (Fᵀ x)``, ``∂F = x (r ⊙ γ)ᵀ``.

    ``∂F`` is summed over columns; for a sparse ``F`` it is computed on the stored entries only. When a graph
    is requested for the backward (double backward), the adjoint solve calls this Function again.
    """

    @staticmethod
    def forward(matrix: Tensor, r: Tensor, b: Tensor, cfg: _Config) -> tuple[Tensor, ...]:  # type: ignore[override]
        x, factors = solve_columns(
            matrix.detach(),
            cfg.plan,
            cfg.areas,
            r.detach(),
            b.detach(),
            transpose=cfg.transpose,
            method=cfg.method,
            tol=cfg.tol,
            max_iter=cfg.max_iter,
            keep_factors=cfg.keep,
            stats=cfg.stats,
        )
        return (x, *factors)

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: tuple[Tensor, ...]) -> None:
        matrix, r, _, cfg = inputs
        x, *factors = output
        ctx.cfg = cfg
        if factors:
            ctx.mark_non_differentiable(*factors)
        ctx.save_for_backward(matrix, r, x, *factors)

    @staticmethod
    def backward(ctx: Any, gx: Tensor, *_: Any) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        matrix, r, x, *factors = ctx.saved_tensors
        cfg: _Config = ctx.cfg
        need_f, need_r, need_b = ctx.needs_input_grad[:3]
        if not (need_f or need_r or need_b):
            return None, None, None, None
        acfg = cfg.adjoint()
        if torch.is_grad_enabled():  # create_graph=True: the adjoint solve itself must be differentiable
            gam = _apply(matrix, r, gx, acfg)
        else:
            gam, _ = solve_columns(
                matrix.detach(),
                cfg.plan,
                cfg.areas,
                r.detach(),
                gx.detach(),
                transpose=acfg.transpose,
                method=cfg.method,
                tol=cfg.tol,
                max_iter=cfg.max_iter,
                factors=factors or None,
                stats=acfg.stats,
            )
        _warn_if_not_converged(acfg.stats, "adjoint (backward) solve")
        grad_f = grad_r = None
        if not cfg.transpose:
            if need_r:
                grad_r = _ft_mm(matrix, gam) * x
            if need_f:
                grad_f = _outer(matrix, gam, r * x)
        else:
            if need_r:
                grad_r = gam * _ft_mm(matrix, x)
            if need_f:
                grad_f = _outer(matrix, x, r * gam)
        return grad_f, grad_r, (gam if need_b else None), None


def _apply(matrix: Tensor, r: Tensor, b: Tensor, cfg: _Config) -> Tensor:
    return _InterreflectSolve.apply(matrix, r, b, cfg)[0]


def _ft_mm(matrix: Tensor, y: Tensor) -> Tensor:
    """``Fᵀ y``."""
    if matrix.layout == torch.strided:
        return matrix.mT @ y
    return matrix.detach().t() @ y


def _outer(matrix: Tensor, a: Tensor, c: Tensor) -> Tensor:
    """``a cᵀ`` summed over columns, dense or sampled at the stored entries of a sparse ``matrix``."""
    if matrix.layout == torch.strided:
        return a @ c.mT
    return torch.sparse.sampled_addmm(matrix.detach().to_sparse_csr(), a, c.mT, beta=0.0)


class _CsrMatmul(torch.autograd.Function):
    """``F @ y`` for a sparse CSR ``F`` whose gradient lives on its stored entries only."""

    @staticmethod
    def forward(matrix: Tensor, y: Tensor) -> Tensor:  # type: ignore[override]
        return matrix.detach() @ y.detach()

    @staticmethod
    def setup_context(ctx: Any, inputs: tuple[Any, ...], output: Tensor) -> None:
        ctx.save_for_backward(*inputs)

    @staticmethod
    def backward(ctx: Any, g: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        matrix, y = ctx.saved_tensors
        gm = _outer(matrix, g, y) if ctx.needs_input_grad[0] else None
        gy = _ft_mm(matrix, g) if ctx.needs_input_grad[1] else None
        return gm, gy


def _mm(matrix: Tensor, y: Tensor) -> Tensor:
    if matrix.layout == torch.strided:
        return matrix @ y
    return _CsrMatmul.apply(matrix, y)


def _warn_if_not_converged(stats: Stats, what: str) -> None:
    if not stats.converged:
        w = ConvergenceWarning(
            f"{what} did not converge within max_iter={stats.iterations} iterations: relative residual "
            f"{stats.residual:.3g} reached (raise max_iter or tol)"
        )
        w.residual = stats.residual  # type: ignore[attr-defined]
        w.iterations = stats.iterations  # type: ignore[attr-defined]
        warnings.warn(w, stacklevel=3)


# ----------------------------------------------------------------------------------------------- checks
def _as_float(x: Any, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        try:
            x = torch.as_tensor(np.asarray(x))
        except Exception as exc:
            raise TypeError(f"{name} must be a tensor; got {type(x).__name__}") from exc
    if x.is_complex():
        raise TypeError(f"{name} must be real; got dtype {x.dtype}")
    return x


def _where(t: Tensor, flat_index: int, facet_dim: int) -> str:
    coord = np.unravel_index(flat_index, tuple(t.shape))
    facet = int(coord[facet_dim])
    rest = [int(c) for i, c in enumerate(coord) if i != facet_dim % t.ndim]
    return f"facet {facet}" + (f" (other indices {rest})" if any(rest) else "")


def _check_finite(t: Tensor, name: str, facet_dim: int) -> None:
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        k = int(torch.nonzero(bad.reshape(-1))[0])
        raise ValueRangeError(
            f"{name} must be finite; got {float(t.reshape(-1)[k])} at {_where(t, k, facet_dim)} "
            f"({int(bad.sum())} non-finite values)"
        )


def _check_reflectance(r: Tensor) -> None:
    """``r`` is ``[..., F, L]``."""
    _check_finite(r, "reflectance", -2)
    if r.numel() == 0:
        return
    flat = r.detach().reshape(-1)
    hi, lo = int(flat.argmax()), int(flat.argmin())
    if float(flat[hi]) > 1:
        raise ValueRangeError(f"reflectance must lie in [0, 1]; got max {float(flat[hi]):.6g} at {_where(r, hi, -2)}")
    if float(flat[lo]) < 0:
        raise ValueRangeError(f"reflectance must lie in [0, 1]; got min {float(flat[lo]):.6g} at {_where(r, lo, -2)}")


def _shapes(n: int, reflectance: Tensor, e0: Tensor) -> tuple[Tensor, Tensor, torch.Size]:
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
        shape = torch.broadcast_shapes(r.shape, e.shape)
    except RuntimeError as exc:
        raise ShapeError(
            f"reflectance {list(r.shape)} (as [..., F, L]) and E0 {list(e.shape)} do not broadcast: "
            f"wavelength counts L = {r.shape[-1]} vs {e.shape[-1]}, batch dims {list(r.shape[:-2])} vs "
            f"{list(e.shape[:-2])}"
        ) from exc
    return r, e, shape


def _to_columns(t: Tensor, shape: torch.Size) -> Tensor:
    """``[..., F, L]`` (broadcast to ``shape``) → ``[F, N]``; differentiable (expand sums the gradient)."""
    n = shape[-2]
    return t.expand(shape).movedim(-2, 0).reshape(n, -1)


def _from_columns(x: Tensor, shape: torch.Size) -> Tensor:
    n = shape[-2]
    return x.reshape(n, *shape[:-2], shape[-1]).movedim(0, -2)


# ------------------------------------------------------------------------------------------ method choice
def _estimate_cg_iterations(rho: float, tol: float, size: int) -> int:
    if rho >= 1:
        return size
    kappa = (1 + rho) / (1 - rho)
    return max(1, min(size, math.ceil(0.5 * math.sqrt(kappa) * math.log(2 / tol))))


def _choose_method(plan: SolvePlan, r_cols: Tensor, tol: float) -> str:
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
    k_cols = int(torch.unique(r_cols, dim=1).shape[1]) if n > 1 else 1
    rho = float(r_cols.max()) * plan.max_row_sum
    gemm_rate = max(cost["gemm_min"], cost["gemm_peak"] * n / (n + cost["gemm_half"]))
    t_dense = t_cg = 0.0
    for c in sizes:
        lu_rate = cost["lu_peak"] * c / (c + cost["lu_half"])
        t_dense += k_cols * ((2 / 3) * c**3 / lu_rate + cost["lu_each"]) + 2 * c * c * n / gemm_rate
        t_dense += cost["call_overhead"]
        k = max(1.0, cost["cg_iter_factor"] * _estimate_cg_iterations(rho, tol, c))
        if plan.is_sparse:
            prod = 2 * plan.nnz * (c / max(plan.num_facets, 1)) * n / cost["spmm_rate"]
        else:
            prod = 2 * c * c * n / gemm_rate
        t_cg += (k + 2) * (prod + c * n / cost["elem_rate"] + cost["iter_overhead"]) + cost["call_overhead"]
    return "dense" if t_dense <= t_cg else "cg"


# ---------------------------------------------------------------------------------------------- public
def solve(
    form_factors: FormFactors,
    reflectance: Tensor,
    E0: Tensor,
    *,
    bounces: int | None = None,
    tol: float = 1e-6,
    method: str = "auto",
    max_iter: int | None = None,
    return_info: bool = False,
) -> Tensor | tuple[Tensor, SolveInfo]:
    """Irradiance after ``bounces`` reflections: ``E = E0 + F R E`` (paper eq. 57), per batch and wavelength.

    Solves ``(I − F R) E = E0`` independently for every column (batch element × wavelength) with one shared
    form-factor matrix. Only what the scene needs is solved: facets that exchange no light keep ``E = E0``,
    independent groups of facets (connected components of the pattern of ``F``, cached per matrix) are solved
    separately, facets with reflectance 0 cost nothing, and iterative methods stop each column when it has
    converged. Gradients (reflectance, ``E0`` and the form-factor values) come from the adjoint system, solved
    by the same method: memory is a few ``[..., F, L]`` tensors, never the iterations.

    Args:
        form_factors: The scene's :class:`~torch_interreflect.FormFactors` (a plain Tensor is not accepted:
            the areas are needed for the symmetric form), or a
            :class:`~torch_interreflect.HierarchicalFormFactors` for large scenes (methods ``"auto"`` = ``"cg"``
            and ``"neumann"``; gradients for reflectance and ``E0`` only, the operator gets none).
            ``matrix`` may require grad (dense, or sparse CSR:
            gradient on the stored entries only). Areas are not differentiated (``E`` does not depend on them).
        reflectance: Diffuse reflectance in [0, 1], ``[..., F]`` (grey: the same at every wavelength) or
            ``[..., F, L]``. A tensor whose dim −2 has size F is read as ``[..., F, L]``.
        E0: Direct irradiance in W·m⁻²·nm⁻¹, ``[..., F, L]`` broadcastable with the reflectance (e.g.
            ``[F, L]``, ``[B, F, L]``, ``[F, 1]``), or ``[F]``.
        bounces: ``None`` (default) for the infinite-bounce solution; ``n ≥ 1`` for the paper's n-bounce
            model, ``E = Σ_{k<n} (F R)^k E0`` (1: direct light only, 2: ``E0 + F R E0``). The finite series is
            computed by ``n − 1`` products and differentiated by autograd through them (memory grows with n).
        tol: Relative residual at which iterative methods stop (per column).
        method: ``"auto"``, ``"dense"`` (batched LU), ``"cg"`` (conjugate gradients on the symmetric form;
            requires reciprocity ``A_i F_ij = A_j F_ji``) or ``"neumann"`` (series iterated to ``tol``).
            Ignored when ``bounces`` is finite.
        max_iter: Iteration limit of ``cg`` / ``neumann`` (default 10 000 / 100 000). Reaching it issues a
            :class:`~torch_interreflect.errors.ConvergenceWarning` whose ``residual`` attribute is the residual
            reached.
        return_info: Also return a :class:`SolveInfo`.

    Returns:
        ``E`` in W·m⁻²·nm⁻¹, or ``(E, info)`` when ``return_info`` is True.

    Raises:
        ShapeError: Shapes (facet or wavelength counts) that do not match.
        ValueRangeError: NaN or inf in any input, reflectance outside [0, 1], negative form factors.
        SingularSystemError: Reflectance 1 on every facet of a closed group of facets (light never leaves).
        TypeError: ``form_factors`` is not a FormFactors.

    Shape:
        - form_factors.matrix: ``[F, F]``
        - reflectance: ``[..., F]`` or ``[..., F, L]``
        - E0: ``[..., F, L]`` (broadcastable), or ``[F]``
        - output: ``broadcast([..., F, L], E0.shape)``

    Example:
        >>> import torch
        >>> from torch_interreflect import FormFactors
        >>> from torch_interreflect.solve import solve
        >>> areas = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
        >>> K = FormFactors(areas.expand(3, 3) / areas.sum(), areas)  # sphere interior: closed
        >>> E = solve(K, torch.full((3,), 0.5, dtype=torch.float64), torch.ones(3, 31, dtype=torch.float64))
        >>> E.shape, round(float(E[0, 0]), 6)  # E0 / (1 - r)
        (torch.Size([3, 31]), 2.0)
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {list(_METHODS)}; got {method!r}")
    if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
        raise ValueError(f"bounces must be None (infinite) or an integer >= 1; got {bounces!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number; got {tol!r}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"max_iter must be None or an integer >= 1; got {max_iter!r}")
    if not isinstance(form_factors, FormFactors):
        from .hierarchical import HierarchicalFormFactors

        if isinstance(form_factors, HierarchicalFormFactors):  # operator path: cg / neumann, no gradient for F
            from ._operator_solve import solve_operator

            return solve_operator(form_factors, reflectance, E0, bounces=bounces, tol=tol, method=method,
                                  max_iter=max_iter, return_info=return_info)
        raise TypeError(
            f"form_factors must be a FormFactors (matrix and areas); got {type(form_factors).__name__}. "
            "Wrap a matrix as FormFactors(matrix, areas)."
        )

    matrix = form_factors.matrix
    n = form_factors.num_facets
    reflectance = _as_float(reflectance, "reflectance")
    E0 = _as_float(E0, "E0")
    dtype = matrix.dtype
    if not dtype.is_floating_point:
        raise TypeError(f"form-factor matrix must be floating point; got {dtype}")
    for t in (reflectance, E0):
        if t.dtype.is_floating_point:
            dtype = torch.promote_types(dtype, t.dtype)
    for name, t in (("reflectance", reflectance), ("E0", E0)):
        if t.device != matrix.device:
            raise ValueError(f"{name} is on {t.device} but the form factors are on {matrix.device}")
    r, e0, shape = _shapes(n, reflectance.to(dtype), E0.to(dtype))
    _check_reflectance(r)
    _check_finite(e0, "E0", -2)
    plan = get_plan(form_factors)  # also checks F for NaN/inf/negatives (cached)
    if matrix.dtype != dtype:
        matrix = matrix.to(dtype)
    areas = form_factors.areas.detach().to(dtype)
    r_cols = _to_columns(r, shape)
    b_cols = _to_columns(e0, shape)

    if bounces is not None:
        x = b_cols
        for _ in range(bounces - 1):
            x = b_cols + _mm(matrix, r_cols * x)
        E = _from_columns(x, shape)
        if not return_info:
            return E
        info = _make_info("series", bounces - 1, True, plan, matrix, areas, r_cols, b_cols, x, Stats())
        return E, info

    if method == "auto":
        method = _choose_method(plan, r_cols.detach(), tol)
    if method == "cg" and not plan.reciprocal:
        i, j = plan.worst_pair
        raise ValueError(
            "method='cg' needs reciprocal form factors (A_i F_ij = A_j F_ji); got a relative violation of "
            f"{plan.reciprocity_error:.3g} at facets ({i}, {j}). Use method='dense' or 'neumann'."
        )
    need_grad = torch.is_grad_enabled() and (matrix.requires_grad or r.requires_grad or e0.requires_grad)
    cfg = _Config(
        plan=plan,
        areas=areas,
        method=method,
        tol=float(tol),
        max_iter=int(max_iter if max_iter is not None else DEFAULT_MAX_ITER.get(method, 1)),
        transpose=False,
        keep=bool(need_grad and method == "dense"),
        stats=Stats(),
    )
    x = _apply(matrix, r_cols, b_cols, cfg)
    _warn_if_not_converged(cfg.stats, f"solve(method={method!r})")
    E = _from_columns(x, shape)
    if not return_info:
        return E
    info = _make_info(
        method, cfg.stats.iterations, cfg.stats.converged, plan, matrix, areas, r_cols, b_cols, x, cfg.stats
    )
    return E, info


def _make_info(
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


def radiance(E: Tensor, reflectance: Tensor) -> Tensor:
    """Radiance of Lambertian facets, ``L = R E / π`` (paper eq. 58), in W·sr⁻¹·m⁻²·nm⁻¹.

    Args:
        E: Irradiance in W·m⁻²·nm⁻¹, ``[..., F, L]``.
        reflectance: ``[..., F]`` (grey) or ``[..., F, L]``, broadcastable with ``E``.

    Returns:
        Radiance, the broadcast shape of ``E`` and the reflectance (as ``[..., F, L]``).

    Shape:
        - E: ``[..., F, L]``
        - reflectance: ``[..., F]`` or ``[..., F, L]``
        - output: ``[..., F, L]``

    Example:
        >>> import torch
        >>> from torch_interreflect.solve import radiance
        >>> radiance(torch.full((2, 3), torch.pi), torch.tensor([0.5, 1.0]))[:, 0]
        tensor([0.5000, 1.0000])
    """
    E = _as_float(E, "E")
    reflectance = _as_float(reflectance, "reflectance")
    if E.ndim < 2:
        raise ShapeError(f"E must have shape [..., F, L]; got {list(E.shape)}")
    r, e, _ = _shapes(E.shape[-2], reflectance, E)
    _check_reflectance(r)
    return r * e / math.pi
