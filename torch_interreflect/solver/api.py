"""Infinite-bounce (and n-bounce) interreflection: solve ``(I − F R) E = E0`` for every batch and wavelength.

:func:`solve` (and :func:`solve_with_info`, which also returns a :class:`SolveInfo`) is the public entry point
(DESIGN.md §1): it validates its inputs, picks a method, and calls a custom autograd Function whose backward pass
solves the adjoint system with the same method, so memory stays at a few ``[..., F, L]`` tensors whatever the
number of iterations. :func:`radiance` turns irradiance into
radiance ``L = R E / π``.

Methods (all columns, i.e. batch × wavelength, share one form-factor matrix):

- ``"dense"``: batched Cholesky of the symmetric positive definite form ``I − R^{1/2} G R^{1/2}`` (batched LU of
  ``I − F R`` when ``F`` is not reciprocal), one ``[F, F]`` factorisation per *distinct* reflectance column (a
  grey reflectance needs one for all wavelengths); the factors are reused for the adjoint.
- ``"cg"``: conjugate gradients on the symmetric positive definite form
  ``(I − R^{1/2} G R^{1/2}) w = R^{1/2} A^{1/2} E0`` with ``G = A^{1/2} F A^{-1/2}``; every iteration is one
  GEMM (or SpMM for sparse ``F``) with all still-unconverged columns. Needs reciprocity ``A_i F_ij = A_j F_ji``.
- ``"neumann"``: the Neumann series ``E ← E0 + F R E`` iterated to ``tol``.
- ``"auto"``: a cost model with constants measured on the development machine (see :data:`AUTO_COST`).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from .._checks import as_real_tensor, check_reflectance
from .._deprecation import warn_once
from ..errors import ShapeError
from ..formfactors.operator import FormFactorOperator, FormFactors
from .columns import broadcast_facet_shapes, finish_output, prepare_inputs, to_columns
from .functions import SolveConfig, apply_solve, matmul
from .info import (
    Solution,
    SolveInfo,
    make_info,
    relative_bound_estimate,
    solver_error,
    warn_if_inaccurate,
    warn_if_not_converged,
)
from .krylov import bounce_series
from .method import AUTO_COST, DEFAULT_MAX_ITER, METHODS, choose_method
from .operator import solve_operator
from .plan import SolvePlan, Stats, get_plan

__all__ = ["AUTO_COST", "Solution", "SolveInfo", "radiance", "solve", "solve_with_info"]



def _check_options(method: str, bounces: int | None, tol: float, max_iter: int | None) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {list(METHODS)}; got {method!r}")
    if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
        raise ValueError(f"bounces must be None (infinite) or an integer >= 1; got {bounces!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number; got {tol!r}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"max_iter must be None or an integer >= 1; got {max_iter!r}")


def _check_method(method: str, plan: SolvePlan) -> None:
    if method == "cg" and not plan.reciprocal:
        i, j = plan.worst_pair
        raise ValueError(
            "method='cg' needs reciprocal form factors (A_i F_ij = A_j F_ji); got a relative violation of "
            f"{plan.reciprocity_error:.3g} at facets ({i}, {j}). Use method='dense' or 'neumann'."
        )


def _warn_accuracy(
    info: SolveInfo | None, stats: Stats, method: str, plan: SolvePlan, r_cols: Tensor, tol: float,
    out_dtype: torch.dtype,
) -> None:
    """Warn when the (reported, or a-priori estimated) relative error bound is above ``tol`` (or above
    ``sqrt(eps)`` of the output dtype, whichever is larger)."""
    rmax = float(r_cols.max()) if r_cols.numel() else 0.0
    if info is not None:
        bound = info.relative_error_bound
    else:
        bound = relative_bound_estimate(solver_error(method, stats, r_cols, tol, plan.max_row_sum, plan.num_facets),
                                        plan.closure_error, rmax, plan.max_row_sum)
    warn_if_inaccurate(bound, tol, out_dtype, plan.closure_error, rmax, plan.max_row_sum,
                       f"solve(method={method!r})", stacklevel=5)


def _solve_matrix(
    form_factors: FormFactors,
    reflectance: Any,
    E0: Any,
    bounces: int | None,
    tol: float,
    method: str,
    max_iter: int | None,
    want_info: bool,
) -> tuple[Tensor, SolveInfo | None]:
    """The solve with a stored matrix (validated options)."""
    matrix = form_factors.matrix
    r, e0, shape, out_dtype, drop = prepare_inputs(form_factors.num_facets, matrix.device, reflectance, E0,
                                                   matrix.dtype)
    plan = get_plan(form_factors)  # also checks F for NaN/inf/negatives (cached)
    matrix = matrix.to(r.dtype)
    areas = form_factors.areas.detach().to(r.dtype)
    r_cols, b_cols = to_columns(r, shape), to_columns(e0, shape)
    if bounces is not None:
        x = bounce_series(lambda y: matmul(matrix, y), r_cols, b_cols, bounces)
        info = make_info("series", bounces - 1, True, plan, matrix, areas, r_cols, b_cols, x, Stats()) if (
            want_info) else None
        return finish_output(x, shape, out_dtype, drop), info
    if method == "auto":
        method = choose_method(plan, r_cols.detach(), tol)
    _check_method(method, plan)
    need_grad = torch.is_grad_enabled() and (matrix.requires_grad or r.requires_grad or e0.requires_grad)
    cfg = SolveConfig(
        plan=plan,
        areas=areas,
        method=method,
        tol=float(tol),
        max_iter=int(max_iter if max_iter is not None else DEFAULT_MAX_ITER.get(method, 1)),
        transpose=False,
        keep=bool(need_grad and method == "dense"),
        stats=Stats(),
    )
    x = apply_solve(matrix, r_cols, b_cols, cfg)
    warn_if_not_converged(cfg.stats, f"solve(method={method!r})")
    info = make_info(method, cfg.stats.iterations, cfg.stats.converged, plan, matrix, areas, r_cols, b_cols, x,
                     cfg.stats) if want_info else None
    _warn_accuracy(info, cfg.stats, method, plan, r_cols.detach(), tol, out_dtype)
    return finish_output(x, shape, out_dtype, drop), info


def _dispatch(
    form_factors: Any,
    reflectance: Any,
    E0: Any,
    bounces: int | None,
    tol: float,
    method: str,
    max_iter: int | None,
    want_info: bool,
) -> tuple[Tensor, SolveInfo | None]:
    """Validate the options and dispatch on what the form-factor object can do (:class:`FormFactorOperator`):
    a stored ``matrix`` (with ``info`` for the cached plan) gets the matrix path, anything else the operator path."""
    _check_options(method, bounces, tol, max_iter)
    if not isinstance(form_factors, FormFactorOperator):
        raise TypeError(
            f"form_factors must be a FormFactors (matrix and areas) or implement FormFactorOperator (num_facets, "
            f"dtype, device, areas, matmul, row_sums); got {type(form_factors).__name__}. Wrap a matrix as "
            "FormFactors(matrix, areas)."
        )
    if isinstance(getattr(form_factors, "matrix", None), Tensor) and isinstance(getattr(form_factors, "info", None),
                                                                                 dict):
        return _solve_matrix(form_factors, reflectance, E0, bounces, tol, method, max_iter, want_info)  # type: ignore[arg-type]
    return solve_operator(form_factors, reflectance, E0, bounces=bounces, tol=tol, method=method,
                          max_iter=max_iter, want_info=want_info)


def solve(
    form_factors: FormFactors | FormFactorOperator,
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
            the areas are needed for the symmetric form), or any
            :class:`~torch_interreflect.formfactors.FormFactorOperator`, e.g. a
            :class:`~torch_interreflect.HierarchicalFormFactors` for large scenes (methods ``"auto"`` = ``"cg"``
            and ``"neumann"``; gradients for reflectance and ``E0`` only, the operator gets none).
            ``matrix`` may require grad (dense, or sparse CSR:
            gradient on the stored entries only). Areas are not differentiated (``E`` does not depend on them).
        reflectance: Diffuse reflectance in [0, 1], ``[..., F]`` (grey: the same at every wavelength) or
            ``[..., F, L]``. A tensor whose dim −2 has size F is read as ``[..., F, L]``.
        E0: Direct irradiance in W·m⁻²·nm⁻¹, ``>= 0``, ``[..., F, L]`` broadcastable with the reflectance (e.g.
            ``[F, L]``, ``[B, F, L]``, ``[F, 1]``), or ``[F]`` (read as ``[F, 1]``; with an ``[F]`` reflectance the
            output is ``[F]``).
        bounces: ``None`` (default) for the infinite-bounce solution; ``n ≥ 1`` for the paper's n-bounce
            model, ``E = Σ_{k<n} (F R)^k E0`` (1: direct light only, 2: ``E0 + F R E0``). The finite series is
            computed by ``n − 1`` products and differentiated by autograd through them (memory grows with n).
        tol: Requested relative accuracy of ``E`` (per column, area-weighted norm): iterative methods stop at the
            relative residual ``tol · (1 − r_max ρ)`` that bounds the error by ``tol``. When the error bound is
            above ``tol`` (the form factors' own closure error amplified near ``r = 1``, or float32 rounding beyond
            ``sqrt(eps)``), an :class:`~torch_interreflect.errors.AccuracyWarning` says so.
        method: ``"auto"``, ``"dense"`` (batched Cholesky of the symmetric form; LU without reciprocity),
            ``"cg"`` (conjugate gradients on the symmetric form;
            requires reciprocity ``A_i F_ij = A_j F_ji``) or ``"neumann"`` (series iterated to ``tol``).
            Ignored when ``bounces`` is finite.
        max_iter: Iteration limit of ``cg`` / ``neumann`` (default 10 000 / 100 000). Reaching it issues a
            :class:`~torch_interreflect.errors.ConvergenceWarning` whose ``residual`` attribute is the residual
            reached.
        return_info: Deprecated: use :func:`solve_with_info`. Also return a :class:`SolveInfo`.

    Returns:
        ``E`` in W·m⁻²·nm⁻¹, in the promoted dtype of the inputs (float16/bfloat16 inputs are solved in float32
        and returned in their dtype); ``(E, info)`` when ``return_info`` is True.

    Raises:
        ShapeError: Shapes (facet or wavelength counts) that do not match.
        ValueRangeError: NaN or inf in any input, reflectance outside [0, 1], negative ``E0``, negative form
            factors; in backward, a non-finite upstream gradient.
        SingularSystemError: Reflectance 1 on every facet of a group of facets that is closed within the form
            factors' accuracy (light never leaves).
        DeviceError: Inputs on another device than the form factors.
        TypeError: ``form_factors`` is neither a FormFactors nor a FormFactorOperator.

    Shape:
        - form_factors.matrix: ``[F, F]``
        - reflectance: ``[..., F]`` or ``[..., F, L]``
        - E0: ``[..., F, L]`` (broadcastable), or ``[F]``
        - output: ``broadcast([..., F, L], E0.shape)``; ``[F]`` when reflectance and E0 are ``[F]``

    Example:
        >>> import torch
        >>> from torch_interreflect import FormFactors
        >>> from torch_interreflect.solver import solve
        >>> areas = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
        >>> K = FormFactors(areas.expand(3, 3) / areas.sum(), areas)  # sphere interior: closed
        >>> E = solve(K, torch.full((3,), 0.5, dtype=torch.float64), torch.ones(3, 31, dtype=torch.float64))
        >>> E.shape, round(float(E[0, 0]), 6)  # E0 / (1 - r)
        (torch.Size([3, 31]), 2.0)
    """
    if return_info:
        warn_once(
            "solve.return_info",
            "solve(..., return_info=True) is deprecated: use torch_interreflect.solver.solve_with_info(...), which "
            "returns Solution(E, info)",
        )
        E, info = _dispatch(form_factors, reflectance, E0, bounces, tol, method, max_iter, True)
        return Solution(E, info)  # type: ignore[arg-type]
    return _dispatch(form_factors, reflectance, E0, bounces, tol, method, max_iter, False)[0]


