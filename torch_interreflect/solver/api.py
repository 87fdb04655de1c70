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

import torch
from torch import Tensor

from .._checks import as_real_tensor, check_finite, check_reflectance
from ..errors import ShapeError
from ..formfactors.operator import FormFactorOperator, FormFactors
from .columns import broadcast_facet_shapes, from_columns, to_columns
from .functions import SolveConfig, apply_solve, matmul
from .info import SolveInfo, make_info, warn_if_not_converged
from .method import AUTO_COST, DEFAULT_MAX_ITER, METHODS, choose_method
from .plan import Stats, get_plan

__all__ = ["AUTO_COST", "SolveInfo", "radiance", "solve"]


# ------------------------------------------------------------------------------------ autograd Functions


# ----------------------------------------------------------------------------------------------- checks


# ------------------------------------------------------------------------------------------ method choice


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
        >>> from torch_interreflect.solver import solve
        >>> areas = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
        >>> K = FormFactors(areas.expand(3, 3) / areas.sum(), areas)  # sphere interior: closed
        >>> E = solve(K, torch.full((3,), 0.5, dtype=torch.float64), torch.ones(3, 31, dtype=torch.float64))
        >>> E.shape, round(float(E[0, 0]), 6)  # E0 / (1 - r)
        (torch.Size([3, 31]), 2.0)
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {list(METHODS)}; got {method!r}")
    if bounces is not None and (isinstance(bounces, bool) or not isinstance(bounces, int) or bounces < 1):
        raise ValueError(f"bounces must be None (infinite) or an integer >= 1; got {bounces!r}")
    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive finite number; got {tol!r}")
    if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1):
        raise ValueError(f"max_iter must be None or an integer >= 1; got {max_iter!r}")
    if not isinstance(form_factors, FormFactors):
        if isinstance(form_factors, FormFactorOperator):  # operator path: cg / neumann, no gradient for F
            from .operator import solve_operator

            return solve_operator(form_factors, reflectance, E0, bounces=bounces, tol=tol, method=method,
                                  max_iter=max_iter, return_info=return_info)
        raise TypeError(
            f"form_factors must be a FormFactors (matrix and areas); got {type(form_factors).__name__}. "
            "Wrap a matrix as FormFactors(matrix, areas)."
        )

    matrix = form_factors.matrix
    n = form_factors.num_facets
    reflectance = as_real_tensor(reflectance, "reflectance")
    E0 = as_real_tensor(E0, "E0")
    dtype = matrix.dtype
    if not dtype.is_floating_point:
        raise TypeError(f"form-factor matrix must be floating point; got {dtype}")
    for t in (reflectance, E0):
        if t.dtype.is_floating_point:
            dtype = torch.promote_types(dtype, t.dtype)
    for name, t in (("reflectance", reflectance), ("E0", E0)):
        if t.device != matrix.device:
            raise ValueError(f"{name} is on {t.device} but the form factors are on {matrix.device}")
    r, e0, shape = broadcast_facet_shapes(n, reflectance.to(dtype), E0.to(dtype))
    check_reflectance(r)
    check_finite(e0, "E0", -2)
    plan = get_plan(form_factors)  # also checks F for NaN/inf/negatives (cached)
    if matrix.dtype != dtype:
        matrix = matrix.to(dtype)
    areas = form_factors.areas.detach().to(dtype)
    r_cols = to_columns(r, shape)
    b_cols = to_columns(e0, shape)

    if bounces is not None:
        x = b_cols
        for _ in range(bounces - 1):
            x = b_cols + matmul(matrix, r_cols * x)
        E = from_columns(x, shape)
        if not return_info:
            return E
        info = make_info("series", bounces - 1, True, plan, matrix, areas, r_cols, b_cols, x, Stats())
        return E, info

    if method == "auto":
        method = choose_method(plan, r_cols.detach(), tol)
    if method == "cg" and not plan.reciprocal:
        i, j = plan.worst_pair
        raise ValueError(
            "method='cg' needs reciprocal form factors (A_i F_ij = A_j F_ji); got a relative violation of "
            f"{plan.reciprocity_error:.3g} at facets ({i}, {j}). Use method='dense' or 'neumann'."
        )
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
    E = from_columns(x, shape)
    if not return_info:
        return E
    info = make_info(
        method, cfg.stats.iterations, cfg.stats.converged, plan, matrix, areas, r_cols, b_cols, x, cfg.stats
    )
    return E, info


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
        >>> from torch_interreflect.solver import radiance
        >>> radiance(torch.full((2, 3), torch.pi), torch.tensor([0.5, 1.0]))[:, 0]
        tensor([0.5000, 1.0000])
    """
    E = as_real_tensor(E, "E")
    reflectance = as_real_tensor(reflectance, "reflectance")
    if E.ndim < 2:
        raise ShapeError(f"E must have shape [..., F, L]; got {list(E.shape)}")
    r, e, _ = broadcast_facet_shapes(E.shape[-2], reflectance, E)
    check_reflectance(r)
    return r * e / math.pi