def solve_with_info(
    form_factors: FormFactors | FormFactorOperator,
    reflectance: Tensor,
    E0: Tensor,
    *,
    bounces: int | None = None,
    tol: float = 1e-6,
    method: str = "auto",
    max_iter: int | None = None,
) -> Solution:
    """:func:`solve`, returning ``Solution(E, info)`` with the :class:`SolveInfo` of the solve.

    Args:
        form_factors, reflectance, E0, bounces, tol, method, max_iter: As in :func:`solve`.

    Returns:
        ``Solution(E, info)`` (a named tuple: ``E, info = solve_with_info(...)`` works).

    Shape:
        - output ``E``: as in :func:`solve`

    Example:
        >>> import torch
        >>> from torch_interreflect import FormFactors
        >>> from torch_interreflect.solver import solve_with_info
        >>> areas = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
        >>> K = FormFactors(areas.expand(3, 3) / areas.sum(), areas)
        >>> sol = solve_with_info(K, torch.full((3,), 0.5, dtype=torch.float64), torch.ones(3, dtype=torch.float64))
        >>> sol.E.shape, sol.info.method, sol.info.relative_error_bound < 1e-12
        (torch.Size([3]), 'dense', True)
    """
    E, info = _dispatch(form_factors, reflectance, E0, bounces, tol, method, max_iter, True)
    return Solution(E, info)  # type: ignore[arg-type]


def radiance(E: Tensor, reflectance: Tensor) -> Tensor:
    """Radiance of Lambertian facets, ``L = R E / π`` (paper eq. 58), in W·sr⁻¹·m⁻²·nm⁻¹.

    Args:
        E: Irradiance in W·m⁻²·nm⁻¹, ``[..., F, L]``, or ``[F]`` (with an ``[F]`` reflectance).
        reflectance: ``[..., F]`` (grey) or ``[..., F, L]``, broadcastable with ``E``.

    Returns:
        Radiance, the broadcast shape of ``E`` and the reflectance (as ``[..., F, L]``); ``[F]`` for ``[F]``
        inputs.

    Shape:
        - E: ``[..., F, L]`` or ``[F]``
        - reflectance: ``[..., F]`` or ``[..., F, L]`` (``[F]`` when E is ``[F]``)
        - output: ``[..., F, L]``; ``[F]`` for ``[F]`` inputs

    Example:
        >>> import torch
        >>> from torch_interreflect.solver import radiance
        >>> radiance(torch.full((2, 3), torch.pi), torch.tensor([0.5, 1.0]))[:, 0]
        tensor([0.5000, 1.0000])
    """
    E = as_real_tensor(E, "E")
    reflectance = as_real_tensor(reflectance, "reflectance")
    vector = E.ndim == 1
    if vector and reflectance.shape != E.shape:
        raise ShapeError(f"E of shape [F] = {list(E.shape)} needs a reflectance of the same shape; got "
                         f"{list(reflectance.shape)} (use E of shape [..., F, L] otherwise)")
    if E.ndim < 1:
        raise ShapeError(f"E must have shape [..., F, L] or [F]; got {list(E.shape)}")
    r, e, _ = broadcast_facet_shapes(E.shape[0] if vector else E.shape[-2], reflectance, E)
    check_reflectance(r)
    out = r * e / math.pi
    return out.squeeze(-1) if vector else out
